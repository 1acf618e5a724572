"""Capture-rig detection at the panorama's nadir: tripod legs, a mount, a black nadir mask, a solid base (docs/rig.md)."""

from __future__ import annotations

import cv2
import numpy as np

from panoworld.depth.rig.base import detect_base
from panoworld.depth.rig.face import (
    FACE_FOV_DEG,
    erp_mask_to_face,
    face_polar,
    face_to_erp_mask,
)
from panoworld.depth.rig.nadir import (
    CAP_DEG,
    NadirFace,
    RigDetection,
    dilate_rim,
    face_shadow,
    floor_source,
    nadir_face,
    no_floor_ring,
    reaches_cap,
    seen_object,
    unlike_floor,
)
from panoworld.depth.rig.shadow import cast_shadows, leg_shadow_lines, relights
from panoworld.depth.rig.shape import (
    MIN_LEG_WIDTH_DEG,
    azimuth_occupancy,
    leg_arms,
    opened,
    without_floor_lines,
)
from panoworld.geometry.cube_views import PerspectiveView, render_view
from panoworld.room.light import apply_gain

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


def detect_rig(rgb: np.ndarray, depth: np.ndarray | None = None, valid: np.ndarray | None = None,
               floor_m: float | None = None) -> RigDetection:
    """Find a capture rig at the nadir of rgb (H, W, 3) uint8; depth/valid (H, W) and the camera's height above the
    floor floor_m (depth units) are optional evidence. Never takes a region reaching CAP_DEG, a solid blob larger
    than MOUNT_MAX_DEG that is not a uniform black mask, or a horizontal surface above the floor (a table).

    Floor colours are first taken broadly (a blotchy concrete floor stays floor); when that finds no rig, once more
    narrowly (a grey mount on a brown floor in shade); the shape tests decide either way. When that finds no rig or
    only a mount, a solid camera base is looked for (detect_base): found, it replaces the mount."""
    nf = nadir_face(rgb, depth, valid, floor_m)  # read, never written, by every look below
    first = _detect_once(rgb, nf, floor_m, FLOOR_SIGMAS[0])
    if not first.found:
        second = _detect_once(rgb, nf, floor_m, FLOOR_SIGMAS[1])
        first = second if second.found else first
    if first.found and first.kind != "mount":
        return first
    base = detect_base(rgb, depth, valid, floor_m, nf=nf)  # a mount's blob is taken whole with its legs, the rest refused
    if base.found:
        return base
    first.stats["base"] = base.reason
    return first


def _detect_once(rgb, nf: NadirFace, floor_m, sigma: float) -> RigDetection:
    H, W = rgb.shape[:2]
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
        mask = face_to_erp_mask(dilate_rim(black, view), view, H, W)
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
    obj = dilate_rim(obj, view) | cast_shadows(lab, obj > 0, theta, view.focal, CAP_DEG)
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
