"""Images for the report: read, shrink, colour-map and embed as compressed data URIs."""

from __future__ import annotations

import base64
import html
from pathlib import Path

import cv2
import numpy as np

JPEG_QUALITY = 80
TURBO = cv2.COLORMAP_TURBO


def read_rgb(path: Path, max_width: int | None = None) -> np.ndarray | None:
    """(H, W, 3) uint8 RGB of an image file, shrunk to max_width (aspect kept); None when missing or unreadable."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR) if Path(path).is_file() else None
    if img is None:
        return None
    return shrink(img[..., ::-1], max_width)


def read_gray(path: Path, max_width: int | None = None) -> np.ndarray | None:
    """(H, W) uint8 (or uint16 for 16-bit PNGs) of an image file; None when missing or unreadable."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if Path(path).is_file() else None
    if img is None:
        return None
    if img.ndim == 3:
        img = img[..., 0]
    return shrink(img, max_width, nearest=True)


def shrink(img: np.ndarray, max_width: int | None, nearest: bool = False) -> np.ndarray:
    """img resized so its width is at most max_width (area filter, or nearest for masks and labels)."""
    if max_width is None or img.shape[1] <= max_width:
        return img
    h = max(1, round(img.shape[0] * max_width / img.shape[1]))
    return cv2.resize(img, (max_width, h), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def data_uri(img: np.ndarray, fmt: str = "jpeg", quality: int = JPEG_QUALITY) -> str:
    """An RGB (H, W, 3) or grey (H, W) uint8 image as a data: URI (JPEG for photos, PNG for masks and plots)."""
    if img.dtype != np.uint8:
        raise ValueError(f"{img.dtype=} but expected uint8")
    bgr = img[..., ::-1] if img.ndim == 3 else img
    if fmt == "jpeg":
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(bgr), [cv2.IMWRITE_JPEG_QUALITY, quality])
    elif fmt == "png":
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(bgr), [cv2.IMWRITE_PNG_COMPRESSION, 6])
    else:
        raise ValueError(f"fmt={fmt!r} but expected 'jpeg' or 'png'")
    if not ok:
        raise ValueError(f"could not encode a {img.shape} image as {fmt}")
    return f"data:image/{fmt};base64,{base64.b64encode(buf.tobytes()).decode('ascii')}"


def colormap(values: np.ndarray, lo: float, hi: float, valid: np.ndarray | None = None) -> np.ndarray:
    """(H, W) float values mapped through the turbo colour map over [lo, hi] to (H, W, 3) RGB; invalid -> black."""
    t = np.clip((np.asarray(values, np.float32) - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = cv2.applyColorMap((t * 255).astype(np.uint8), TURBO)[..., ::-1].copy()
    if valid is not None:
        rgb[~valid] = 0
    return rgb


def depth_image(path: Path, max_width: int) -> tuple[np.ndarray, float, float]:
    """A depth.npy (H, W) ray distance read every k-th pixel to at most max_width wide and turbo-mapped over its
    2nd-98th percentile -> (RGB (h, w, 3), lo, hi); invalid (0, inf, NaN) black. OSError / ValueError when unreadable."""
    depth = np.load(path, mmap_mode="r")
    step = max(1, int(np.ceil(depth.shape[1] / max_width)))
    depth = np.asarray(depth[::step, ::step], np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    lo, hi = (np.percentile(depth[valid], [2, 98]) if valid.any() else (0.0, 1.0))
    return colormap(depth, float(lo), float(hi), valid), float(lo), float(hi)


def colormap_css(n: int = 9) -> str:
    """A CSS linear-gradient of the turbo colour map (left = low), for scale bars."""
    lut = cv2.applyColorMap(np.linspace(0, 255, n).astype(np.uint8)[None], TURBO)[0, :, ::-1]
    stops = ", ".join(f"rgb({r},{g},{b})" for r, g, b in lut)
    return f"linear-gradient(to right, {stops})"


def rgb_hex(rgb) -> str:
    r, g, b = (int(c) for c in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"


def colors_for(values: np.ndarray, lo: float, hi: float) -> list[str]:
    """Hex colours of 1-D values on the turbo map over [lo, hi]."""
    rgb = colormap(np.asarray(values, np.float32)[None], lo, hi)[0]
    return [rgb_hex(c) for c in rgb]


def scale_bar(lo: float, hi: float, unit: str) -> str:
    """HTML of a colour scale bar labelled lo .. hi."""
    return (f'<div class="scale"><span>{lo:.2f} {html.escape(unit)}</span>'
            f'<div class="bar" style="background:{colormap_css()}"></div><span>{hi:.2f} {html.escape(unit)}</span></div>')
