"""COLMAP's image work redone bit for bit, faster: SIFT thumbnails (grey + OpenImageIO triangle resize, numba), point colours."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from numba import njit

F32 = np.float32
THUMB_SUFFIX = ".bmp"
"""Appended to a frame's file name for its thumbnail (uncompressed: quick to write and for COLMAP to read)."""


def thumbnail_size(width: int, height: int, max_image_size: int) -> tuple[int, int]:
    """(width, height) after colmap::Bitmap::Thumbnail(max_image_size): the longer side fitted to max_image_size."""
    if width <= max_image_size and height <= max_image_size:
        return width, height
    scale = max_image_size / max(width, height)
    return int(math.floor(width * scale + 0.5)), int(math.floor(height * scale + 0.5))


def grey_reference(rgb: np.ndarray) -> np.ndarray:
    """colmap::Bitmap::CloneAsGrey of (H, W, 3) uint8 RGB: round(.2126 R + .7152 G + .0722 B) in float32."""
    r, g, b = (rgb[..., k].astype(F32) for k in range(3))
    v = (F32(0.2126) * r + F32(0.7152) * g) + F32(0.0722) * b
    return np.floor(v + F32(0.5)).astype(np.uint8)


def triangle_taps(dst: int, src: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised tap weights (dst, taps) float32 and clamped source indices (dst, taps) of OpenImageIO 3.1's
    separable resize_ with the width-2 triangle filter, in its float32 arithmetic (imagebufalgo_xform.cpp)."""
    ratio = F32(dst) / F32(src)
    pixel = F32(1.0) / F32(dst)
    rad = int(math.ceil(F32(1.0) / ratio))
    taps = 2 * rad + 1
    w = np.zeros((dst, taps), F32)
    idx = np.zeros((dst, taps), np.int64)
    for x in range(dst):
        sf = F32(0.0) + ((F32(x) + F32(0.5)) * pixel) * F32(src)
        fl = np.floor(sf)
        frac = F32(sf - fl)
        total = F32(0.0)
        for i in range(taps):
            a = abs(ratio * (F32(i - rad) - (frac - F32(0.5))) * F32(1.0))
            w[x, i] = F32(1.0) - a if a < F32(1.0) else F32(0.0)
            total = F32(total + w[x, i])
        if total != F32(0.0):
            w[x] = w[x] / total
        idx[x] = np.clip(np.arange(int(fl) - rad, int(fl) + rad + 1), 0, src - 1)
    return w, idx


# uint8 -> float as OpenImageIO converts pixels: v * (1 / 255) in float32.
_TO_FLOAT = np.arange(256, dtype=F32) * (F32(1.0) / F32(255.0))


def resize_reference(grey: np.ndarray, width: int, height: int) -> np.ndarray:
    """OpenImageIO's triangle resize of an (H, W) uint8 image to (height, width), numpy (the test oracle)."""
    wx, ix = triangle_taps(width, grey.shape[1])
    wy, iy = triangle_taps(height, grey.shape[0])
    src = _TO_FLOAT[grey]
    pel = np.zeros((height, width), F32)
    for j in range(wy.shape[1]):
        rows = src[iy[:, j]]
        for i in range(wx.shape[1]):
            pel = pel + (wy[:, j, None] * wx[None, :, i]) * rows[:, ix[:, i]]
    return np.clip(pel * F32(255.0) + F32(0.5), 0, 255).astype(np.uint8)


@njit(cache=True, nogil=True)
def _thumbnail_kernel(bgr, to_float, wy, iy, wx, ix, out):  # pragma: no cover - numba
    h, w = bgr.shape[:2]
    grey = np.empty((h, w), np.float32)
    for r in range(h):
        for c in range(w):
            v = (np.float32(0.2126) * np.float32(bgr[r, c, 2]) + np.float32(0.7152) * np.float32(bgr[r, c, 1])) \
                + np.float32(0.0722) * np.float32(bgr[r, c, 0])
            grey[r, c] = to_float[np.int64(math.floor(v + np.float32(0.5)))]
    dh, ny = wy.shape
    nx = wx.shape[0]
    dw = wx.shape[1]
    pel = np.empty(dw, np.float32)
    for y in range(dh):
        pel[:] = 0.0
        for j in range(ny):  # per pixel the sum runs over j, then i, as OpenImageIO's does
            wyj = wy[y, j]
            if wyj == 0.0:
                continue
            row = grey[iy[y, j]]
            for i in range(nx):
                for x in range(dw):
                    pel[x] += (wyj * wx[i, x]) * row[ix[i, x]]
        for x in range(dw):
            out[y, x] = np.uint8(min(max(pel[x] * np.float32(255.0) + np.float32(0.5), np.float32(0.0)),
                                     np.float32(255.0)))


class Thumbnailer:
    """Grey thumbnails of same-sized BGR frames as COLMAP's extractor makes them (taps computed once)."""

    def __init__(self, height: int, width: int, max_image_size: int):
        self.width, self.height = thumbnail_size(width, height, max_image_size)
        wx, ix = triangle_taps(self.width, width)
        self._taps = (*triangle_taps(self.height, height), np.ascontiguousarray(wx.T), np.ascontiguousarray(ix.T))

    def __call__(self, bgr: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 BGR (OpenCV order) -> (height, width) uint8 grey thumbnail."""
        out = np.empty((self.height, self.width), np.uint8)
        _thumbnail_kernel(np.ascontiguousarray(bgr), _TO_FLOAT, *self._taps, out)
        return out


def write_thumbnails(
    paths: list[Path], out_dir: Path, max_image_size: int, num_threads: int = -1, frames: dict | None = None,
) -> tuple[int, int] | None:
    """Grey thumbnails of the frames under out_dir as NAME + THUMB_SUFFIX; the frames' (width, height).

    frames, when given, receives each frame's (H, W, 3) uint8 BGR pixels by file name (for point_colors).

    None (nothing to gain or not reproducible: then let COLMAP read the frames) unless every frame is an 8-bit RGB
    PNG of one size larger than max_image_size: only there is OpenCV's decode the same as COLMAP's.
    """
    import os

    import cv2

    if max_image_size <= 0 or not paths or any(p.suffix.lower() != ".png" for p in paths):
        return None
    first = cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED)
    if first is None or first.dtype != np.uint8 or first.ndim != 3 or first.shape[2] != 3:
        return None
    height, width = first.shape[:2]
    if max(width, height) <= max_image_size:
        return None
    shrink = Thumbnailer(height, width, max_image_size)
    out_dir.mkdir(parents=True, exist_ok=True)

    def one(p: Path) -> bool:
        bgr = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if bgr is None or bgr.dtype != np.uint8 or bgr.shape != (height, width, 3):
            return False
        if frames is not None:
            frames[p.name] = bgr
        return cv2.imwrite(str(out_dir / (p.name + THUMB_SUFFIX)), shrink(bgr))

    workers = (os.cpu_count() or 1) if num_threads <= 0 else num_threads
    with ThreadPoolExecutor(workers) as pool:
        ok = all(pool.map(one, paths))
    return (width, height) if ok else None


def restore_full_size(database: Path, width: int, height: int) -> None:
    """Make a database that COLMAP extracted from write_thumbnails' files the one it makes from the frames: the
    frames' names and size (width, height) for the EQUIRECTANGULAR cameras, keypoints scaled as its extractor scales
    them after shrinking (float32)."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        scales = {}
        for cam in db.read_all_cameras():
            if cam.model != pycolmap.CameraModelId.EQUIRECTANGULAR or list(cam.params) != [cam.width, cam.height]:
                raise ValueError(f"restore_full_size: camera {cam} is not an EQUIRECTANGULAR camera of its image size")
            sx, sy = F32(width) / F32(cam.width), F32(height) / F32(cam.height)
            scales[cam.camera_id] = np.array([sx, sy, sx, sy, sx, sy], F32)  # FeatureKeypoint::Rescale's columns
            cam.width, cam.height, cam.params = width, height, [width, height]
            db.update_camera(cam)
        for img in db.read_all_images():
            kp = db.read_keypoints(img.image_id)
            db.update_keypoints(img.image_id, kp * scales[img.camera_id])
            if not img.name.endswith(THUMB_SUFFIX):
                raise ValueError(f"restore_full_size: image {img.name} is not a thumbnail of write_thumbnails")
            img.name = img.name[: -len(THUMB_SUFFIX)]
            db.update_image(img)
    finally:
        db.close()


def set_point_colors(rec, frames: dict[str, np.ndarray]) -> None:
    """colmap::Reconstruction::ExtractColorsForAllImages from decoded frames (BGR by image name): each point's colour
    is the rounded mean over its observations of the bilinear sample at (x - 0.5, y - 0.5), float32 per sample;
    points without an in-bounds observation are black."""
    ids, samples = [], []
    for img in rec.images.values():
        if not img.has_pose:
            continue
        obs = [(q.xy, q.point3D_id) for q in img.points2D if q.has_point3D()]
        if not obs:
            continue
        bgr = frames[img.name]
        h, w = bgr.shape[:2]
        xy = np.array([o[0] for o in obs], np.float64) - 0.5
        pid = np.array([o[1] for o in obs], np.int64)
        x0, y0 = np.floor(xy[:, 0]).astype(np.int64), np.floor(xy[:, 1]).astype(np.int64)
        ok = (x0 >= 0) & (x0 + 1 < w) & (y0 >= 0) & (y0 + 1 < h)
        xy, pid, x0, y0 = xy[ok], pid[ok], x0[ok], y0[ok]
        dx, dy = (xy[:, 0] - x0)[:, None], (xy[:, 1] - y0)[:, None]
        rgb = [bgr[r, c, ::-1].astype(np.float64) for r, c in ((y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1))]
        top = (1 - dx) * rgb[0] + dx * rgb[1]
        bottom = (1 - dx) * rgb[2] + dx * rgb[3]
        samples.append(((1 - dy) * top + dy * bottom).astype(F32).astype(np.float64))
        ids.append(pid)
    point_ids = np.asarray(sorted(rec.point3D_ids()), np.int64)
    total = np.zeros((len(point_ids), 3))
    count = np.zeros(len(point_ids))
    if ids:
        at = np.searchsorted(point_ids, np.concatenate(ids))
        np.add.at(total, at, np.concatenate(samples))
        np.add.at(count, at, 1.0)
    mean = total / np.maximum(count, 1.0)[:, None]
    colors = np.where(count[:, None] > 0, np.floor(mean + 0.5), 0.0).astype(np.uint8)  # std::round: halves up
    for pid, color in zip(point_ids.tolist(), colors):
        rec.point3D(pid).color = color
