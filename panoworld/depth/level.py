"""A panorama taken with the camera off level, levelled before its depth is cleaned: its vertical lines, checked by its
depth's floor."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from panoworld.core.shapes import check_shape
from panoworld.geometry.floor_view import camera_height
from panoworld.geometry.level import angle_deg, floor_down, level_from_down, levelled_depth, tilt_deg
from panoworld.geometry.verticals import gravity_from_image

MIN_TILT_DEG = 1.0
"""A panorama whose vertical lines read less than this from level is left as taken: the real captures' own levelling
(ZInD's photos 0.1-0.7 deg, the Realsee LiDAR capture 0.7 deg) is not worth resampling the panorama for."""
MAX_TILT_DEG = 45.0
"""Nor one read as farther off than this (its lines are not the room's verticals)."""
AGREE_DEG = 1.0
"""The depth's floor, once the panorama is levelled by its lines, must be level within this; else both are left as
taken (the depth and the photo disagree about the camera: a layout drawn level under a tilted photo)."""
_UP = np.array([0.0, 1.0, 0.0])
_NOMINAL_HEIGHT_M = 1.6
"""The depth, in any units, is scaled to put its floor this far below the camera for the floor fit (its bands are
metric)."""


@dataclass
class Levelling:
    level_from_cam: np.ndarray | None
    """(3, 3) rotation from the camera as taken to the levelled camera, None when left as taken."""
    info: dict = field(default_factory=dict)
    """The manifest's record: image_tilt_deg, verticals, floor_residual_deg, tilt_deg, level_from_cam."""
    note: str | None = None
    """A line for the manifest's decisions when the panorama reads off level."""


def level_panorama(rgb: np.ndarray, depth: np.ndarray, valid: np.ndarray) -> Levelling:
    """Whether and how to level a panorama (H, W, 3) uint8 with its depth (H, W) (any scale) and valid (H, W) bool.

    Gravity comes from the panorama's vertical lines (geometry.verticals); a tilt of MIN_TILT_DEG to MAX_TILT_DEG is
    levelled when the depth, levelled by it, shows its floor level within AGREE_DEG (the floor's own normal then
    finishes the levelling, so the floor lies level), or shows no floor there nor, as taken, one off the lines' gravity
    by more than AGREE_DEG (the lines alone)."""
    dims = check_shape("rgb", rgb, "H W 3")
    check_shape("depth", depth, "H W", dims=dims)
    check_shape("valid", valid, "H W", dims=dims)
    g = gravity_from_image(rgb)
    if g is None:
        return Levelling(None, {"image_tilt_deg": None})
    tilt = g.tilt_deg
    info: dict = {"image_tilt_deg": round(tilt, 3), "verticals": g.verticals}
    if not MIN_TILT_DEG <= tilt <= MAX_TILT_DEG:
        return Levelling(None, info)
    by_lines = level_from_down(g.down_cam)
    d = np.where(valid & np.isfinite(depth), depth, 0.0).astype(np.float32)
    h = camera_height(d)
    floor = residual = None
    if h is not None and h > 0:
        d *= np.float32(_NOMINAL_HEIGHT_M / h)
        floor = floor_down(levelled_depth(d, by_lines))
        if floor is not None:
            residual = angle_deg(floor, _UP)
        elif (as_taken := floor_down(d)) is not None:  # a floor near level as taken: the lines' levelling tilts it
            residual = angle_deg(as_taken, g.down_cam)
    if residual is not None:
        info["floor_residual_deg"] = round(residual, 3)
        if residual > AGREE_DEG:
            return Levelling(None, info, f"the panorama's vertical lines read {tilt:.1f}° from level but its depth's "
                             f"floor is {residual:.1f}° off from that: left as taken (docs/conventions.md)")
    if floor is None:
        R, how = by_lines, "its vertical lines (the depth shows no floor near that level to check them)"
    else:
        R, how = level_from_down(floor) @ by_lines, (f"its vertical lines; the depth's floor agrees within "
                                                     f"{residual:.1f}° and levels it exactly")
    undone = tilt_deg(R)
    if undone < MIN_TILT_DEG:  # the floor puts it back near level: nothing worth resampling
        return Levelling(None, info)
    info.update(tilt_deg=round(undone, 3), level_from_cam=R.round(9).tolist())
    return Levelling(R, info, f"taken {info['tilt_deg']:.1f}° from level ({how}): levelled, the scene is built level")
