"""A panorama's depth made usable: metric scale, the near cut, rig removal and completion of poles and dropouts."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from panoworld.core.errors import InputError
from panoworld.core.shapes import check_shape
from panoworld.depth.options import Rescale


@dataclass
class Cleaned:
    rgb: np.ndarray
    """(H, W, 3) uint8: the panorama the later stages use (rig removed)."""
    depth: np.ndarray
    """(H, W) float32 metric ray distance, 0 where invalid."""
    valid: np.ndarray
    """(H, W) bool."""
    info: dict
    """Manifest entries: scale, rig, pole_completion, dropout_completion, valid_fraction, depth_range_m."""
    rig: object | None = None
    """The rig detection (panoworld.depth.rig.nadir.RigDetection) when removal ran, else None."""
    notes: list[str] = field(default_factory=list)
    """Decisions worth a line in the manifest."""


def clean_depth(rgb: np.ndarray, depth: np.ndarray, valid: np.ndarray, *, relative: bool, rescale: Rescale,
                camera_height: float, min_depth_m: float, detect_rig: Callable | None, rig_mask: Path | np.ndarray | None,
                complete_poles: bool, complete_dropouts: bool, source: Path) -> Cleaned:
    """rgb (H, W, 3), depth and valid (H, W) from a depth backend -> metric, rig-free, completed depth.

    detect_rig None keeps the rig; else it is called as the rig backends are (panoworld/depth/rig/backends/) and rig_mask, a
    user mask (its file, or (H, W) bool), overrides it. source names the file in the one-line error when no depth is left."""
    from panoworld.depth import depth_map as dep

    dims = check_shape("rgb", rgb, "H W 3")
    check_shape("depth", depth, "H W", dims=dims)
    check_shape("valid", valid, "H W", dims=dims)
    notes: list[str] = []
    info: dict = {}
    valid = valid & (depth >= np.finfo(np.float32).tiny)  # subnormal depths: no scale survives them
    depth, scale_info = dep.metric_rescale(depth, valid, relative=relative, rescale=rescale, camera_height=camera_height)
    info.update(scale_info)
    if scale_info.get("scale_note"):
        notes.append(scale_info["scale_note"])
    near = valid & (depth < min_depth_m)
    if near.any():
        valid = valid & ~near
        notes.append(f"{int(near.sum())} pixels nearer than min_depth_m {min_depth_m} m made invalid")
    if not valid.any():
        raise InputError(f"{source}: no depth left beyond min_depth_m {min_depth_m} m")
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    det = None
    if detect_rig is not None:
        from panoworld.depth.rig.remove import rig_step

        rgb, depth, valid, info["rig"], det = rig_step(rgb, depth, valid, info.get("camera_height_estimated_after"),
                                                         user_mask=rig_mask, detect=detect_rig)
        notes.append(f"capture rig {'removed' if det.found else 'not found'}: {det.reason}")
    depth, valid, unknown, planes = _plausible(depth, valid, info, notes)
    if complete_poles:
        from panoworld.depth.complete import complete_poles as poles

        depth, valid, info["pole_completion"] = poles(depth, valid, exclude=unknown, planes=planes)
        if info["pole_completion"]["completed_fraction"] > 0:
            notes.append(f"{info['pole_completion']['completed_fraction']:.1%} of the pixels (poles, bands) completed "
                         "from the floor/ceiling planes")
    if complete_dropouts:
        from panoworld.depth.complete import complete_dropouts as dropouts

        depth, valid, info["dropout_completion"] = dropouts(depth, valid, exclude=unknown)
        d = info["dropout_completion"]
        if d["completed_fraction"] > 0:
            notes.append(f"{d['completed_fraction']:.1%} of the pixels ({d['dropouts']} dropouts) completed: "
                         f"{d['plane_fraction']:.0%} from their rim's plane, {d['smooth_fraction']:.0%} as smooth surface, "
                         f"{d['step_fraction']:.0%} as a step at a depth edge")
    if not valid.any():
        raise InputError(f"{source}: no plausible depth left (every surface passes within "
                         f"{info['plausibility']['near_plane_m']} m of the camera or lies beyond its room)")
    info["valid_fraction"] = float(valid.mean())
    info["depth_range_m"] = [float(depth[valid].min()), float(depth[valid].max())]
    return Cleaned(rgb=rgb, depth=depth, valid=valid, info=info, rig=det, notes=notes)


def _plausible(depth: np.ndarray, valid: np.ndarray, info: dict, notes: list[str]):
    """room.plausible.implausible_mask on the floor and ceiling planes (room.floor.fit_planes) made invalid: its
    record goes to info["plausibility"], a line to notes when anything was masked. Returns (depth, valid, what the
    completions must leave unknown (room.plausible.unknown_beyond) or None, the planes)."""
    from panoworld.room.floor import fit_planes
    from panoworld.room.plausible import describe, mask_implausible

    planes = fit_planes(depth, valid)
    depth, valid, unknown, info["plausibility"] = mask_implausible(depth, valid, *planes)
    if unknown is not None:
        notes.append(describe(info["plausibility"]))
    return depth, valid, unknown, planes
