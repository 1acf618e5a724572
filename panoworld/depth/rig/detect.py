"""Capture-rig detection and removal at the panorama's nadir, on the downward cube face (docs/rig.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from panoworld.core.conventions import erp_dirs, erp_pixel_solid_angle
from panoworld.core.errors import InputError
from panoworld.depth.rig.base import BASE_BG_DEG, attached_legs, base_component, base_stats, grabcut_nadir, is_base
from panoworld.depth.rig.face import (
    FACE_FOV_DEG,
    erp_mask_to_face,
    face_depth,
    face_polar,
    face_to_erp,
    face_to_erp_mask,
    nadir_view,
)
from panoworld.depth.rig.inpaint import inpaint_plane, matte_rim
from panoworld.depth.rig.shadow import cast_shadows, leg_shadow_lines, linear_luminance, relights, shadow_gain
from panoworld.depth.rig.shape import (
    MIN_LEG_WIDTH_DEG,
    azimuth_occupancy,
    horizontal_surface,
    leg_arms,
    opened,
    without_floor_lines,
)
from panoworld.geometry.cube_views import PerspectiveView, render_view
from panoworld.io.images import check_mask_file, read_image
from panoworld.room.light import apply_gain

CAP_DEG = 30.0
"""Largest rig: candidates must lie within this angle of the nadir (a tripod's feet reach 15-25 degrees)."""
RING_DEG = (30.0, 42.0)
"""The floor ring whose colours define 'floor' for the cap inside it."""
MOUNT_MAX_DEG = 20.0
"""A solid blob at the nadir (a camera mount without visible legs) is a rig only up to this angle."""
FLOOR_SIGMAS = (1.0, 0.6)
"""Smoothing (histogram bins) of the floor ring's colours: broad first, narrow when the broad pass finds no rig."""
HUB_DEG = 6.0
"""Anomalous regions reaching this close to the nadir are candidates (the mount and the roots of the legs)."""
RIG_DROP_MAX = 0.6
"""With depth, a candidate reaching CAP_DEG is looked at once more without what cannot be the rig: surfaces off the
floor plane whose vertical drop below the camera exceeds this share of the camera's height (walls and furniture at the
cap's edge; the rig hangs from the camera: its hub and most of its legs lie far above the floor) and thin lines on the
floor plane (grout, plank seams, leg shadows: narrower than FLOOR_LINE_DEG): at 720 rows grout can tie a tripod's
legs to the walls beside it, and the whole would be refused as reaching 30 deg."""
SURFACE_DEG = 4.0
"""Only far surfaces at least this wide are left out in that second look (the lower half of a leg lies far below
the camera too, but is 1-2 degrees wide)."""
FLOOR_LINE_DEG = 1.0
"""On-floor candidate pixels narrower than this (a morphological opening) are floor lines, not rig, in that second look."""
LEG_SHADOW_WIDTH_DEG = 0.75
"""A leg's cast-shadow line must be dark this wide across (a 3.6 cm leg's shadow is >= 1.2 deg): floor lines are
narrower. Tested only where its half-width exceeds a face pixel (at 720 rows, not 256)."""


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


def detect_rig(rgb: np.ndarray, depth: np.ndarray | None = None, valid: np.ndarray | None = None,
               floor_m: float | None = None) -> RigDetection:
    """Find a capture rig at the nadir of rgb (H, W, 3) uint8; depth/valid (H, W) and the camera's height above the
    floor floor_m (depth units) are optional evidence. Never takes a region reaching CAP_DEG, a solid blob larger
    than MOUNT_MAX_DEG that is not a uniform black mask, or a horizontal surface above the floor (a table).

    Floor colours are first taken broadly (a blotchy concrete floor stays floor); when that finds no rig, once more
    narrowly (a grey mount on a brown floor in shade); the shape tests decide either way. When that finds no rig or
    only a mount, a solid camera base is looked for (detect_base): found, it replaces the mount."""
    first = _detect_once(rgb, depth, valid, floor_m, FLOOR_SIGMAS[0])
    if not first.found:
        second = _detect_once(rgb, depth, valid, floor_m, FLOOR_SIGMAS[1])
        first = second if second.found else first
    if first.found and first.kind != "mount":
        return first
    base = detect_base(rgb, depth, valid, floor_m)  # a mount's blob is taken whole with its legs, the rest refused
    if base.found:
        return base
    first.stats["base"] = base.reason
    return first


def detect_base(rgb: np.ndarray, depth: np.ndarray | None = None, valid: np.ndarray | None = None,
                floor_m: float | None = None) -> RigDetection:
    """A solid camera base at the nadir (panoworld.depth.rig.base): GrabCut on the downward face, compared with the floor
    that is there (on the floor plane by depth, BASE_BG_DEG-42 deg from the nadir: in a narrow hallway nearer than the
    floor ring); a region that is no compact, centred body unlike that floor and closed by it is kept."""
    H, W = rgb.shape[:2]
    nf = nadir_face(rgb, depth, valid, floor_m)
    ref = nf.on_floor & (nf.theta >= BASE_BG_DEG) & (nf.theta < RING_DEG[1])
    share = float(ref.sum() / max(((nf.theta >= BASE_BG_DEG) & (nf.theta < RING_DEG[1])).sum(), 1))
    if share < 0.15:
        return RigDetection(False, f"no floor {BASE_BG_DEG:.0f}-{RING_DEG[1]:.0f} deg from the nadir to compare a "
                            "camera base with", stats={"base_floor_share": share})
    comp = base_component(grabcut_nadir(nf.face, nf.theta), nf.theta)
    if comp is None:
        return RigDetection(False, "no region at the nadir stands out from the floor")
    unlike = unlike_floor(nf.face, ref, nf.view)
    stats = base_stats(comp, nf.theta, unlike)
    why = is_base(stats)
    if why is None and (refusal := seen_object(nf, comp, floor_m)) is not None:
        why = refusal.reason
    if why is not None:
        return RigDetection(False, f"the region at the nadir is no camera base: {why}, kept", stats=stats)
    legs = attached_legs(comp, unlike, nf.theta, nf.view.focal)
    stats["leg_pixels"] = int(legs.sum())
    mask = face_to_erp_mask(cv2.dilate((comp | legs).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0, nf.view, H, W)
    return RigDetection(True, f"a solid camera base centred on the nadir, {stats['cap_deg']:.1f} deg, unlike the floor "
                        "around it", "base", mask, np.zeros_like(mask), stats, source=floor_source(nf.face, nf))


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
    chroma = _floor_chroma(face, nf.ring_floor)
    lum = linear_luminance(face)
    not_floor = rig_px & (~nf.on_floor | ~chroma | (lum < 0.3 * np.median(lum[nf.ring_floor])))
    return shadow_gain(face, _dilate(not_floor, nf.view), nf.on_floor & chroma, nf.theta, nf.phi, nf.view.focal)


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


def _detect_once(rgb, depth, valid, floor_m, sigma: float) -> RigDetection:
    H, W = rgb.shape[:2]
    nf = nadir_face(rgb, depth, valid, floor_m)
    refusal = no_floor_ring(nf)
    if refusal is not None:
        return refusal
    view, face, theta, phi, ring_floor = nf.view, nf.face, nf.theta, nf.phi, nf.ring_floor
    stats: dict = {}
    source = floor_source(face, nf)
    black = _black_mask(face, theta, view)
    if black is not None:
        extent = float(np.percentile(theta[black], 98))
        stats.update(cap_deg=extent, face_pixels=int(black.sum()))
        mask = face_to_erp_mask(_dilate(black, view), view, H, W)
        return RigDetection(True, f"a uniform black patch centred on the nadir, {extent:.1f} deg (a nadir mask)",
                            "mask", mask, np.zeros_like(mask), stats, source=source)
    comp = _nadir_component(face, theta, ring_floor, view, sigma)
    if comp is None:
        return RigDetection(False, "nothing at the nadir differs in colour from the floor ring around it", stats=stats)
    # A region that reaches CAP_DEG before any shadow is divided out is a seen object (a dark rug read as a shadow
    # would leave a mount-sized remainder), unless what reaches it cannot be the rig by depth (RIG_DROP_MAX).
    refusal = seen_object(nf, comp, floor_m)
    not_rig = None
    if reaches_cap(nf, comp):
        not_rig, comp2 = _second_look(nf, face, sigma, floor_m)
        if comp2 is not None and seen_object(nf, comp2, floor_m) is None:
            comp, refusal = comp2, None
            stats["second_look"] = SECOND_LOOK
    if refusal is not None:
        return refusal
    # A soft shadow around the rig is divided out first, so that only the rig itself is measured below.
    gain, sh_deg, sh_stats = face_shadow(nf, face, comp)
    stats.update(sh_stats)
    if sh_deg > 0:
        face = apply_gain(face, gain)
        source = floor_source(face, nf)
        comp = _nadir_component(face, theta, ring_floor, view, sigma, not_rig)
        if comp is not None and not_rig is None and reaches_cap(nf, comp):  # relit, the legs' cast shadows join
            not_rig, comp2 = _second_look(nf, face, sigma, floor_m)
            if comp2 is not None and not reaches_cap(nf, comp2):
                comp = comp2
                stats["second_look"] = SECOND_LOOK
        if comp is None:
            return RigDetection(False, f"a soft shadow at the nadir ({sh_deg:.0f} deg) but nothing under it that "
                                "differs from the floor: kept", stats=stats)
    lab = cv2.cvtColor(cv2.medianBlur(face, 3), cv2.COLOR_RGB2LAB)
    t, p = theta[comp], phi[comp]
    extent = float(np.percentile(t, 98))
    px_deg = np.rad2deg(1.0 / view.focal)
    ring_lum = float(np.median(lab[..., 0][ring_floor]))
    comp_lum = float(np.median(lab[..., 0][comp]))
    stats.update(cap_deg=extent, face_pixels=int(comp.sum()), darkness=1.0 - comp_lum / max(ring_lum, 1.0),
                 lum_std=float(lab[..., 0][comp].std()))
    occ_in, arms_in = azimuth_occupancy(p[(t > 0.3 * extent) & (t < 0.7 * extent)])
    occ_out, arms_out = azimuth_occupancy(p[(t > 0.45 * extent) & (t < 0.85 * extent)])
    stats.update(occupancy_inner=occ_in, occupancy_outer=occ_out, arms=arms_out)
    n_legs, occ_legs, widths = leg_arms(comp, theta, phi, view.focal, extent)
    widths = sorted(widths, reverse=True)
    stats.update(legs=n_legs, occupancy_legs=occ_legs, arm_widths_deg=[round(w, 3) for w in widths[:8]])
    refusal = seen_object(nf, comp, floor_m)
    if refusal is not None:
        refusal.stats = {**stats, **refusal.stats}
        return refusal
    yy, xx = np.nonzero(comp)
    r_mean = float(np.mean(np.hypot(xx + 0.5 - 0.5 * view.size, yy + 0.5 - 0.5 * view.size))) + 1e-9
    off = float(np.hypot(xx.mean() + 0.5 - 0.5 * view.size, yy.mean() + 0.5 - 0.5 * view.size)) / r_mean
    stats["centroid_offset"] = off
    kind = reason = None
    hub_seen = bool((t < HUB_DEG / 2).any())
    hub_legs = extent >= 6.0 and hub_seen and off < 0.5 and stats["darkness"] > 0.2
    if hub_legs and 3 <= n_legs <= 6 and occ_legs <= 0.5:
        kind, reason = "legs", f"{n_legs} thin arms from a hub at the nadir out to {extent:.1f} deg (tripod legs)"
    elif occ_in >= 0.9 and off < 0.35 and extent >= max(2.0, 3 * px_deg):
        if extent <= MOUNT_MAX_DEG:
            kind, reason = "mount", f"a solid blob centred on the nadir, {extent:.1f} deg, unlike the floor (camera mount)"
    if kind is None and hub_legs and 3 <= arms_out <= 6 and occ_out <= 0.5:
        return RigDetection(False, f"{arms_out} arms from the nadir out to {extent:.1f} deg, {n_legs} of them as wide "
                            f"as a tripod leg (>= {MIN_LEG_WIDTH_DEG} deg; the third widest {widths[2]:.2f}): lines "
                            "of the floor's texture (grout, plank seams), kept", stats=stats)
    if kind is None:
        return RigDetection(False, f"a {extent:.1f} deg region at the nadir that is neither tripod legs nor a centred "
                            f"mount (occupancy {occ_in:.2f}/{occ_out:.2f}, {arms_out} arms, "
                            f"offset {off:.2f}): a seen object, kept", stats=stats)
    obj = comp.astype(np.uint8)
    if kind == "legs":  # the hub between the legs' roots, floor-coloured parts of the mount included
        hub = np.argwhere(comp & (theta < 0.4 * extent))[:, ::-1].astype(np.int32)
        if len(hub) >= 3:
            cv2.fillConvexPoly(obj, cv2.convexHull(hub), 1)
    obj = without_floor_lines(obj > 0, nf.on_floor, view.focal).astype(np.uint8)
    obj = _dilate(obj, view) | cast_shadows(lab, obj > 0, theta, view.focal, CAP_DEG)
    stats["shadow_deg"] = sh_deg
    mask = face_to_erp_mask(obj, view, H, W)
    if kind == "legs":
        mask |= _leg_shadows(rgb, mask, gain, view)
    if not relights(stats):  # the rig was measured relit, the floor stays
        gain = np.ones_like(gain)
    sh = face_to_erp_mask(gain > 1.0, view, H, W) & ~mask
    if sh.any():
        reason += f" with its shadow ({sh_deg:.0f} deg, up to {1 - 1 / gain.max():.0%} darker)"
    return RigDetection(True, reason, kind, mask, sh, stats, shadow_gain=gain, source=source)


def _leg_shadows(rgb: np.ndarray, mask: np.ndarray, gain: np.ndarray, view: PerspectiveView) -> np.ndarray:
    """ERP pixels of the legs' thin cast shadows (rig_shadow.leg_shadow_lines) on a downward face at twice the
    resolution (a shadow line is 1-2 ERP pixels wide), relit by the soft shadow's gain."""
    H, W = rgb.shape[:2]
    fine = PerspectiveView(view.cam_from_view, FACE_FOV_DEG, 2 * view.size)
    g = cv2.resize(gain, (fine.size, fine.size), interpolation=cv2.INTER_LINEAR)
    face = apply_gain(render_view(rgb, fine), g)
    theta, _ = face_polar(fine)
    width = fine.focal * np.deg2rad(LEG_SHADOW_WIDTH_DEG)
    width = width if 0.5 * width >= 2.0 else 0.0  # resolvable: the half-width is more than one face pixel
    lines = leg_shadow_lines(face, theta, erp_mask_to_face(mask, fine), CAP_DEG, 2.0, width_px=width)
    return face_to_erp_mask(lines, fine, H, W) if lines.any() else np.zeros_like(mask)


def _floor_chroma(face: np.ndarray, ring_floor: np.ndarray) -> np.ndarray:
    """Face pixels of a chroma (Lab a, b) the floor ring shows, at any lightness: floor, shadowed or not."""
    lab = cv2.cvtColor(cv2.medianBlur(face, 3), cv2.COLOR_RGB2LAB)
    lab[..., 0] = 128
    return floor_coloured(lab, ring_floor)


def _dilate(mask: np.ndarray, view: PerspectiveView) -> np.ndarray:
    """Grow a face mask over the rig's anti-aliased rim and highlights (1 px at 256 rows: a wider margin replaces
    seen floor by a guess)."""
    k = 2 * max(1, view.size // 180) + 1
    return cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0


def _black_mask(face: np.ndarray, theta: np.ndarray, view: PerspectiveView) -> np.ndarray | None:
    """The near-black (every channel <= 12) region holding the nadir when it is a centred, convex-ish patch of 3 to
    CAP_DEG degrees (a capture system's nadir mask: a black disc or hexagon), else None."""
    black = (face.max(-1) <= 12).astype(np.uint8)
    _, labels = cv2.connectedComponents(black, connectivity=4)
    c = view.size // 2
    lab = labels[c, c]
    if lab == 0:
        return None
    comp = labels == lab
    t = theta[comp]
    extent = float(np.percentile(t, 98))
    if not 3.0 <= extent < CAP_DEG - 1.0:
        return None
    yy, xx = np.nonzero(comp)
    r = np.hypot(xx + 0.5 - 0.5 * view.size, yy + 0.5 - 0.5 * view.size)
    off = float(np.hypot(xx.mean() + 0.5 - 0.5 * view.size, yy.mean() + 0.5 - 0.5 * view.size)) / (r.mean() + 1e-9)
    hull = cv2.convexHull(np.stack([xx, yy], 1).astype(np.int32))
    solidity = comp.sum() / max(cv2.contourArea(hull), 1.0)
    return comp if off < 0.2 and solidity > 0.9 else None


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


def _not_rig_by_depth(nf: NadirFace, floor_m: float | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(off-floor pixels far below the camera, on-floor pixels) on the face (RIG_DROP_MAX), or None without depth."""
    if nf.depth is None or nf.valid is None or not floor_m:
        return None
    drop = nf.depth * np.cos(np.deg2rad(nf.theta))
    on = nf.valid & (np.abs(drop - floor_m) < 0.05 * floor_m)
    far = nf.valid & ~on & (drop > RIG_DROP_MAX * floor_m)
    k = 2 * int(np.ceil(0.5 * nf.view.focal * np.deg2rad(SURFACE_DEG))) + 1  # a leg's foot is far too, but thin
    return opened(far, k), on


SECOND_LOOK = "walls, furniture and floor lines left out by depth"


def _second_look(nf: NadirFace, face: np.ndarray, sigma: float, floor_m: float | None
                 ) -> tuple[tuple[np.ndarray, np.ndarray] | None, np.ndarray | None]:
    """What depth says is not the rig (_not_rig_by_depth) and the candidate of face rebuilt without it; (None, None)
    without depth."""
    not_rig = _not_rig_by_depth(nf, floor_m)
    if not_rig is None:
        return None, None
    return not_rig, _nadir_component(face, nf.theta, nf.ring_floor, nf.view, sigma, not_rig)


def _nadir_component(face: np.ndarray, theta: np.ndarray, ring_floor: np.ndarray, view: PerspectiveView,
                     sigma: float = 1.0, not_rig: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray | None:
    """Face pixels within CAP_DEG, connected to the nadir, whose colour the floor ring (almost) never shows or that
    are far darker than the floor around them; None when the nadir itself looks like floor. not_rig (far, on_floor):
    leave out far pixels and the on-floor ones narrower than FLOOR_LINE_DEG (_not_rig_by_depth)."""
    anom = (theta < CAP_DEG) & unlike_floor(face, ring_floor, view, sigma)
    if not_rig is not None:
        far, on = not_rig
        k = 2 * int(np.ceil(0.5 * view.focal * np.deg2rad(FLOOR_LINE_DEG))) + 1
        wide = opened(anom & on, k)
        anom = anom & ~far & (~on | wide)
    anom = cv2.morphologyEx(anom.astype(np.uint8), cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3)))
    _, labels = cv2.connectedComponents(anom, connectivity=8)
    seed = theta < HUB_DEG  # the mount may be floor-coloured; its legs start within a few degrees of the nadir
    hit = np.unique(labels[seed & (labels > 0)])
    if len(hit) == 0:
        return None
    comp = np.isin(labels, hit)
    k = 2 * max(5, view.size // 30) + 1
    near = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    for _ in range(2):  # parts cut off by a floor-coloured piece of the mount (a leg behind a grey hub)
        touch = np.unique(labels[(cv2.dilate(comp.astype(np.uint8), near) > 0) & (labels > 0)])
        comp = np.isin(labels, touch)
    return comp


def unlike_floor(face: np.ndarray, ring_floor: np.ndarray, view: PerspectiveView, sigma: float = 1.0) -> np.ndarray:
    """Face pixels (size, size) bool whose colour the floor pixels ring_floor (almost) never show, or far darker
    (< 0.6x) than the floor around them (thin dark legs on a floor whose grout lines are dark too)."""
    lab = cv2.cvtColor(cv2.medianBlur(face, 3), cv2.COLOR_RGB2LAB)
    floor_like = floor_coloured(lab, ring_floor, sigma)
    win = 2 * max(5, view.size // 24) + 1
    local = cv2.medianBlur(lab[..., 0], min(win, 255)).astype(np.float32)
    floor_l = float(np.median(lab[..., 0][ring_floor]))
    return ~floor_like | (lab[..., 0] < 0.6 * np.maximum(local, floor_l))


def read_user_mask(path: Path, H: int, W: int) -> np.ndarray:
    """A user rig mask (a 2:1 grayscale image, white = rig) -> (H, W) bool; InputError when not a 2:1 image."""
    check_mask_file(path)
    m = read_image(path, cv2.IMREAD_GRAYSCALE, what="rig mask")
    if m.shape[1] != 2 * m.shape[0]:
        raise InputError(f"{path}: rig mask is {m.shape[1]}x{m.shape[0]} but must be 2:1 like the panorama")
    return cv2.resize(m, (W, H), interpolation=cv2.INTER_NEAREST) > 127


# ---------------------------------------------------------------- removal


def remove_rig(rgb: np.ndarray, det: RigDetection) -> np.ndarray:
    """The panorama with the rig inpainted and its shadow relit on the downward face, changed only inside the
    masks (H, W, 3) uint8. The rig: Telea inpainting for the low frequencies plus the texture of the best-matching
    floor patch elsewhere on the face (the floor is a plane there, so its texture repeats under translation); the
    mask's rim is matted between the rig's colour and the fill (rig_inpaint.matte_rim)."""
    H, W = rgb.shape[:2]
    view = nadir_view(H)
    face = render_view(rgb, view).astype(np.float32)
    obj = erp_mask_to_face(det.mask, view)  # not grown further: a wider hole replaces seen floor by a guess
    lin = (face / 255.0) ** 2.2
    if det.shadow_gain is not None:
        lin = lin * det.shadow_gain[..., None]
    source = det.source if det.source is not None and det.source.shape == obj.shape else np.ones_like(obj)
    clean = inpaint_plane(np.clip(lin, 0, 1) ** (1 / 2.2) * 255.0, obj, source)
    back = face_to_erp(clean, view, H, W)
    lit = rgb
    if det.shadow_gain is not None:  # the rim's floor is matted in the relit panorama
        lit = apply_gain(rgb, face_to_erp(det.shadow_gain, view, H, W, 1.0))
    out = rgb.copy()
    out[det.mask] = np.clip(np.rint(matte_rim(lit, back, det.mask)[det.mask]), 0, 255).astype(np.uint8)
    if det.shadow is not None and det.shadow_gain is not None:  # relit where it is: the texture is not resampled
        sh = det.shadow & ~det.mask
        out[sh] = lit[sh]
    return out


def floor_depth(H: int, W: int, floor_m: float) -> np.ndarray:
    """Ray distance (H, W) to the horizontal floor floor_m below the camera (0 where a ray does not look down)."""
    down = erp_dirs(H, W, np.float64)[..., 1]
    return np.where(down > 1e-3, floor_m / np.maximum(down, 1e-3), 0.0).astype(np.float32)


def area_stats(mask: np.ndarray) -> dict:
    """Solid-angle share of the sphere and the cap (degrees from the nadir) holding 98 % of a mask's pixels."""
    H, W = mask.shape
    omega = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    frac = float(omega[mask].sum() / (4 * np.pi))
    rows = np.nonzero(mask.any(1))[0]
    cap = float(180.0 - (rows.min() + 0.5) / H * 180.0) if len(rows) else 0.0
    return {"sphere_fraction": frac, "cap_deg": cap, "pixels": int(mask.sum())}


# ---------------------------------------------------------------- the depth stage's step


def rig_step(rgb: np.ndarray, depth: np.ndarray, valid: np.ndarray, floor_m: float | None, *,
             user_mask: Path | None = None, detect=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, RigDetection]:
    """Detect with detect(rgb, depth, valid, floor_m) (default detect_rig), or take the user's mask, and remove the
    rig: (rgb, depth, valid, info, detection). Inside the rig
    mask depth comes from the floor plane floor_m below the camera (invalid when no floor was found); outside the
    masks nothing changes (no rig: the very same arrays)."""
    H, W = rgb.shape[:2]
    if user_mask is not None:
        m = read_user_mask(user_mask, H, W)
        det = RigDetection(bool(m.any()), f"user mask {Path(user_mask).name}", "user", m, np.zeros_like(m))
    else:
        det = (detect or detect_rig)(rgb, depth, valid, floor_m)
    info = {"found": det.found, "reason": det.reason, "kind": det.kind,
            "stats": {k: (round(v, 4) if isinstance(v, float) else v) for k, v in det.stats.items()}}
    if not det.found:
        return rgb, depth, valid, info, det
    rgb = remove_rig(rgb, det)
    info["mask"] = area_stats(det.mask)
    info["shadow"] = area_stats(det.shadow)
    depth, valid = depth.copy(), valid.copy()
    if floor_m:
        plane = floor_depth(H, W, floor_m)
        put = det.mask & (plane > 0)
        depth[put], valid[put] = plane[put], True
        valid[det.mask & ~put] = False
        info["depth"] = f"floor plane {floor_m:.3f} m below the camera"
    else:
        valid[det.mask] = False
        info["depth"] = "no floor found: depth under the rig made invalid"
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    return rgb, depth, valid, info, det


def nadir_luminance_gap(rgb: np.ndarray, cap_deg: float = 15.0) -> float:
    """Relative difference of the mean luminance (solid-angle weighted) of the cap within cap_deg of the nadir and
    of the floor ring RING_DEG around it: (cap - ring) / ring, e.g. -0.5 for a cap half as bright (a dark mount)."""
    H, W = rgb.shape[:2]
    theta = (np.arange(H) + 0.5) / H * 180.0  # degrees from the zenith
    from_nadir = 180.0 - theta
    lum = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64).mean(1)
    w = erp_pixel_solid_angle(H, W)[:, 0]
    cap = from_nadir < cap_deg
    ring = (from_nadir >= RING_DEG[0]) & (from_nadir < RING_DEG[1])
    lc = float((lum * w)[cap].sum() / w[cap].sum())
    lr = float((lum * w)[ring].sum() / w[ring].sum())
    return (lc - lr) / max(lr, 1e-6)


def nadir_cap_psnr(a: np.ndarray, b: np.ndarray, deg: float = 15.0) -> float:
    """Solid-angle weighted PSNR (dB) of two ERP images (H, W, 3) uint8 over the cap within deg of the nadir."""
    h, w = a.shape[:2]
    r0 = int(h * (1.0 - deg / 180.0))
    wt = np.broadcast_to(erp_pixel_solid_angle(h, w)[r0:], (h - r0, w))[..., None]
    mse = float((wt * (a[r0:].astype(np.float64) - b[r0:]) ** 2).sum() / (3 * wt.sum()))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))
