"""Depth PNGs (uint16 millimetres) of the conditions, video and poses artifacts: one decoder, one policy.

Policy: 0 in the PNG is "unknown" and stays 0.0 in the float32 metres it decodes to (as in depth.npy and everywhere
else in memory: a depth <= 0 or non-finite is no depth)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.core.conventions import DEPTH_PNG_SCALE, depth_to_mm
from panoworld.core.errors import InputError


def metres_from_png(raw: np.ndarray, scale: float = DEPTH_PNG_SCALE, *, what: str = "depth PNG") -> np.ndarray:
    """Decoded uint16 (H, W) PNG values -> float32 metres (0 = unknown); InputError naming `what` otherwise."""
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
        shape = None if raw is None else f"{raw.shape} {raw.dtype}"
        raise InputError(f"{what}: not a single-channel uint16 depth PNG (got {shape})")
    return raw.astype(np.float32) * np.float32(scale)


def read_depth_png(path: Path | str, scale: float = DEPTH_PNG_SCALE) -> np.ndarray:
    """A uint16 depth PNG file -> float32 metres (H, W), 0 = unknown."""
    import cv2

    return metres_from_png(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), scale, what=str(path))


DEPTH_PNG_COMPRESSION = 4
"""zlib level of the depth PNGs (Up filter): on the demo's 720x1440 depth ~24 % smaller than level 1 for ~6 ms more
per frame; level 5 saves 4 % more for 1.5x the time, level 6 8 % more for 3x (bench/bench_png.py)."""


def encode_depth_png(mm: np.ndarray) -> bytes:
    """uint16 millimetres (H, W) -> the bytes of its depth PNG."""
    from panoworld.io.png import encode_png

    return encode_png(mm, compression=DEPTH_PNG_COMPRESSION)


def write_depth_png(path: Path | str, depth_m: np.ndarray) -> None:
    """Depth (H, W) metres -> uint16 PNG in millimetres (unknown (0, NaN, inf) -> 0, clipped at 65.535 m)."""
    from panoworld.core.shapes import check_shape

    check_shape("depth_m", depth_m, "H W")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(encode_depth_png(depth_to_mm(depth_m)))
