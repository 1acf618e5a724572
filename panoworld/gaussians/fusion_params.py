"""Settings of the voxel-fusion backend, importable without torch (stage modules build their CLI from them)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from panoworld.core.params import param


class Confidence(enum.StrEnum):
    """Non-learned per-pixel confidence w of the voxel-fusion backend."""

    UNIFORM = "uniform"
    """w = 1: every pixel one vote (views closer to a surface sample it more densely and so dominate)."""
    AREA = "area"
    """w = footprint area of the pixel on the surface: surface-area-weighted moments, every view counts equally."""
    RESOLUTION = "resolution"
    """w = cos(grazing angle) / depth^2: frontal, close (sharper) observations dominate."""


@dataclass(kw_only=True)
class FusionParams:
    """Settings of the non-learned voxel-fusion backend."""

    voxel_size: float = param(0.02, gt=0)
    """Voxel edge length in metres (the paper's epsilon)."""
    per_voxel: int = param(1, ge=1)
    """Gaussians per occupied voxel, K in {1, 2, 4, 8}: the voxel's samples are split in two along each of its
    log2(K) principal axes and every non-empty part becomes one Gaussian."""
    confidence: Confidence = Confidence.RESOLUTION
    """Per-pixel confidence weight used in the fusion."""
    min_points: int = param(1, ge=1)
    """Prune voxels (and sub-voxel parts) observed by fewer pixels than this."""
    scale_factor: float = param(1.6, gt=0)
    """Gaussian standard deviation = scale_factor * sqrt(eigenvalue of the fused covariance)."""
    min_scale: float = param(0.05, gt=0)
    """Lower clamp of every Gaussian scale, as a fraction of voxel_size (keeps surfels from being degenerate)."""
    max_scale: float = param(1.0, gt=0)
    """Upper clamp of every Gaussian scale, as a multiple of voxel_size."""
    opacity: float = param(0.98, gt=0, le=1)
    """Opacity of every emitted Gaussian."""
    min_cos: float = param(0.08, ge=0, le=1)
    """Drop pixels seen at grazing angles with |cos| below this (depth discontinuities, flying pixels)."""
    max_depth: float = param(0.0, ge=0)
    """Drop pixels with depth beyond this many metres (0 = keep all)."""

    def check(self) -> None:
        if not self.voxel_size > 0:
            raise ValueError(f"voxel_size={self.voxel_size} but expected > 0")
        if self.per_voxel not in (1, 2, 4, 8):
            raise ValueError(f"per_voxel={self.per_voxel} but expected one of 1, 2, 4, 8")
        if self.min_points < 1:
            raise ValueError(f"min_points={self.min_points} but expected >= 1")
        if not 0 < self.min_scale <= self.max_scale:
            raise ValueError(f"min_scale={self.min_scale}, max_scale={self.max_scale} but expected 0 < min <= max")
        if not 0 < self.opacity < 1:
            raise ValueError(f"opacity={self.opacity} but expected in (0, 1)")
