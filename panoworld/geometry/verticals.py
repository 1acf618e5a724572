"""The camera's gravity direction from the vertical lines a panorama shows (door frames, wall corners, furniture)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from panoworld.core.shapes import check_shape
from panoworld.geometry.cube_views import PerspectiveView, render_view
from panoworld.geometry.level import level_from_down, levelled
from panoworld.geometry.upright import yaw_matrix

VIEWS = 8
"""Perspective views around the horizon the lines are found in (90 deg wide, 45 deg apart)."""
VIEW_SIZE = 512
"""Their side in pixels."""
MIN_LENGTH_PX = 30
"""A line segment shorter than this (in a view) is left out."""
MAX_SLANT_DEG = 30.0
"""A segment more than this from the view's vertical is no candidate (a camera tilted <= 15 deg keeps its verticals
within ~20 deg there)."""
WIDE_SLANT_DEG = 50.0
"""The same for the second try, for a steeper tilt."""
INLIER_DEG = 0.5
"""A segment's great circle within this of the gravity direction is one of its vertical lines."""
MIN_VERTICALS = 20
"""Vertical lines needed to trust the direction they meet in."""
MIN_SHARE = 0.4
"""Nor fewer than this share of the candidate lines' length (the rest: slanted lines, clutter)."""
MAX_TILT_DEG = 15.0
"""Directions farther than this from the camera's own down are not tried first."""
WIDE_TILT_DEG = 45.0
"""Nor farther than this at all."""
REFINE_DEG = 5.0
"""A tilt beyond this is refined on the panorama levelled by it."""
MIN_ROWS = 256
"""A panorama of fewer rows is not read (its lines too short and blurred to place within a degree)."""


@dataclass(frozen=True)
class Gravity:
    down_cam: np.ndarray
    """(3,) unit vector, gravity (down) in the camera frame (docs/conventions.md: +y is down for a level camera)."""
    verticals: int
    """Line segments on its great circles (the support)."""
    share: float
    """Their share of the candidates' length."""

    @property
    def tilt_deg(self) -> float:
        """The angle between the camera's down (+y) and gravity."""
        return float(np.degrees(np.arccos(np.clip(self.down_cam[1], -1.0, 1.0))))


VIEWS_AROUND = tuple(PerspectiveView(yaw_matrix(2.0 * np.pi * k / VIEWS), 90.0, VIEW_SIZE) for k in range(VIEWS))
"""The views around the horizon the lines are found in."""


def _rays(view: PerspectiveView, pts: np.ndarray) -> np.ndarray:
    """Camera-frame rays (N, 3) (not unit) through the view's continuous pixel coordinates pts (N, 2) (the centre of
    pixel (r, c) at (c, r), as PerspectiveView.rays)."""
    xy = (pts + 0.5 - 0.5 * view.size) / view.focal
    return np.hstack([xy, np.ones((len(pts), 1))]) @ view.cam_from_view.T


def vertical_candidates(gray: np.ndarray, max_slant_deg: float = MAX_SLANT_DEG) -> tuple[np.ndarray, np.ndarray]:
    """The great-circle normals (N, 3) (camera frame, unit) and lengths (N,) (view pixels) of the line segments within
    max_slant_deg of the vertical in views around the horizon of an ERP grayscale image (H, W) uint8."""
    check_shape("gray", gray, "H W")
    lsd = cv2.createLineSegmentDetector()
    normals, lengths = [], []
    for view in VIEWS_AROUND:
        segs = lsd.detect(render_view(gray, view))[0]
        if segs is None:
            continue
        segs = segs.reshape(-1, 4).astype(np.float64)
        dx, dy = segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]
        length = np.hypot(dx, dy)
        keep = (length >= MIN_LENGTH_PX) & (np.degrees(np.arctan2(np.abs(dx), np.abs(dy))) < max_slant_deg)
        if not keep.any():
            continue
        n = np.cross(_rays(view, segs[keep, :2]), _rays(view, segs[keep, 2:]))
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
        lengths.append(length[keep])
    if not normals:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(normals), np.concatenate(lengths)


def gravity_from_image(rgb: np.ndarray, *, tries: int = 1000, seed: int = 0) -> Gravity | None:
    """Gravity in the camera frame from an ERP panorama (H, W, 3) uint8: the direction the most vertical lines meet
    in (every vertical line's great circle passes through it). Near the camera's own down first (MAX_TILT_DEG); where
    that finds no direction most lines agree on, among steeper lines up to WIDE_TILT_DEG; a direction beyond
    REFINE_DEG is found again on the panorama levelled by it (its verticals then upright in the views). None when
    fewer than MIN_VERTICALS or MIN_SHARE agree, or the panorama has fewer than MIN_ROWS rows."""
    h, w = check_shape("rgb", rgb, "H W 3").values()
    if h < MIN_ROWS:
        return None
    if h > 1024:  # the lines' directions, not their detail: 1024 rows carry them
        rgb = cv2.resize(rgb, (round(w * 1024 / h), 1024), interpolation=cv2.INTER_AREA)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    g = _fit(*vertical_candidates(gray, MAX_SLANT_DEG), MAX_TILT_DEG, tries, seed)
    if g is not None and g.share >= MIN_SHARE:
        if g.tilt_deg <= REFINE_DEG:
            return g
    else:
        g = _fit(*vertical_candidates(gray, WIDE_SLANT_DEG), WIDE_TILT_DEG, tries, seed)
        if g is None or g.tilt_deg <= MAX_TILT_DEG:
            return None
    R = level_from_down(g.down_cam)
    fine = _fit(*vertical_candidates(levelled(gray, R), MAX_SLANT_DEG), MAX_TILT_DEG, tries, seed)
    if fine is None or fine.share < MIN_SHARE:
        return None
    return Gravity(down_cam=R.T @ fine.down_cam, verticals=fine.verticals, share=fine.share)


def _fit(n: np.ndarray, length: np.ndarray, max_tilt_deg: float, tries: int, seed: int) -> Gravity | None:
    """The direction within max_tilt_deg of +y most of the great circles n (N, 3) (weighted by length (N,)) pass
    through: RANSAC over pairs, then a length-weighted least-squares refit on those within INLIER_DEG."""
    if len(n) < MIN_VERTICALS:
        return None
    rng = np.random.default_rng(seed)
    tol, cos_max = np.sin(np.radians(INLIER_DEG)), np.cos(np.radians(max_tilt_deg))
    i, j = rng.integers(0, len(n), (2, tries))
    g = np.cross(n[i], n[j])
    norm = np.linalg.norm(g, axis=1)
    ok = norm > 1e-3
    g = g[ok] / norm[ok, None]
    g *= np.sign(g[:, 1:2]) + (g[:, 1:2] == 0)
    g = g[g[:, 1] >= cos_max]
    if not len(g):
        return None
    score = (np.abs(n @ g.T) < tol).T @ length
    down = g[int(np.argmax(score))]
    for _ in range(3):
        inl = np.abs(n @ down) < tol
        if inl.sum() < 2:
            return None
        down = np.linalg.eigh((n[inl] * length[inl, None]).T @ n[inl])[1][:, 0]
        down = down if down[1] > 0 else -down
    inl = np.abs(n @ down) < tol
    if inl.sum() < MIN_VERTICALS:
        return None
    return Gravity(down_cam=down, verticals=int(inl.sum()), share=float(length[inl].sum() / length.sum()))
