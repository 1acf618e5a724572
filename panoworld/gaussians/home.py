"""One Gaussian scene over a home: every capture panorama as per-pixel Gaussians at its registered pose (each surface
from the panorama that sees it nearest), the video frames voxel-fused where no panorama sees."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from panoworld.core.conventions import erp_dirs, invert_pose, transform_points
from panoworld.gaussians.fusion import ContextSource
from panoworld.gaussians.fusion_params import SourcePixelParams
from panoworld.gaussians.pixel import SourceVisibility, fuse_unseen, merge_gaussians, pixel_gaussians
from panoworld.geometry.panoramas import nearest_source
from panoworld.geometry.resize import rgbd_at_height
from panoworld.io.gaussian_set import FusionResult


class SourcesVisibility:
    """What any of several source panoramas sees (SourceVisibility of each, or-ed)."""

    def __init__(self, sources: list[SourceVisibility]):
        self.sources = sources
        self.centres = np.array([invert_pose(s.cam_from_world)[:3, 3] for s in sources])

    def explained(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool: SourceVisibility.explained by any source. The sources are asked nearest to the points' mean
        first, each only about the points the nearer ones left (most of a frame is explained by one source)."""
        explained = np.zeros(len(points), bool)
        if not len(points):
            return explained
        rest = np.arange(len(points))
        for k in np.argsort(np.linalg.norm(self.centres - points.mean(0), axis=1)):
            e = self.sources[k].explained(points[rest])
            explained[rest[e]] = True
            rest = rest[~e]
            if not len(rest):
                break
        return explained

    def poking_through(self, g) -> np.ndarray:
        """(N,) bool: SourceVisibility.poking_through of any source."""
        return np.logical_or.reduce([s.poking_through(g) for s in self.sources])


def home_anchored_fusion(frames: ContextSource, sources: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
                         params: SourcePixelParams, *, progress: bool = False) -> FusionResult:
    """Per-pixel Gaussians of every source {NAME: (rgb (H, W, 3), depth (H, W) metres (0 = unknown), world_from_cam)}
    at most params.source_height rows (0 = as given), a pixel kept only when no other source sees its surface from
    nearer (geometry.panoramas.nearest_source: no doubled surfaces), plus voxel fusion of what the frames see that no
    source does (SourceVisibility of each, tolerance params.source_tol) in voxels of params.unseen_voxel_size (0 =
    params.voxel_size), less those poking through a surface a source saw: source_anchored_fusion of a single panorama,
    over several."""
    names = list(sources)
    tol = params.source_tol
    small = {n: rgbd_at_height(sources[n][0], sources[n][1], params.source_height) for n in names}
    depths = {n: small[n][1] for n in names}
    poses = {n: np.asarray(sources[n][2], np.float64) for n in names}
    pix_params = replace(params, scale_factor=params.source_scale)
    parts = []
    for k, n in enumerate(names):
        rgb, depth = small[n]
        h, w = depth.shape
        pts = transform_points(poses[n], erp_dirs(h, w, np.float64).reshape(-1, 3) * depth.reshape(-1, 1))
        keep = nearest_source(k, pts, names, depths, poses, tol=tol).reshape(h, w)
        parts.append(pixel_gaussians(rgb, np.where(keep & (depth > 0), depth, 0.0).astype(np.float32), poses[n],
                                     pix_params))
    pix = merge_gaussians(parts)
    seen = SourcesVisibility([SourceVisibility(depths[n], poses[n], tol) for n in names])
    return fuse_unseen(pix, frames, seen, params, unseen_voxel_size=params.unseen_voxel_size, progress=progress)
