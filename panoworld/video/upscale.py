"""x2 upscaling of ERP video frames after generation: seam-aware Lanczos, Real-ESRGAN (learned), nearest for depth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from panoworld.core.shapes import check_shape
from panoworld.video.erp_fill import erp_pad

SCALE = 2


METHODS = ("none", "lanczos", "realesrgan")


def lanczos_x2(rgb: np.ndarray, *, pad: int = 8) -> np.ndarray:
    """ERP frame (H, W, 3) uint8 -> (2H, 2W, 3) with cv2.INTER_LANCZOS4 on a sphere-padded copy (wrapped columns,
    mirrored polar rows), so the left/right borders stay continuous."""
    check_shape("rgb", rgb, "H W 3", dtype=np.uint8)
    H, W = rgb.shape[:2]
    pad = min(pad, H, W)
    big = cv2.resize(erp_pad(rgb, pad, pad if W % 2 == 0 else 0), None, fx=SCALE, fy=SCALE,
                     interpolation=cv2.INTER_LANCZOS4)
    py = SCALE * pad if W % 2 == 0 else 0
    return np.ascontiguousarray(big[py : py + SCALE * H, SCALE * pad : SCALE * (pad + W)])


def nearest_x2(depth: np.ndarray) -> np.ndarray:
    """Depth (H, W) -> (2H, 2W), each pixel repeated 2x2 (0 = unknown stays unknown, no mixed depths at edges)."""
    check_shape("depth", depth, "H W")
    return np.repeat(np.repeat(depth, SCALE, axis=0), SCALE, axis=1)


class FrameUpscaler:
    """Upscales frames one at a time by the chosen method; the Real-ESRGAN model is loaded once."""

    def __init__(self, method: str, *, weights: Path | str | None = None, tile: int = 0, device: str = "cpu",
                 dtype: str = "float32"):
        if str(method) not in METHODS:
            raise ValueError(f"upscale method {method!r} not one of {METHODS}")
        self.method = str(method)
        self.scale = 1 if self.method == "none" else SCALE
        self._model = None
        self._kw = {"tile": tile, "device": device, "dtype": dtype}
        if self.method == "realesrgan":
            from panoworld.models.rrdbnet import load_rrdbnet

            self._model = load_rrdbnet(weights)
            if self._model.scale != SCALE:
                raise ValueError(f"{weights}: a x{self._model.scale} Real-ESRGAN model; the video stage needs x{SCALE} "
                                 "(RealESRGAN_x2plus.pth)")

    def rgb(self, frame: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (sH, sW, 3) uint8."""
        if self.method == "none":
            return frame
        if self.method == "lanczos":
            return lanczos_x2(frame)
        from panoworld.models.rrdbnet import upscale_frames

        return upscale_frames(self._model, frame[None], **self._kw)[0]

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) -> (sH, sW) by nearest neighbour."""
        return depth if self.scale == 1 else nearest_x2(depth)
