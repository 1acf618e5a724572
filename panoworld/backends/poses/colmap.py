"""colmap: COLMAP panorama SfM (pycolmap), Sim(3)-aligned to the planned trajectory for metric scale and canonical frame."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from panoworld.backends import register
from panoworld.choices import Matcher, RenderType
from panoworld.params import param


class Mapper(enum.StrEnum):
    GLOBAL = "global"
    """COLMAP's global mapper (GLOMAP): rotation averaging, global positioning, one bundle adjustment."""
    INCREMENTAL = "incremental"
    """COLMAP's incremental mapper: registers frames one by one with repeated bundle adjustment (slower)."""


@dataclass(kw_only=True)
class ColmapOptions:
    """COLMAP settings, sized for a sequential panoramic video on a few CPU cores."""

    render_type: RenderType = RenderType.SPHERICAL
    """Native equirectangular camera (spherical) or rigs of perspective views (fallback for hard cases)."""
    matcher: Matcher = Matcher.SEQUENTIAL
    """Which frame pairs are matched."""
    overlap: int = param(10, ge=1)
    """sequential: each frame is matched with this many successors (plus successors 2^k further: quadratic overlap)."""
    mapper: Mapper = Mapper.GLOBAL
    """spherical: how the matched frames become a model."""
    max_image_size: int = param(1024, ge=0)
    """spherical: SIFT runs on frames downscaled to at most this width (0 = as stored); keypoints are scaled back, so
    the model stays in the video's pixel coordinates."""
    max_features: int = param(2048, ge=1)
    """spherical: SIFT features per frame."""
    upsample_features: bool = False
    """spherical: start SIFT's pyramid at the 2x upsampled frame (COLMAP's default; ~3x the extraction time). Always
    on for frames narrower than 640 px, where the plain pyramid finds too few features."""
    num_threads: int = param(-1, ge=-1)
    """CPU threads (-1 = all)."""
    seed: int = 0
    """Random seed of RANSAC and the mapper."""


def estimate(job):
    from panoworld.poses import colmap_estimate

    o: ColmapOptions = job.options
    return colmap_estimate(job.video.rgb, job.planned, render_type=o.render_type, matcher=o.matcher, sfm=o,
                           alignment=job.align)


register("poses", "colmap", estimate, options=ColmapOptions, key="colmap", needs_plan=True)
