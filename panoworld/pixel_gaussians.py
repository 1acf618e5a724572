"""Per-pixel Gaussians of the source panorama, and the test of which observations of other frames it already explains."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from panoworld.conventions import erp_pixel_from_dir, invert_pose
from panoworld.fusion_params import FusionParams
from panoworld.gaussians import (
    ContextSource,
    FusionResult,
    Gaussians,
    Observations,
    bbox_extent,
    frame_observations,
    gaussians_from_cov,
    voxel_fusion,
)


def pole_thinning(height: int, width: int) -> np.ndarray:
    """(H, W) bool: ERP pixels kept when each row keeps every k-th column, k = the largest power of two <= 1 / cos(lat)
    (at most W / 8), so kept pixels are 0.5-1x as wide as tall on the sphere (about 78 % of all pixels)."""
    lat = (np.arange(height) + 0.5) / height * np.pi - np.pi / 2
    k = 2 ** np.floor(np.log2(1.0 / np.maximum(np.cos(lat), 1e-6)))
    k = np.minimum(k, max(width // 8, 1)).astype(int)
    return (np.arange(width)[None, :] % k[:, None]) == 0


def pixel_gaussians(rgb: np.ndarray, depth: np.ndarray, world_from_cam: np.ndarray, params: FusionParams,
                    *, thin_poles: bool = True) -> Gaussians:
    """One Gaussian per valid pixel of an ERP frame (rgb (H, W, 3), depth (H, W) metres, pose (4, 4)).

    Each is the pixel's surface footprint (frame_observations' parallelogram covariance) times params.scale_factor,
    flat along the surface normal (at least min_scale * voxel_size thick); with thin_poles, rows near the poles keep
    every k-th pixel (pole_thinning) with a k times wider footprint along the row.
    """
    h, w = depth.shape
    obs = frame_observations(rgb, depth, world_from_cam, params)
    steps = obs.steps
    if thin_poles:
        keep_px = pole_thinning(h, w).ravel()
        k_row = np.bincount(np.arange(h).repeat(w), weights=1.0 - keep_px, minlength=h)
        k_row = w / np.maximum(w - k_row, 1)  # columns per kept pixel in each row
        sel = keep_px[obs.pixels.numpy()]
        obs = obs.subset(torch.from_numpy(sel))
        k = torch.from_numpy(k_row[obs.pixels.numpy() // w])
        steps = obs.steps.clone()
        steps[:, 0] *= k[:, None]
    cov = torch.einsum("mki,mkj->mij", steps, steps) / 12.0
    return gaussians_from_cov(obs.points, cov, obs.colors, params, max_scale_m=np.inf)


class SourceVisibility:
    """What the source view sees: its ERP depth (H, W) metres (0/NaN/inf = unknown) and world_from_cam (4, 4)."""

    def __init__(self, depth: np.ndarray, world_from_cam: np.ndarray, tol: float):
        self.depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan).astype(np.float64)
        self.cam_from_world = invert_pose(np.asarray(world_from_cam, np.float64))
        self.tol = tol

    def _lookup(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance of world points (M, 3) from the source, the source's depth along their ray (NaN = none))."""
        p = np.einsum("ij,mj->mi", self.cam_from_world[:3, :3], points) + self.cam_from_world[:3, 3]
        dist = np.linalg.norm(p, axis=1)
        h, w = self.depth.shape
        u, v = erp_pixel_from_dir(p / np.maximum(dist, 1e-12)[:, None], h, w)
        j = np.mod(np.floor(u).astype(np.int64), w)
        i = np.clip(np.floor(v).astype(np.int64), 0, h - 1)
        return dist, self.depth[i, j]

    def explained(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool for world points (M, 3): on the source's visible surfaces or in front of them (within tol of its
        depth, relative, or nearer), i.e. the per-pixel Gaussians already stand for them or they would float in
        front of what the source saw. Points behind the source's surfaces or where it has no depth are not."""
        dist, d_src = self._lookup(points)
        with np.errstate(invalid="ignore"):
            return np.isfinite(d_src) & (dist <= d_src * (1.0 + self.tol))

    def poking_through(self, g: Gaussians, reach: float = 3.0) -> np.ndarray:
        """(N,) bool: Gaussians behind the source's surface by less than reach x their largest scale, i.e. whose
        splat reaches through a surface the source saw (inside a wall, they show only as a smear on it)."""
        dist, d_src = self._lookup(np.asarray(g.means, np.float64))
        with np.errstate(invalid="ignore"):
            return np.isfinite(d_src) & (dist - d_src < reach * np.asarray(g.scales).max(1))

    def keep_unexplained(self, obs: Observations) -> Observations:
        return obs.subset(torch.from_numpy(~self.explained(obs.points.numpy())))


def merge_gaussians(parts: list[Gaussians]) -> Gaussians:
    """One Gaussians set from several (same SH degree)."""
    return Gaussians(*(np.concatenate([getattr(g, f) for g in parts]) for f in
                       ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")))


def source_anchored_fusion(frames: ContextSource, params: FusionParams, *, source_height: int = 0, tol: float = 0.03,
                           source_scale: float | None = None, unseen_voxel_size: float = 0.0, thin_poles: bool = True,
                           progress: bool = False) -> FusionResult:
    """Per-pixel Gaussians of the source view (video frame 0, at source_height rows; 0 = as the other frames) plus
    voxel fusion of what the other frames see that the source does not (SourceVisibility with tolerance tol) in voxels
    of unseen_voxel_size (0 = params.voxel_size), less those poking through the source's surfaces: the capture point keeps the input's full detail, the rest of the
    room is fused as before. source_scale: the per-pixel Gaussians' scale_factor (None = params.scale_factor). Without
    frame 0 among the frames it is plain voxel fusion."""
    if not frames.indices or frames.indices[0] != 0:
        return voxel_fusion(frames, params, progress=progress)
    src = replace(frames, height=min(source_height or frames.height, frames.stored_height))
    rgb, depth, pose = src.frame(0)
    pix_params = params if source_scale is None else replace(params, scale_factor=source_scale)
    pix = pixel_gaussians(rgb, depth, pose, pix_params, thin_poles=thin_poles)
    rest = replace(frames, rgb_paths=frames.rgb_paths[1:], depth_paths=frames.depth_paths[1:],
                   world_from_cam=frames.world_from_cam[1:], indices=frames.indices[1:])
    if not len(rest):
        return FusionResult(pix, len(pix), 0, 0, bbox_extent(pix.means), params.voxel_size)
    vox_params = replace(params, voxel_size=unseen_voxel_size) if unseen_voxel_size > 0 else params
    vis = SourceVisibility(depth, pose, tol)
    fused = voxel_fusion(rest, vox_params, progress=progress, select=vis.keep_unexplained)
    poking = vis.poking_through(fused.gaussians)
    g = merge_gaussians([pix, fused.gaussians.subset(~poking)])
    return FusionResult(g, fused.num_observations + len(pix), fused.num_voxels, fused.num_pruned + int(poking.sum()),
                        bbox_extent(g.means), vox_params.voxel_size, num_source=len(pix))
