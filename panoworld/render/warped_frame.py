"""The frame a pose renders from the scene mesh (RGB, depth, mask): what the conditions stage writes and the video
generator is conditioned on; produced by panoworld.render.rasterize, written and read back by panoworld.conditions.warp."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class WarpedFrame:
    """One pose rendered from the mesh: what the generator is conditioned on."""

    rgb: np.ndarray
    """(H, W, 3) uint8 interpolated vertex colour; 0 where mask is False."""
    depth: np.ndarray
    """(H, W) float32 ray distance in metres; 0 where mask is False."""
    mask: np.ndarray
    """(H, W) bool: True = the pixel sees a valid face; False = no geometry or a stretched face (to be generated)."""
