"""How well a home's Gaussian scene reproduces each capture panorama at its registered pose."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from panoworld.io.splat_ply import read_gaussians_ply
from panoworld.render.erp import render_erp
from panoworld.render.metrics import psnr


def capture_psnr(gaussians_ply: Path, captures: dict[str, np.ndarray], panoramas: dict[str, np.ndarray], *,
                 height: int = 256) -> dict[str, float]:
    """{NAME: PSNR dB} of the Gaussians rendered (anti-aliased ERP renderer) at each capture pose world_from_cam
    against that panorama (RGB uint8) area-downsampled to height x 2 height."""
    g = read_gaussians_ply(gaussians_ply)
    out = {}
    for n, pose in captures.items():
        ref = cv2.resize(panoramas[n], (2 * height, height), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        img = np.clip(np.asarray(render_erp(g, pose, height, 2 * height).rgb, np.float32), 0, 1)
        out[n] = psnr(img, ref, data_range=1.0)
    return out
