"""The poses stage's choices: COLMAP render type, matcher, mapper, alignment and the COLMAP options (cheap to import)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from panoworld.core.params import param


class RenderType(enum.StrEnum):
    """How COLMAP sees the panoramas (pycolmap.panorama.PanoRenderType)."""

    SPHERICAL = "spherical"
    """Native EQUIRECTANGULAR camera model on the full panoramas (fastest)."""
    PERSPECTIVE_OVERLAPPING = "perspective_overlapping"
    """A rig of 12 overlapping 90-degree pinhole views per panorama, converted back to one ERP camera."""
    PERSPECTIVE_NON_OVERLAPPING = "perspective_non_overlapping"
    """A rig of 4 horizontal cube faces per panorama, converted back to one ERP camera."""


class Matcher(enum.StrEnum):
    """Which image pairs COLMAP matches."""

    SEQUENTIAL = "sequential"
    """Each frame with its 10 successors (and quadratic overlap): for videos."""
    EXHAUSTIVE = "exhaustive"
    """All pairs: slow for long videos, robust for short or shuffled ones."""


class Alignment(enum.StrEnum):
    """How estimated poses are brought into the canonical frame of the planned trajectory."""

    SIM3 = "sim3"
    """Similarity (scale, rotation, translation) fitted to the planned trajectory: metric scale and canonical frame."""
    SE3 = "se3"
    """Rigid fit to the planned trajectory, keeping the estimator's own (metric) scale."""
    NONE = "none"
    """Keep the estimator's frame (PanoVGGT: camera 0 at the origin, its own metric scale)."""


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
    ba_iterations: int = param(1, ge=1)
    """global: rounds of bundle adjustment and track filtering after global positioning (COLMAP's default is 3);
    the retriangulation's refinement runs after them either way. On a smooth planned path more rounds cost time and
    do not move the poses."""
    max_tracks: int = param(1000, ge=1)
    """global: the longest tracks kept for global positioning and its bundle adjustments (COLMAP keeps all); the
    retriangulation afterwards triangulates every match again, so the model keeps all its points."""
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


