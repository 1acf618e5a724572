"""Artifact and user-file readers of depth: the panorama, provided depth files (npy, EXR, 16-bit PNG), the depth artifact."""

from __future__ import annotations

import enum
from pathlib import Path

import cv2
import numpy as np

from panoworld.core.errors import InputError
from panoworld.core.limits import check_image_size, depth_plane, exr_header, load_npy
from panoworld.io.images import read_exr, read_image


class DepthKind(enum.StrEnum):
    """What a monocular depth model predicts for a perspective view."""

    RELATIVE = "relative"
    """Affine-invariant inverse depth (disparity up to an unknown scale and shift), e.g. Depth Anything V2."""
    METRIC = "metric"
    """Metric z-depth along the optical axis, up to a small per-view scale error."""


def read_panorama(path: Path, notes: list[str] | None = None) -> np.ndarray:
    """Read an ERP panorama -> RGB uint8 (H, W, 3); InputError if unreadable or not 2:1.

    Grayscale, RGBA (alpha dropped), 16-bit (scaled to 8 bit) and EXIF-rotated JPEGs (orientation applied) are
    accepted; what was converted is appended to notes.
    """
    path = Path(path)
    notes = [] if notes is None else notes
    img = read_image(path, cv2.IMREAD_UNCHANGED, what="panorama")
    gray = img.ndim == 2 or img.shape[2] == 1
    if path.suffix.lower() in (".jpg", ".jpeg") and img.dtype == np.uint8:
        # IMREAD_UNCHANGED ignores the EXIF orientation; IMREAD_COLOR applies it (same decoder otherwise).
        oriented = cv2.imread(str(path), cv2.IMREAD_COLOR)
        plain = img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        if oriented is not None and (oriented.shape != plain.shape or not np.array_equal(oriented, plain)):
            img = oriented
            notes.append("EXIF orientation applied")
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
        notes.append("16-bit panorama scaled to 8 bit")
    if img.dtype != np.uint8:
        raise InputError(f"{path}: panorama has dtype {img.dtype}; give an 8- or 16-bit PNG/JPEG")
    if gray:
        notes.append("grayscale panorama expanded to RGB")
    if img.ndim == 2 or img.shape[2] == 1:
        img = cv2.cvtColor(img.reshape(img.shape[:2]), cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        notes.append("alpha channel dropped")
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    H, W = img.shape[:2]
    if W != 2 * H:
        raise InputError(
            f"{path}: panorama is {W}x{H} (WxH) but an equirectangular panorama must be 2:1; give a full 360x180 ERP image"
        )
    return img


def read_depth(path: Path, *, png_scale: float = 0.001) -> np.ndarray:
    """Read a depth map (H, W) as float32 in file units times scale; NaN/inf/<=0 are kept (they mark invalid pixels).

    `.npy`: float array, metres. `.exr`: first channel, metres (OpenCV with OpenEXR, else the `OpenEXR` package).
    `.png`: 16-bit, metres = value * png_scale (0.001 for millimetres; Matterport-style 1/4000 m per unit is
    png_scale=0.00025; Realsee-style PNGs store value / depth_scale with a per-view scale). Extra channels are dropped.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise InputError(f"{path}: depth file not found")
    if suffix == ".npy":
        depth = load_npy(path, "depth array", kinds="fiu")
    elif suffix == ".exr":
        exr_header(path)
        depth = read_exr(path)
    elif suffix == ".png":
        depth = read_image(path, cv2.IMREAD_UNCHANGED, what="depth PNG")
        if depth.dtype != np.uint16:
            raise InputError(
                f"{path}: depth PNG is {depth.dtype}; an 8-bit PNG cannot hold depth, save 16-bit (value * png_scale = metres)"
            )
        depth = depth.astype(np.float32) * np.float32(png_scale)
    else:
        raise InputError(f"{path}: unsupported depth format {suffix!r}; give depth.npy, depth.exr or a 16-bit depth.png")
    depth = depth_plane(depth, path)
    check_image_size(path, depth.shape[1], depth.shape[0], "depth")
    return np.asarray(depth, dtype=np.float32)


def load_depth_artifact(artifact_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a depth artifact dir -> (depth (H, W) float32 metres, valid (H, W) bool, rgb (H, W, 3) uint8)."""
    artifact_dir = Path(artifact_dir)
    depth = np.load(artifact_dir / "depth.npy")
    valid = cv2.imread(str(artifact_dir / "valid.png"), cv2.IMREAD_GRAYSCALE) > 127
    rgb = cv2.cvtColor(cv2.imread(str(artifact_dir / "panorama.png"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return depth, valid, rgb
