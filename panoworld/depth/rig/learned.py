"""The learned rig detector: a small U-Net's rig mask on the downward face, with the heuristic's safety tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from panoworld.depth.rig import nadir
from panoworld.depth.rig.detect import HUB_DEG
from panoworld.depth.rig.face import face_to_erp_mask
from panoworld.room.light import apply_gain

THRESHOLD = 0.5
"""Rig probability above which a face pixel is rig."""


def network_mask(net, face: np.ndarray, theta: np.ndarray) -> np.ndarray | None:
    """The network's rig pixels (size, size) connected to the nadir (within HUB_DEG), or None."""
    m = ((net.predict(face) > THRESHOLD) & (theta < 40.0)).astype(np.uint8)
    _, labels = cv2.connectedComponents(m, connectivity=8)
    hit = np.unique(labels[(theta < HUB_DEG) & (labels > 0)])
    return np.isin(labels, hit) if len(hit) else None


def detect_rig_learned(rgb: np.ndarray, depth: np.ndarray | None, valid: np.ndarray | None, floor_m: float | None,
                       *, weights: Path | None, device: str = "cpu") -> nadir.RigDetection:
    """detect_rig with the rig U-Net (weights: its directory) instead of the colour and shape tests; a seen object
    (reaching CAP_DEG, or a horizontal surface above the floor) is still kept, a soft shadow still relit."""
    from panoworld.models.rig_unet import RigUNet

    net = RigUNet.load(weights, device)
    nf = nadir.nadir_face(rgb, depth, valid, floor_m)
    refusal = nadir.no_floor_ring(nf)
    if refusal is not None:
        return refusal
    H, W = rgb.shape[:2]
    comp = network_mask(net, nf.face, nf.theta)
    if comp is None:
        return nadir.RigDetection(False, "the rig network finds nothing at the nadir")
    refusal = nadir.seen_object(nf, comp, floor_m)
    if refusal is not None:
        return refusal
    gain, sh_deg, stats = nadir.face_shadow(nf, nf.face, comp)
    face = apply_gain(nf.face, gain) if sh_deg > 0 else nf.face
    extent = float(np.percentile(nf.theta[comp], 98))
    stats.update(cap_deg=extent, face_pixels=int(comp.sum()), shadow_deg=sh_deg)
    mask = face_to_erp_mask(nadir.dilate_rim(comp, nf.view), nf.view, H, W)
    shadow = face_to_erp_mask(gain > 1.0, nf.view, H, W) & ~mask
    reason = f"the rig network's mask at the nadir, {extent:.1f} deg" + (f" with a shadow ({sh_deg:.0f} deg)" if sh_deg else "")
    return nadir.RigDetection(True, reason, "learned", mask, shadow, stats, shadow_gain=gain, source=nadir.floor_source(face, nf))
