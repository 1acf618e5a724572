"""The floor and ceiling planes of a room seen in an ERP depth map."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panoworld.core.conventions import erp_dirs64, erp_pixel_solid_angle


@dataclass
class FloorFit:
    """Horizontal floor plane below the camera found in an ERP depth map."""

    camera_height: float
    """Distance from the camera centre down to the floor plane, in the depth map's units."""
    support: float
    """Fraction of the downward-looking valid solid angle whose points lie on the fitted floor."""


def estimate_floor(
    depth: np.ndarray, valid: np.ndarray, *, min_below_deg: float = 15.0, max_tilt_deg: float = 15.0, bin_rel: float = 0.01
) -> FloorFit | None:
    """Fit the floor (a horizontal plane y = h > 0, up = -Y) to an ERP depth map (H, W) with validity (H, W).

    Points seen at least min_below_deg below the horizon whose local normal is within max_tilt_deg of vertical
    vote, weighted by surface area, in a histogram of log y (bins of bin_rel relative width); among the peaks
    holding at least half of the strongest bin's weight the lowest wins (furniture tops lie above the floor),
    refined by the weighted median of its inliers. None if no such horizontal surface exists.
    """
    H, W = depth.shape
    dirs = erp_dirs64(H, W)
    # Only rows min_below_deg below the horizon vote: they and the row above them (their normals' neighbour) are used.
    r0 = max(int(np.argmax(dirs[:, 0, 1] > np.sin(np.deg2rad(min_below_deg)))) - 1, 0)
    if not (dirs[:, 0, 1] > np.sin(np.deg2rad(min_below_deg))).any():
        r0 = H
    dirs, depth, valid = dirs[r0:], depth[r0:], valid[r0:]
    d = np.where(valid, depth, 0.0)
    pts = [dirs[..., k] * d for k in range(3)]  # x, y, z (h, W) each: the arithmetic of an (h, W, 3) array, per axis
    # Central differences with the seam wrapped; rows clamp at the bottom pole (the top row of the slice never votes).
    dx = [np.roll(p, -1, axis=1) - np.roll(p, 1, axis=1) for p in pts]
    dy = [np.concatenate([p[1:], p[-1:]]) - np.concatenate([p[:1], p[:-1]]) for p in pts]
    n = [dx[1] * dy[2] - dx[2] * dy[1], dx[2] * dy[0] - dx[0] * dy[2], dx[0] * dy[1] - dx[1] * dy[0]]  # np.cross
    nn = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    ok = valid & np.roll(valid, 1, 1) & np.roll(valid, -1, 1)
    ok[1:] &= valid[:-1]
    ok[:-1] &= valid[1:]
    ok &= nn > 0
    cos_vert = np.abs(n[1]) / np.maximum(nn, 1e-30)
    below = dirs[..., 1] > np.sin(np.deg2rad(min_below_deg))
    y = pts[1]
    sel = ok & below & (cos_vert >= np.cos(np.deg2rad(max_tilt_deg))) & (y > 0)
    omega = np.broadcast_to(erp_pixel_solid_angle(H, W)[r0:], depth.shape)
    down_total = omega[below & valid].sum()
    if sel.sum() < 20 or down_total <= 0:
        return None
    cos_inc = np.clip(np.abs(dirs[..., 1][sel]), 0.05, 1.0)  # ray vs vertical normal
    area = omega[sel] * depth[sel] ** 2 / cos_inc
    ly = np.log(y[sel])
    lo, hi = ly.min(), ly.max()
    nb = max(1, int(np.ceil((hi - lo) / bin_rel)) + 1)
    hist, edges = np.histogram(ly, bins=nb, range=(lo, lo + nb * bin_rel), weights=area)
    # Smooth with the ends padded ('same' mode would return 3 bins for a 1- or 2-bin histogram: planar layouts).
    hist = np.convolve(np.pad(hist, 1), [0.25, 0.5, 0.25], mode="valid")
    strong = np.nonzero(hist >= 0.5 * hist.max())[0]
    peak = strong.max()
    ly_peak = 0.5 * (edges[peak] + edges[peak + 1])
    inl = np.abs(ly - ly_peak) <= 2.0 * bin_rel
    order = np.argsort(ly[inl])
    cw = np.cumsum(area[inl][order])
    h = float(np.exp(ly[inl][order][np.searchsorted(cw, 0.5 * cw[-1])]))
    on_floor = np.abs(y - h) <= 0.02 * h
    support = float(omega[on_floor & below & valid].sum() / down_total)
    return FloorFit(camera_height=h, support=support)


def column_reach(depth: np.ndarray) -> np.ndarray:
    """(W,) the farthest horizontal distance from the camera of the points (depth > 0) of each column of depth (H, W)
    (0 where a column has none): in a room's layout, the wall of that column."""
    dirs = erp_dirs64(*depth.shape)
    return np.where(depth > 0, depth * np.hypot(dirs[..., 0], dirs[..., 2]), 0.0).max(0)


def fit_planes(depth: np.ndarray, valid: np.ndarray) -> tuple[float | None, float | None]:
    """(floor, ceiling) distances below / above the camera of the horizontal planes found in depth (H, W): the
    floor fit of panoworld.room.floor.estimate_floor (area-weighted robust mode of horizontal surfaces), run on the
    depth map as it is and flipped upside down; None where no such plane is visible."""
    floor = estimate_floor(depth, valid)
    ceiling = estimate_floor(np.ascontiguousarray(depth[::-1]), np.ascontiguousarray(valid[::-1]))
    return (floor.camera_height if floor else None), (ceiling.camera_height if ceiling else None)
