"""Several registered panoramas: which one sees a surface point from nearest."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import erp_pixel_from_dir, invert_pose, transform_points


def erp_pixel_index(pts_cam: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) (M,) of the ERP pixels (height, width) the camera-frame points (M, 3) lie in the direction of."""
    u, v = erp_pixel_from_dir(pts_cam, height, width)
    return np.clip(np.floor(v).astype(int), 0, height - 1), np.floor(u).astype(int) % width


def depth_along(depth: np.ndarray, pts_cam: np.ndarray) -> np.ndarray:
    """(M,) the ERP depth (H, W) of the pixel in the direction of each camera-frame point (M, 3)."""
    return depth[erp_pixel_index(pts_cam, *depth.shape)]


def nearest_source(k: int, pts_world: np.ndarray, names: list[str], depths: dict[str, np.ndarray],
                   world_from_cam: dict[str, np.ndarray], *, tol: float = 0.03) -> np.ndarray:
    """(M,) bool for surface points (M, 3) seen by panorama names[k]: no other panorama j sees the same surface (its
    depth along the ray agrees within tol in log range) from nearer (ties: the lower index keeps it)."""
    # ranges as each other panorama's are computed (through its camera frame), so two panoramas at one pose tie
    r_k = np.linalg.norm(transform_points(invert_pose(world_from_cam[names[k]]), pts_world), axis=1)
    keep = np.ones(len(pts_world), bool)
    for j, other in enumerate(names):
        if j == k:
            continue
        at = np.flatnonzero(keep)  # each panorama tests the points still kept, its depth looked up where it is nearer
        # those about as near to it (a margin over the rounding of the test below), before the exact test
        near = np.linalg.norm(pts_world[at] - world_from_cam[other][:3, 3], axis=1) <= r_k[at] * (1.0 + 1e-6) + 1e-9
        at = at[near]
        p = transform_points(invert_pose(world_from_cam[other]), pts_world[at])
        r_j = np.linalg.norm(p, axis=1)
        nearer = (r_j < r_k[at]) | ((r_j == r_k[at]) & (j < k))
        at, p, r_j = at[nearer], p[nearer], r_j[nearer]
        d_j = depth_along(np.asarray(depths[other], np.float64), p)
        seen = np.isfinite(d_j) & (d_j > 0) & (np.abs(np.log(np.maximum(r_j, 1e-6) / np.maximum(d_j, 1e-6))) < tol)
        keep[at[seen]] = False
    return keep
