"""Seam-aware 2D fills and blurs of ERP images: columns wrap at the seam, rows continue across the poles."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    pass
from panoworld.core.shapes import check_shape


def erp_pad(img: np.ndarray, pad_x: int, pad_y: int = 0) -> np.ndarray:
    """Pad an ERP image (H, W[, C]) so that it continues over the sphere: columns wrap around (pad_x each side),
    rows mirror across the poles rotated by 180 degrees of longitude (pad_y each side; needs an even W)."""
    H, W = img.shape[:2]
    if pad_x > W or pad_y > H or (pad_y and W % 2):
        raise ValueError(f"{img.shape=}: cannot pad by {pad_x=}, {pad_y=} (need pad_x <= W, pad_y <= H, even W)")
    if pad_y:
        top = np.roll(img[:pad_y][::-1], W // 2, axis=1)
        bottom = np.roll(img[H - pad_y :][::-1], W // 2, axis=1)
        img = np.concatenate([top, img, bottom], axis=0)
    if pad_x:
        img = np.concatenate([img[:, W - pad_x :], img, img[:, :pad_x]], axis=1)
    return img


def erp_gaussian_blur(img: np.ndarray, sigma: float, *, across_poles: bool) -> np.ndarray:
    """img (h, w[, C]) float32 blurred by a Gaussian of sigma pixels, columns wrapped at the seam and, across_poles
    (w even), rows continued across the poles (erp_pad); the same shape back."""
    h, w = img.shape[:2]
    pad = int(np.ceil(3 * sigma)) + 1
    px, py = min(pad, w), (min(pad, h) if across_poles and w % 2 == 0 else 0)
    return cv2.GaussianBlur(erp_pad(img, px, py), (0, 0), sigma)[py:py + h, px:px + w]


def erp_inpaint(img: np.ndarray, mask: np.ndarray, *, radius: float = 3.0, pad_frac: float = 0.25) -> np.ndarray:
    """cv2.inpaint (Telea) of an ERP image (H, W, 3) uint8 or (H, W) uint16/float where mask (H, W) is True,
    seam-aware: the image is padded by pad_frac * W wrapped columns and mirrored polar rows, so fills continue
    across the left/right border and the poles. Pixels outside the mask are returned unchanged.

    Float images are quantised to 16 bits over the range of their unmasked values (OpenCV's Telea gives garbage
    on float32 input).
    """
    mask = np.asarray(mask, bool)
    check_shape("mask", mask, "H W", dims=check_shape("img", img, "H W" if img.ndim == 2 else "H W *"))
    if not mask.any():
        return img.copy()
    if mask.all():
        raise ValueError("erp_inpaint: the mask covers the whole image; nothing to fill from")
    if img.dtype.kind == "f":
        if img.ndim != 2:
            raise ValueError(f"{img.shape=} {img.dtype=}: float images must be single-channel (H, W)")
        lo, hi = float(img[~mask].min()), float(img[~mask].max())
        scale = 65535.0 / (hi - lo) if hi > lo else 1.0
        q = np.rint((np.clip(img, lo, hi) - lo) * scale).astype(np.uint16)
        out = erp_inpaint(q, mask, radius=radius, pad_frac=pad_frac).astype(np.float64) / scale + lo
        return np.where(mask, out, img).astype(img.dtype)
    if not (img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3) and not (
        img.dtype in (np.uint8, np.uint16) and img.ndim == 2
    ):
        raise ValueError(f"{img.shape=} {img.dtype=} but expected (H, W, 3) uint8 or (H, W) uint8/uint16/float")
    H, W = mask.shape
    px = max(1, min(W, int(round(pad_frac * W))))
    py = min(H, max(2, int(np.ceil(radius)) + 1)) if W % 2 == 0 else 0
    src = erp_pad(img, px, py)
    m = erp_pad(mask.astype(np.uint8), px, py)
    out = cv2.inpaint(np.ascontiguousarray(src), m, radius, cv2.INPAINT_TELEA)[py : py + H, px : px + W]
    return np.where(mask[..., None] if img.ndim == 3 else mask, out, img)
