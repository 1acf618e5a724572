"""The nadir candidate's shape tests: tripod-leg arms by width, azimuth occupancy, a horizontal surface in depth, floor lines."""

from __future__ import annotations

import cv2
import numpy as np

TABLE_MIN_GAP_M = 0.3
"""A horizontal surface at least this far below the camera (and above the floor) is a seen object, not the mount."""
FLOOR_LINE_MAX_DEG = 0.5
"""On-floor parts of the rig's mask and of its cast shadows narrower than this are floor lines (tile grout, plank
seams) touching the legs, not the rig: without this, a tiled floor's grout network can join the mask through the
cast shadows out to 30 deg at 720 rows. Where it spans under a face pixel (256 rows) nothing is opened."""
MIN_LEG_WIDTH_DEG = 0.6
"""An arm of the candidate is a tripod leg only when at least this wide on average over 45-85 % of its extent (a leg
1.5-4 cm across seen from 0.6-1.7 m: >= 1 degree). Thinner arms (the anti-aliased dashes of a tiled floor's grout,
1 cm at the floor, <= 0.3 degrees) neither count as legs nor in their azimuth occupancy."""


def azimuth_histogram(phi: np.ndarray, bins: int) -> np.ndarray:
    """Pixel count (bins,) per azimuth bin of the face azimuths phi (K,) radians in [-pi, pi]."""
    return np.bincount(((phi + np.pi) / (2 * np.pi) * bins).astype(int) % bins, minlength=bins)


def leg_arms(comp: np.ndarray, theta: np.ndarray, phi: np.ndarray, focal: float, extent: float,
             bins: int = 72) -> tuple[int, float, list[float]]:
    """The candidate's arms between 45 % and 85 % of its extent (circular runs of occupied azimuth bins) that are at
    least MIN_LEG_WIDTH_DEG wide: their number and share of the bins, and every arm's width (degrees: its pixels on
    the downward face of focal length `focal` px over the band's radial length; dashes along a line count as a
    thinner arm)."""
    band = comp & (theta > 0.45 * extent) & (theta < 0.85 * extent)
    h = azimuth_histogram(phi[band], bins)
    if not h.any() or h.all():
        return 0, 0.0, []
    h = np.roll(h, -int(np.argmin(h)))  # start at an empty bin: no run wraps around
    edges = np.diff(np.r_[0, (h > 0).astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    t0, t1 = np.deg2rad(0.45 * extent), np.deg2rad(0.85 * extent)
    length = focal * (np.tan(t1) - np.tan(t0))
    widths = [float(np.rad2deg(h[a:b].sum() / length / focal)) for a, b in zip(starts, ends)]
    legs = [b - a for a, b, w in zip(starts, ends, widths) if w >= MIN_LEG_WIDTH_DEG]
    return len(legs), sum(legs) / bins, widths


def azimuth_occupancy(phi: np.ndarray, bins: int = 72) -> tuple[float, int]:
    """Share of azimuth bins holding pixels, and the number of circular runs of occupied bins (arms)."""
    if len(phi) == 0:
        return 0.0, 0
    h = azimuth_histogram(phi, bins) > 0
    runs = int(np.sum(h & ~np.roll(h, 1)))
    return float(h.mean()), runs if not h.all() else 1


def horizontal_surface(theta, fd, fv, floor_m) -> float | None:
    """Distance below the camera of a horizontal surface holding >= 60 % of the region's depth pixels, when it lies
    between TABLE_MIN_GAP_M below the camera and 5 % above the floor; else None."""
    if fd is None or fv is None or not floor_m or fv.mean() < 0.5:
        return None
    drop = fd[fv] * np.cos(np.deg2rad(theta[fv]))
    med = float(np.median(drop))
    if np.mean(np.abs(drop - med) < 0.03 * med) < 0.6:
        return None
    return med if TABLE_MIN_GAP_M <= med < 0.95 * floor_m else None


def opened(mask: np.ndarray, k: int) -> np.ndarray:
    """mask (S, S) less its parts narrower than k face pixels: a morphological opening by a k x k ellipse (bool)."""
    return cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0


def thin_kernel(focal: float, deg: float) -> int:
    """The odd kernel (face pixels) of an opening that removes lines narrower than deg (1: none at this resolution)."""
    return 2 * int(round(0.5 * focal * np.deg2rad(deg))) + 1


def without_floor_lines(obj: np.ndarray, on_floor: np.ndarray, focal: float) -> np.ndarray:
    """obj less its on-floor parts narrower than FLOOR_LINE_MAX_DEG: floor lines (grout, plank seams) touching the
    legs, which the rig's mask would otherwise carry into the inpainting."""
    k = thin_kernel(focal, FLOOR_LINE_MAX_DEG)
    if k <= 1:
        return obj
    wide = opened(obj & on_floor, k)
    out = obj & (~on_floor | wide)
    n, labels, st, _ = cv2.connectedComponentsWithStats(out.astype(np.uint8), connectivity=8)
    if n <= 2:
        return out
    area = st[1:, cv2.CC_STAT_AREA]
    return np.isin(labels, 1 + np.nonzero(area >= 0.05 * area.max())[0])  # pieces of grout left, cut off the rig
