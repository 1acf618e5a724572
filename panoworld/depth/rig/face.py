"""The downward cube face of an ERP panorama, where the capture rig is found and removed: its view, the polar
angles of its pixels and resampling between it and the ERP (docs/rig.md)."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from panoworld.core.conventions import erp_dirs64, erp_pixel_from_dir
from panoworld.geometry.cube_views import PerspectiveView, render_view

FACE_FOV_DEG = 96.0
"""Field of view of the downward face (48 degrees from the nadir at its sides)."""
def nadir_view(height: int) -> PerspectiveView:
    """The downward face for an ERP of height rows, with about the ERP's angular resolution at the nadir."""
    size = max(64, int(round(2.0 * np.tan(np.deg2rad(FACE_FOV_DEG / 2)) * height / np.pi)))
    return PerspectiveView(Rotation.from_euler("x", -90, degrees=True).as_matrix(), FACE_FOV_DEG, size)


def face_polar(view: PerspectiveView) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of every face pixel: degrees from the nadir, azimuth in radians."""
    c = np.arange(view.size) + 0.5 - 0.5 * view.size
    x, y = np.meshgrid(c, c)
    return np.rad2deg(np.arctan(np.hypot(x, y) / view.focal)), np.arctan2(y, x)


def face_depth(depth: np.ndarray, valid: np.ndarray, view: PerspectiveView) -> tuple[np.ndarray, np.ndarray]:
    u, v = erp_pixel_from_dir(view.rays(), *depth.shape)
    iu = np.clip(u.astype(int), 0, depth.shape[1] - 1)
    iv = np.clip(v.astype(int), 0, depth.shape[0] - 1)
    return depth[iv, iu], valid[iv, iu]


def face_to_erp(values: np.ndarray, view: PerspectiveView, H: int, W: int, outside: float = 0.0) -> np.ndarray:
    """Face values (size, size[, C]) float -> (H, W[, C]) ERP, bilinear; outside where a pixel does not see the face."""
    out = np.full((H, W, *values.shape[2:]), outside, np.float32)
    rows = cap_rows(H, view)
    px, py, front = _erp_maps(np.asarray(view.cam_from_view, np.float64).tobytes(), float(view.fov_deg),
                              int(view.size), H, W)
    m = cv2.remap(values.astype(np.float32), px, py, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                  borderValue=outside)
    out[rows] = np.where(front.reshape(front.shape + (1,) * (values.ndim - 2)), m, outside)
    return out


@lru_cache(maxsize=4)
def _erp_maps(rot: bytes, fov_deg: float, size: int, H: int, W: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """face_to_erp's remap coordinates (float32) and its ERP pixels in front of the view, on cap_rows (cached;
    read-only)."""
    view = PerspectiveView(np.frombuffer(rot, np.float64).reshape(3, 3), fov_deg, size)
    px, py, cos = view.project(erp_dirs64(H, W)[cap_rows(H, view)])
    maps = np.nan_to_num(px, nan=-10).astype(np.float32), np.nan_to_num(py, nan=-10).astype(np.float32), cos > 0
    for m in maps:
        m.flags.writeable = False
    return maps


def face_to_erp_mask(face_mask: np.ndarray, view: PerspectiveView, H: int, W: int) -> np.ndarray:
    """A face mask (size, size) bool -> the ERP pixels (H, W) whose centre samples it (> 0.5 bilinear)."""
    return face_to_erp(face_mask.astype(np.float32), view, H, W) > 0.5


def cap_rows(H: int, view: PerspectiveView) -> slice:
    """ERP rows that can see the face (from FACE_FOV_DEG / 2 above the nadir, cornered: 56 deg)."""
    lat0 = np.deg2rad(-90.0 + 56.0)
    return slice(int(np.floor((0.5 - lat0 / np.pi) * H)), H)


def erp_mask_to_face(mask: np.ndarray, view: PerspectiveView) -> np.ndarray:
    return render_view(np.repeat(mask.astype(np.uint8)[..., None] * 255, 3, axis=2), view)[..., 0] > 127


def nadir_crop(rgb: np.ndarray, size: int = 192, fov_deg: float = 70.0) -> np.ndarray:
    """A small downward view (size, size, 3) of an ERP panorama: the nadir before/after picture of the report."""
    return render_view(rgb, PerspectiveView(nadir_view(rgb.shape[0]).cam_from_view, fov_deg, size))
