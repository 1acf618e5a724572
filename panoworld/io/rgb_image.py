"""RGB frame files of the video and conditions artifacts: PNG (lossless) or JPEG of a quality; their encoder and decoder."""

from __future__ import annotations

import enum

import numpy as np

from panoworld.io.png import decode_png, encode_png


class RgbFormat(enum.StrEnum):
    PNG = "png"
    """Lossless (about 1 MB per 720x1440 frame)."""
    JPEG = "jpeg"
    """Lossy at the writer's quality, full-resolution chroma (quality 95: about 0.3 MB per 720x1440 frame, ~45 dB PSNR
    to the PNG; bench/bench_artifact_size.py)."""


SUFFIX = {RgbFormat.PNG: ".png", RgbFormat.JPEG: ".jpg"}


def rgb_file_name(index: int, fmt: RgbFormat | str) -> str:
    """The file name of frame index in a directory of fmt frames (000012.png, 000012.jpg)."""
    return f"{index:06d}{SUFFIX[RgbFormat(fmt)]}"


def encode_rgb(rgb: np.ndarray, fmt: RgbFormat | str, *, quality: int = 95, compression: int = 1) -> bytes:
    """Bytes of an RGB (H, W, 3) uint8 image as fmt: PNG of zlib compression, or baseline JPEG of quality with 4:4:4
    chroma (4:2:0 costs ~3 dB at quality 95 on coloured edges for ~20 % less size; progressive JPEG: the same pixels
    once decoded and ~5 % smaller, but 6x the encoding and 3x the decoding time)."""
    import cv2

    if RgbFormat(fmt) == RgbFormat.PNG:
        return encode_png(rgb, compression=compression)
    if not 1 <= quality <= 100:
        raise ValueError(f"JPEG {quality=} must be in [1, 100]")
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [
        cv2.IMWRITE_JPEG_QUALITY, quality, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
    if not ok:
        raise RuntimeError(f"JPEG encoding failed for an image of shape {rgb.shape}")
    return buf.tobytes()


def decode_rgb(data: bytes, *, what: str = "image") -> np.ndarray:
    """Inverse of encode_rgb (either format): RGB (H, W, 3) uint8; ValueError naming `what` when it is not one."""
    img = decode_png(data, what=what)
    if img.ndim != 3 or img.dtype != np.uint8:
        raise ValueError(f"{what}: {img.shape} {img.dtype} image but expected RGB uint8")
    return img


def image_format_of(data: bytes) -> str:
    """'jpeg' or 'png' from the magic bytes (the Foxglove CompressedImage format string)."""
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    raise ValueError("neither a JPEG nor a PNG")
