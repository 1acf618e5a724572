"""A room-layout annotation's depth as ZInD renders it: a polygon's walls, an unbounded floor and ceiling."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import erp_dirs


def polygon_layout_depth(polygon: np.ndarray, cam_xz: np.ndarray, camera_height: float, ceiling_above: float,
                         H: int, W: int) -> np.ndarray:
    """ERP ray depth (H, W) float32 of a room outline polygon (K, 2) (x, z metres, either winding) seen from cam_xz (2,):
    its wall segments (both faces), a floor camera_height below and a ceiling ceiling_above the camera; rays that miss
    every wall reach those planes however far (a camera outside its polygon sees them recede for hundreds of metres,
    as the layout depth of a ZInD tour does)."""
    d = erp_dirs(H, W, np.float64)
    mid = d[H // 2]
    ux, uz = mid[:, 0] / np.hypot(mid[:, 0], mid[:, 2]), mid[:, 2] / np.hypot(mid[:, 0], mid[:, 2])
    p = np.asarray(polygon, np.float64) - np.asarray(cam_xz, np.float64)
    t_wall = np.full(W, np.inf)
    for a, b in zip(p, np.roll(p, -1, 0)):
        e = b - a
        den = ux * e[1] - uz * e[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (a[0] * e[1] - a[1] * e[0]) / den
            s = (a[0] * uz - a[1] * ux) / den
        hit = np.isfinite(t) & (t > 0) & (s >= 0) & (s <= 1)
        t_wall = np.where(hit, np.minimum(t_wall, t), t_wall)
    horiz = np.hypot(d[..., 0], d[..., 2])
    down = d[..., 1]  # +Y is down
    plane = np.where(down > 0, camera_height / np.maximum(down, 1e-9), ceiling_above / np.maximum(-down, 1e-9))
    return np.minimum(t_wall[None, :] / np.maximum(horiz, 1e-9), plane).astype(np.float32)
