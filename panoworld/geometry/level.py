"""A tilted panorama's levelling: the rotation from the floor its depth shows, and its images and depth resampled
as the levelled camera sees them."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from panoworld.core.conventions import erp_dirs64, erp_pixel_from_dir
from panoworld.core.shapes import check_shape
from panoworld.geometry.floor_view import camera_height
from panoworld.geometry.resize import DEPTH_EDGE_REL

MIN_TILT_DEG = 0.25
"""A floor tilted less than this is taken as level (nothing is resampled): 1 cm at 2.3 m."""
MAX_TILT_DEG = 10.0
"""A plane tilted more than this below the camera is not taken for its floor (a ramp, stairs, a bed)."""
MIN_FLOOR_POINTS = 500
"""Depth pixels on the floor plane needed to trust its normal."""
_MAX_POINTS = 200_000


def floor_down(depth: np.ndarray) -> np.ndarray | None:
    """(3,) unit normal of the floor a ray depth (H, W) shows, pointing down (camera frame, docs/conventions.md); None
    where no floor is seen or it is tilted beyond MAX_TILT_DEG.

    The floor: the depth pixels 25 to 60 deg below the horizon (not the cap under the camera, where a rig was removed
    and the poles completed level) within 10 % of the camera height
    (geometry.floor_view.camera_height, robust to walls), a least-squares plane refitted to the points near it, the
    band narrowed from 10 % of the height to 2 cm (or 1 %)."""
    check_shape("depth", depth, "H W")
    h = camera_height(depth)
    if h is None or not h > 0:
        return None
    dirs = erp_dirs64(*depth.shape)
    down = dirs[..., 1]  # the sine of the depression; the cap under the camera (rig, completed poles) left out
    sel = np.isfinite(depth) & (depth > 0) & (down > np.sin(np.radians(25.0))) & (down < np.sin(np.radians(60.0)))
    pts = dirs[sel] * depth[sel][:, None].astype(np.float64)
    if len(pts) > _MAX_POINTS:
        pts = pts[:: len(pts) // _MAX_POINTS + 1]
    n, c = np.array([0.0, 1.0, 0.0]), np.array([0.0, h, 0.0])
    for band in (0.1, 0.1, 0.05, 0.05, 0.02, 0.01, 0.01):  # the plane turns towards the floor as the band narrows
        inl = np.abs((pts - c) @ n) < max(0.02, band * h)
        if inl.sum() < MIN_FLOOR_POINTS:
            return None
        c = pts[inl].mean(0)
        n = np.linalg.svd(pts[inl] - c, full_matrices=False)[2][2]
        n = n if n[1] > 0 else -n
    return n if angle_deg(n, np.array([0.0, 1.0, 0.0])) <= MAX_TILT_DEG else None


def level_from_down(down: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking the camera frame to the levelled one whose +y is `down` (3,) (gravity in the camera
    frame), turned about the axis in the floor level with the camera (so its yaw stays)."""
    axis = np.cross(down, [0.0, 1.0, 0.0])  # turning down onto +y about it
    norm = np.linalg.norm(axis)
    if norm < 1e-12:
        return np.eye(3)
    return cv2.Rodrigues(axis / norm * np.radians(angle_deg(down, np.array([0.0, 1.0, 0.0]))))[0]


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between two directions (3,), in degrees."""
    return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))


def level_from_cam(depth: np.ndarray) -> np.ndarray | None:
    """(3, 3) rotation taking the camera frame to the levelled one whose +y is the floor's normal (floor_down) from
    the ray depth (H, W); None where the floor is level within MIN_TILT_DEG, not seen, or tilted beyond
    MAX_TILT_DEG."""
    n = floor_down(depth)
    if n is None or angle_deg(n, np.array([0.0, 1.0, 0.0])) < MIN_TILT_DEG:
        return None
    return level_from_down(n)


def tilt_deg(level_from_cam_: np.ndarray) -> float:
    """The tilt a levelling rotation (3, 3) undoes, in degrees."""
    return float(np.degrees(np.arccos(np.clip(level_from_cam_[1, 1], -1.0, 1.0))))


def levelled(image: np.ndarray, level_from_cam_: np.ndarray, *, nearest: bool = False) -> np.ndarray:
    """An ERP image (H, W[, C]) as the levelled camera sees it: each pixel of the levelled frame sampled along its
    ray in the camera frame (8-bit images bicubic: a panorama tilted 2° and levelled back comes within 45.0 dB of
    itself, 41.5 bilinear; other types bilinear; nearest for depth and masks, whose values must not blend)."""
    mx, my = _sampling_grid(*image.shape[:2], np.asarray(level_from_cam_, np.float64).tobytes())
    src = image.astype(np.uint8) if image.dtype == bool else image
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_CUBIC if image.dtype == np.uint8 else cv2.INTER_LINEAR
    out = cv2.remap(src, mx, my, interp, borderMode=cv2.BORDER_WRAP)
    return out.astype(bool) if image.dtype == bool else out


@lru_cache(maxsize=2)
def _sampling_grid(h: int, w: int, rotation: bytes) -> tuple[np.ndarray, np.ndarray]:
    """levelled's remap grids (h, w) float32 for a levelling rotation (its float64 bytes): the panorama, its depth and
    masks of one levelling share them."""
    u, v = erp_pixel_from_dir(erp_dirs64(h, w).reshape(-1, 3) @ np.frombuffer(rotation).reshape(3, 3), h, w)
    mx = ((u - 0.5) % w).reshape(h, w).astype(np.float32)
    my = np.clip(v - 0.5, 0, h - 1).reshape(h, w).astype(np.float32)
    mx.flags.writeable = my.flags.writeable = False
    return mx, my


def levelled_depth(depth: np.ndarray, level_from_cam_: np.ndarray, edge_rel: float = DEPTH_EDGE_REL) -> np.ndarray:
    """A ray depth (H, W) (0 or not finite = none) as the levelled camera sees it, sampled as geometry.resize does:
    bilinear on smooth surfaces (the 3x3 source pixels around the sample all valid, their depths within edge_rel of
    each other), nearest at depth edges and next to invalid pixels (no depth between two surfaces). Nearest
    everywhere would put a plane's pixels on a terraced grid, one step each time the tilt crosses a row."""
    check_shape("depth", depth, "H W")
    d = np.asarray(depth, np.float32)
    ok = np.isfinite(d) & (d > 0)
    d = np.where(ok, d, 0.0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    hi = levelled(cv2.dilate(d, kernel), level_from_cam_, nearest=True)
    lo = levelled(cv2.erode(d, kernel), level_from_cam_, nearest=True)  # 0 next to an invalid pixel
    smooth = (lo > 0) & (hi <= lo * (1.0 + edge_rel))
    return np.where(smooth, levelled(d, level_from_cam_), levelled(d, level_from_cam_, nearest=True)).astype(np.float32)
