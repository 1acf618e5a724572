"""The downward face around the nadir: what its floor looks like (the floor ring), the refusals shared by the rig detectors, and their result (docs/rig.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from panoworld.depth.rig.face import (
    face_depth,
    face_polar,
    nadir_view,
)
from panoworld.depth.rig.shadow import linear_luminance, shadow_gain
from panoworld.depth.rig.shape import (
    horizontal_surface,
)
from panoworld.geometry.cube_views import PerspectiveView, render_view

CAP_DEG = 30.0
"""Largest rig: candidates must lie within this angle of the nadir (a tripod's feet reach 15-25 degrees)."""


RING_DEG = (30.0, 42.0)
"""The floor ring whose colours define 'floor' for the cap inside it."""


@dataclass
class RigDetection:
    """What detect_rig found at the nadir; `found` with the ERP masks, else the reason none was taken."""

    found: bool
    reason: str
    """One line: what was found and why it counts as a rig, or why nothing was removed."""
    kind: str | None = None
    """legs (tripod legs around a hub), mount (a small solid blob), mask (a uniform black nadir patch), base (a camera
    base segmented by GrabCut, panoworld.depth.rig.base), user."""
    mask: np.ndarray | None = None
    """(H, W) bool ERP pixels of the rig itself (inpainted)."""
    shadow: np.ndarray | None = None
    """(H, W) bool ERP pixels of its shadow on the floor (relit, texture kept)."""
    stats: dict = field(default_factory=dict)
    """Shape measurements behind the decision (cap_deg, azimuth occupancy, arms, darkness, ...)."""
    shadow_gain: np.ndarray | None = None
    """(size, size) light factor on the downward face that divides the shadow out (1 outside it)."""
    source: np.ndarray | None = None
    """(size, size) face pixels the inpainting may copy floor texture from (floor-coloured, on the floor)."""
    fill: str = "plane"
    """plane: inpaint_plane (floor texture from anywhere on the face: thin legs); ring: ring_fill (a solid base's
    large hole, from the floor ring just outside it alone)."""


@dataclass
class NadirFace:
    """The downward face of a panorama and what detection measures on it."""

    view: PerspectiveView
    face: np.ndarray
    """(size, size, 3) uint8."""
    theta: np.ndarray
    """Degrees from the nadir per face pixel."""
    phi: np.ndarray
    """Azimuth (radians) per face pixel."""
    on_floor: np.ndarray
    """Face pixels on the floor plane by depth (all True without depth or floor height)."""
    ring_floor: np.ndarray
    """The floor ring RING_DEG's on-floor pixels: what 'floor' looks like."""
    depth: np.ndarray | None = None
    valid: np.ndarray | None = None


def nadir_face(rgb: np.ndarray, depth: np.ndarray | None, valid: np.ndarray | None, floor_m: float | None) -> NadirFace:
    view = nadir_view(rgb.shape[0])
    theta, phi = face_polar(view)
    on_floor = np.ones(theta.shape, bool)
    fd = fv = None
    if depth is not None and valid is not None:
        fd, fv = face_depth(depth, valid, view)
        if floor_m:
            drop = fd * np.cos(np.deg2rad(theta))  # vertical distance below the camera
            on_floor = ~fv | (np.abs(drop - floor_m) < 0.05 * floor_m)
    ring = (theta >= RING_DEG[0]) & (theta < RING_DEG[1])
    return NadirFace(view, render_view(rgb, view), theta, phi, on_floor, ring & on_floor, fd, fv)


def no_floor_ring(nf: NadirFace) -> RigDetection | None:
    """The refusal when the floor ring is mostly not floor (nothing to compare the nadir with), else None."""
    ring = (nf.theta >= RING_DEG[0]) & (nf.theta < RING_DEG[1])
    share = float(nf.ring_floor.sum() / max(ring.sum(), 1))
    if share >= 0.3:
        return None
    return RigDetection(False, f"the floor ring {RING_DEG[0]:.0f}-{RING_DEG[1]:.0f} deg from the nadir is mostly "
                        "not floor: nothing to compare the nadir with", stats={"ring_floor_share": share})


def face_shadow(nf: NadirFace, face: np.ndarray, rig_px: np.ndarray) -> tuple[np.ndarray, float, dict]:
    """rig_shadow.shadow_gain on the face's floor (by depth and chroma), the rig pixels rig_px left out."""
    chroma = floor_chroma(face, nf.ring_floor)
    lum = linear_luminance(face)
    not_floor = rig_px & (~nf.on_floor | ~chroma | (lum < 0.3 * np.median(lum[nf.ring_floor])))
    return shadow_gain(face, dilate_rim(not_floor, nf.view), nf.on_floor & chroma, nf.theta, nf.phi, nf.view.focal)


def floor_source(face: np.ndarray, nf: NadirFace) -> np.ndarray:
    """Face pixels the inpainting may copy floor texture from: floor-coloured and on the floor."""
    return floor_coloured(cv2.cvtColor(cv2.medianBlur(face, 3), cv2.COLOR_RGB2LAB), nf.ring_floor) & nf.on_floor


def reaches_cap(nf: NadirFace, comp: np.ndarray) -> bool:
    """Whether the candidate comp reaches CAP_DEG from the nadir (larger than any rig)."""
    px_deg = np.rad2deg(1.0 / nf.view.focal)
    return int((comp & (nf.theta > CAP_DEG - 2 * px_deg - 0.5)).sum()) > 3


def seen_object(nf: NadirFace, comp: np.ndarray, floor_m: float | None) -> RigDetection | None:
    """The refusal for a candidate that is a seen object (reaches CAP_DEG, or a horizontal surface above the
    floor in depth), else None."""
    if reaches_cap(nf, comp):
        return RigDetection(False, f"the region under the camera reaches {CAP_DEG:.0f} deg from the nadir: larger than "
                            "any rig (a rug, furniture, a floor pattern), kept")
    table = horizontal_surface(nf.theta[comp], nf.depth[comp] if nf.depth is not None else None,
                                nf.valid[comp] if nf.valid is not None else None, floor_m)
    if table is not None:
        return RigDetection(False, f"the region under the camera is a horizontal surface {table:.2f} m below the "
                            f"camera, above the floor: a seen object (a table, a stool), kept",
                            stats={"surface_below_camera_m": table})
    return None


def floor_chroma(face: np.ndarray, ring_floor: np.ndarray) -> np.ndarray:
    """Face pixels of a chroma (Lab a, b) the floor ring shows, at any lightness: floor, shadowed or not."""
    lab = cv2.cvtColor(cv2.medianBlur(face, 3), cv2.COLOR_RGB2LAB)
    lab[..., 0] = 128
    return floor_coloured(lab, ring_floor)


def dilate_rim(mask: np.ndarray, view: PerspectiveView) -> np.ndarray:
    """Grow a face mask over the rig's anti-aliased rim and highlights (1 px at 256 rows: a wider margin replaces
    seen floor by a guess)."""
    k = 2 * max(1, view.size // 180) + 1
    return cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0


def floor_coloured(lab: np.ndarray, ring_floor: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """Pixels (size, size) whose Lab colour the floor ring shows: a 16x32x32 histogram of the ring's colours
    smoothed by sigma bins, thresholded so that 98 % of the ring's own pixels pass."""
    bins = (16, 32, 32)
    idx = tuple((lab[..., k].astype(np.int32) * bins[k]) >> 8 for k in range(3))
    hist = np.zeros(bins)
    np.add.at(hist, tuple(i[ring_floor] for i in idx), 1.0)
    hist = ndimage.gaussian_filter(hist, sigma, mode="constant")
    dens = hist[idx]
    return dens >= np.percentile(dens[ring_floor], 2.0)


def unlike_floor(face: np.ndarray, ring_floor: np.ndarray, view: PerspectiveView, sigma: float = 1.0) -> np.ndarray:
    """Face pixels (size, size) bool whose colour the floor pixels ring_floor (almost) never show, or far darker
    (< 0.6x) than the floor around them (thin dark legs on a floor whose grout lines are dark too)."""
    lab = cv2.cvtColor(cv2.medianBlur(face, 3), cv2.COLOR_RGB2LAB)
    floor_like = floor_coloured(lab, ring_floor, sigma)
    win = 2 * max(5, view.size // 24) + 1
    local = cv2.medianBlur(lab[..., 0], min(win, 255)).astype(np.float32)
    floor_l = float(np.median(lab[..., 0][ring_floor]))
    return ~floor_like | (lab[..., 0] < 0.6 * np.maximum(local, floor_l))
