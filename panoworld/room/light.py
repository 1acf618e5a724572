"""Light in linear RGB: a gain applied to an sRGB image with its chroma kept."""

from __future__ import annotations

import numpy as np


def apply_gain(face: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Multiply a uint8 sRGB image (..., 3) by a light factor (...) in linear RGB (chroma kept)."""
    lin = (face.astype(np.float32) / 255.0) ** 2.2 * gain[..., None]
    return np.clip(np.rint(255.0 * np.clip(lin, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.uint8)
