"""Shadows in the hidden fill: the room's ceiling lights found in the source view, and the fill darkened where an occluder hides them."""

from __future__ import annotations

import cv2
import numpy as np

from panoworld.geometry.raycast import Raycaster

LIGHT_LUMA = 245.0
"""A source pixel brighter than this (8-bit luma) on the ceiling belongs to a light."""
CEILING_BAND_M = 0.1
"""A light's pixels lie within this distance of the fitted ceiling plane."""
LIGHT_DROP_M = 0.15
"""The point light sits this far below its emitter's centroid (shadow rays stop short of the emitter itself)."""
MIN_AREA_M2 = 0.01
"""Bright ceiling patches smaller than this are not lights."""
START_M = 0.03
"""Shadow rays start this far from the surface point towards the light."""


def ceiling_lights(points: np.ndarray, rgb: np.ndarray, valid: np.ndarray, ceiling_y: float | None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Lights of an ERP grid of points (h, w, 3) (canonical frame, y down) with colours rgb (h, w, 3) uint8: the
    connected bright patches (luma >= LIGHT_LUMA) within CEILING_BAND_M of the ceiling plane y = ceiling_y. Returns
    positions (L, 3) (each patch's centroid LIGHT_DROP_M below it) and weights (L,) (the patch's area, m^2); empty
    without a ceiling."""
    none = np.zeros((0, 3)), np.zeros(0)
    if ceiling_y is None:
        return none
    h, w = valid.shape
    luma = rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    bright = valid & (luma >= LIGHT_LUMA) & (np.abs(points[..., 1] - ceiling_y) <= CEILING_BAND_M)
    if not bright.any():
        return none
    n, label = cv2.connectedComponents(bright.astype(np.uint8), connectivity=8)
    depth = np.linalg.norm(points, axis=-1)
    lat = (0.5 - (np.arange(h) + 0.5) / h) * np.pi
    px = 2 * np.pi / w
    area = (depth * px) ** 2 * np.cos(lat)[:, None]  # the pixel's footprint facing the camera (m^2), a lower bound
    lab = label.reshape(-1)
    keep = lab > 0
    size = np.bincount(lab[keep], area.reshape(-1)[keep], minlength=n)
    cnt = np.bincount(lab[keep], minlength=n)
    cen = np.stack([np.bincount(lab[keep], points.reshape(-1, 3)[keep, a], minlength=n) for a in range(3)], 1)
    ok = np.flatnonzero(size >= MIN_AREA_M2)
    ok = ok[ok > 0]
    pos = cen[ok] / cnt[ok, None]
    pos[:, 1] += LIGHT_DROP_M  # y down: below the ceiling
    return pos, size[ok]


def lit_fraction(rc: Raycaster, points: np.ndarray, lights: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N,) share of the lights' (weighted, inverse-square) irradiance that reaches each point (N, 3) unblocked by
    the mesh of rc: 1 = fully lit, 0 = in every light's shadow."""
    points = np.asarray(points, np.float64)
    num = np.zeros(len(points))
    den = np.zeros(len(points))
    for pos, wt in zip(lights, weights):
        to = pos - points
        dist = np.linalg.norm(to, axis=1)
        dirs = to / np.maximum(dist, 1e-9)[:, None]
        hits = rc.cast(points + START_M * dirs, dirs)
        clear = hits.distance >= dist - START_M - 1e-3
        irr = wt / np.maximum(dist, 0.3) ** 2
        num += irr * clear
        den += irr
    return np.where(den > 0, num / np.maximum(den, 1e-12), 1.0)


def shadow_gain(lit_here: np.ndarray, lit_donor: np.ndarray, ambient: float) -> np.ndarray:
    """Linear-light gain taking a colour seen with lit fraction lit_donor to a point with lit_here, when ambient light
    is this share of a fully lit point's irradiance."""
    return (ambient + (1 - ambient) * lit_here) / (ambient + (1 - ambient) * lit_donor)

