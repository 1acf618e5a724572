"""Upright poses along a path, step lengths, exact clearance against the scene mesh, pose validation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panoworld.geometry.navmesh import NavMesh
from panoworld.io.trajectory import path_indices


def yaw_of_path(positions: np.ndarray, *, closed: bool, sigma_frames: float = 3.0) -> np.ndarray:
    """Heading (N,) about the up axis relative to the first pose's heading, smoothed, with yaw[0] = 0."""
    from scipy.ndimage import gaussian_filter1d

    p = np.asarray(positions, np.float64)
    d = (np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0)) if closed else np.gradient(p, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 0], d[:, 1]))
    if sigma_frames > 0:
        heading = gaussian_filter1d(heading, sigma_frames, mode="wrap" if closed else "nearest")
    return heading - heading[0]


def path_yaw(positions: np.ndarray, paths: list[dict], *, closed: bool) -> np.ndarray:
    """yaw_of_path over each path of a multi-path trajectory (pose ranges [start, stop); a path starting after pose 0
    leaves from its predecessor `from`, pose 0 unless given)."""
    yaw = np.zeros(len(positions))
    for p in paths:
        idx = path_indices(p)
        if len(idx) < 2:  # a single pose (a capture frame alone): the initial heading
            continue
        y = yaw_of_path(positions[idx], closed=closed and len(paths) == 1)
        yaw[p["start"]:p["stop"]] = y[len(idx) - (p["stop"] - p["start"]):]
    return yaw


def poses_from_positions(positions: np.ndarray, yaw: np.ndarray | None = None, camera_y: float = 0.0) -> np.ndarray:
    """Upright world_from_cam poses (N, 4, 4) at x,z positions (N, 2), height camera_y, yaw (N,) about -Y.

    Yaw psi turns the camera's forward axis (+z) towards +x: forward = (sin psi, 0, cos psi).
    """
    positions = np.asarray(positions, np.float64)
    n = len(positions)
    yaw = np.zeros(n) if yaw is None else np.asarray(yaw, np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = c, s, -s, c
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = positions[:, 0], camera_y, positions[:, 1]
    return T


def step_lengths(poses: np.ndarray) -> np.ndarray:
    """Distances (N - 1,) between consecutive camera centres of poses (N, 4, 4)."""
    return np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)


# ---------------------------------------------------------------- clearance against a mesh


CLEARANCE_CAP_M = 0.5
"""Clearances are measured exactly up to max(this, 2 x agent radius) and reported as that cap beyond it."""


def clearance_cap(agent_radius: float) -> float:
    return max(CLEARANCE_CAP_M, 2.0 * agent_radius)


def mesh_clearance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, cap: float = np.inf) -> np.ndarray:
    """Exact distance (N,) from points (N, 3) to the nearest triangle of a mesh (V, 3) / (F, 3), at most cap.

    Triangles whose bounding box is farther than cap from the points' bounding box are dropped first (a finite
    cap makes dense ERP meshes fast). The nearest vertex bounds each answer from above; the rest are bucketed
    by bounding-sphere radius (powers of two) with a KD-tree on their centroids per bucket, so only triangles
    whose sphere can be nearer are tested exactly (trimesh.triangles.closest_point).
    """
    import trimesh
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64).reshape(-1, 3)
    vertices = np.asarray(vertices)
    faces = np.asarray(faces).reshape(-1, 3)
    best = np.full(len(points), float(cap))
    if len(faces) == 0 or len(points) == 0:
        return best
    if np.isfinite(cap):
        lo, hi = points.min(axis=0) - cap, points.max(axis=0) + cap
        # Outcodes: a face's bounding box misses the box iff its three vertices share an outside bit.
        code = np.zeros(len(vertices), np.uint8)
        for k in range(3):
            code |= (vertices[:, k] < lo[k]).astype(np.uint8) << (2 * k)
            code |= (vertices[:, k] > hi[k]).astype(np.uint8) << (2 * k + 1)
        fc = code[faces]
        faces = faces[(fc[:, 0] & fc[:, 1] & fc[:, 2]) == 0]
        if len(faces) == 0:
            return best
    tri = vertices[faces].astype(np.float64)
    cen = tri.mean(axis=1)
    rad = np.sqrt(((tri - cen[:, None]) ** 2).sum(-1).max(axis=1))
    used = np.zeros(len(vertices), bool)
    used[faces.reshape(-1)] = True
    d_vertex = cKDTree(vertices[used].astype(np.float64)).query(points, distance_upper_bound=cap)[0]
    best = np.minimum(best, d_vertex)
    bucket = np.floor(np.log2(np.maximum(rad, 1e-6))).astype(int)
    for b in np.unique(bucket):
        idx = np.flatnonzero(bucket == b)
        cands = cKDTree(cen[idx]).query_ball_point(points, best + rad[idx].max())
        pi = np.repeat(np.arange(len(points)), [len(c) for c in cands])
        if len(pi) == 0:
            continue
        fi = idx[np.concatenate([np.asarray(c, int) for c in cands])]
        q = trimesh.triangles.closest_point(tri[fi], points[pi])
        np.minimum.at(best, pi, np.linalg.norm(q - points[pi], axis=1))
    return best


# ---------------------------------------------------------------- validation


@dataclass
class PoseIssue:
    index: int
    reasons: list[str]


def validate_poses(
    poses: np.ndarray, nav: NavMesh, clearance: np.ndarray, *, agent_radius: float, skip: tuple[int, ...] = ()
) -> list[PoseIssue]:
    """Every pose that leaves the walkable area, flies outside the agent's height band, or is closer than
    agent_radius to the mesh (clearance (N,) from mesh_clearance). Poses in `skip` are not checked."""
    xz = poses[:, [0, 2], 3]
    inside = nav.contains(xz)
    dist_out = np.where(inside, 0.0, -nav.clearance(xz))
    height = nav.floor_y - poses[:, 1, 3]
    step = nav.agent.get("step_height_m", 0.0)
    top = nav.agent.get("band_top_m", np.inf)
    issues = []
    for i in range(len(poses)):
        if i in skip:
            continue
        r = []
        if clearance[i] < agent_radius:
            r.append(f"clearance {clearance[i]:.3f} m < agent radius {agent_radius:.3f} m")
        if not inside[i]:
            r.append(f"outside the walkable NavMesh by {dist_out[i]:.3f} m")
        if not step < height[i] < top:
            r.append(f"camera {height[i]:.3f} m above the floor, outside ({step:.2f}, {top:.2f}) m")
        if r:
            issues.append(PoseIssue(i, r))
    return issues


def _ranges(idx: list[int]) -> str:
    out, k = [], 0
    while k < len(idx):
        j = k
        while j + 1 < len(idx) and idx[j + 1] == idx[j] + 1:
            j += 1
        out.append(str(idx[k]) if j == k else f"{idx[k]}-{idx[j]}")
        k = j + 1
    return ",".join(out)


def format_issues(issues: list[PoseIssue], n_poses: int) -> str:
    """One line naming every invalid pose, grouped by kind of problem."""
    groups: dict[str, list[tuple[int, str]]] = {}
    for it in issues:
        for r in it.reasons:
            key = r.split(" ", 1)[0] if not r.startswith("outside") else "outside"
            groups.setdefault(key, []).append((it.index, r))
    parts = []
    for key, items in groups.items():
        idx = [i for i, _ in items]
        worst = items[0][1]
        label = {"clearance": "too close to the mesh", "outside": "outside the walkable NavMesh", "camera": "outside the agent height band"}[key]
        parts.append(f"{label}: poses {_ranges(idx)} (e.g. pose {items[0][0]}: {worst})")
    return f"{len(issues)} of {n_poses} poses are invalid; " + "; ".join(parts)


# ---------------------------------------------------------------- files
