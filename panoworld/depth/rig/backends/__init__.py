"""Rig detectors of the depth stage (`depth.rig_detector`): `impl(rgb, depth, valid, floor_m, params) -> RigDetection`."""

from __future__ import annotations

from panoworld.core.registry import register


def heuristic(rgb, depth, valid, floor_m, params):
    from panoworld.depth.rig.detect import detect_rig

    return detect_rig(rgb, depth, valid, floor_m)


def learned(rgb, depth, valid, floor_m, params):
    from panoworld.depth.rig.learned import detect_rig_learned

    return detect_rig_learned(rgb, depth, valid, floor_m, weights=params.rig_weights, device=params.rig_device)


register("rig", "heuristic", heuristic, weights=False)
register("rig", "learned", learned, weights=True)
