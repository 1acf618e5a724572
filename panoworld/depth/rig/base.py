"""A solid camera base at the nadir (a camera body or stitched base with its tripod's legs), segmented by GrabCut on the downward face (docs/rig.md)."""

from __future__ import annotations

import cv2
import numpy as np

from panoworld.depth.rig.face import face_to_erp_mask
from panoworld.depth.rig.nadir import (
    RING_DEG,
    NadirFace,
    RigDetection,
    floor_source,
    nadir_face,
    seen_object,
    unlike_floor,
)

BASE_FG_DEG = 10.0
"""GrabCut starts with everything within this angle of the nadir as probably the rig."""
BASE_BG_DEG = 27.0
"""... and everything beyond this angle as surely not the rig (a tripod's feet reach 20-25 deg)."""
BASE_MAX_DEG = 24.0
"""The base (its 98th-percentile angle from the nadir) lies within this angle; a larger region is a seen object."""
LEG_MAX_DEG = 2.0
"""Parts of the rig narrower than this that touch the base are its legs (attached_legs)."""
LEG_MIN_ASPECT = 3.0
"""... and at least this elongated (attached_legs)."""
LEG_MIN_DARK = 0.15
"""A leg's pixel is darker than the lightest pixel within LEG_MAX_DEG of it by at least this share of that lightness
(radial_legs) ..."""
LEG_MIN_DEG = 3.0
"""... on a straight run at least this long ..."""
LEG_RADIAL_DEG = 30.0
"""... within this angle of the direction away from the nadir ..."""
LEG_REACH_DEG = 1.5
"""... with an end within this angle of the base ..."""
LEG_WIDTH_DEG = 0.6
"""... and its pixels within this angle of the line."""
LEG_FOOT_DEG = 3.0
"""A dark blob touching the rig no larger than a disc this wide is its foot or tip (rig_feet)."""
BASE_MAX_OFFSET = 0.4
"""Its centroid lies within this share of its mean radius of the nadir (the camera stands above it)."""
BASE_MIN_SOLIDITY = 0.6
"""Its area over its convex hull's (a compact body; legs lower it, floor patches scatter it)."""
BASE_MIN_UNLIKE = 0.7
"""At least this share of its pixels has a colour the floor around it (almost) never shows, or is far darker ..."""
BASE_MIN_UNLIKE_OUTLINED = 0.4
"""... or at least this share when its outline is an edge all round (BASE_MIN_OUTLINE): a beige base on a carpet
that shows beige too."""
SIDE_GAP_DEG = 8.0
"""A separate piece of the rig (the base's side bar beyond a gap) lies within this angle of the base (side_pieces)."""
SIDE_MAX_DEG = 29.0
"""... lies wholly within this angle of the nadir (a side bar reaches ~27 deg; what goes on past it is floor or
furniture) ..."""
SIDE_MAX_SHARE = 0.25
"""... and is at most this share of the base's area ..."""
SIDE_MIN_SHARE = 0.025
"""... and at least this share (the bar: 3-4 % of the base; the floor's speckle falls apart smaller) ..."""
SIDE_MIN_ON_FLOOR = 0.9
"""... and this share of it on the floor plane by depth ..."""
SIDE_MIN_SOLIDITY = 0.7
"""... and solid (a bar or a knob; a patch of the floor's texture is ragged)."""
BASE_MIN_OUTLINE = 0.85
"""Share of the outline's pixels whose colour gradient exceeds the floor's 90th percentile (outline_edges); a region
cut out of the floor's own texture scores about 0.1 (its outline meets the floor's strong gradients at random)."""


def grabcut_nadir(face: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """GrabCut of the downward face (size, size, 3) uint8 around the nadir: probable rig within BASE_FG_DEG, probable
    floor out to BASE_BG_DEG, sure floor beyond; (size, size) bool foreground. Runs on the square holding 30 deg."""
    size = face.shape[0]
    c = size // 2
    r = min(c, int(np.count_nonzero(theta[c, c:] < 30.0)) + 2)
    sl = (slice(c - r, c + r), slice(c - r, c + r))
    t = theta[sl]
    m = np.full(t.shape, cv2.GC_PR_BGD, np.uint8)
    m[t < BASE_FG_DEG] = cv2.GC_PR_FGD
    m[t >= BASE_BG_DEG] = cv2.GC_BGD
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.setRNGSeed(0)
    cv2.grabCut(np.ascontiguousarray(face[sl]), m, None, bgd, fgd, 5, cv2.GC_INIT_WITH_MASK)
    out = np.zeros(theta.shape, bool)
    out[sl] = (m == cv2.GC_FGD) | (m == cv2.GC_PR_FGD)
    return out


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """mask (S, S) bool with its enclosed holes filled."""
    inv = np.pad(~mask, 1, constant_values=True).astype(np.uint8)
    cv2.floodFill(inv, None, (0, 0), 0)
    return mask | (inv[1:-1, 1:-1] > 0)


def base_component(fg: np.ndarray, theta: np.ndarray) -> np.ndarray | None:
    """The foreground's components reaching within 4 deg of the nadir, holes filled; None when none does."""
    _, labels = cv2.connectedComponents(fg.astype(np.uint8), connectivity=8)
    hit = np.unique(labels[(theta < 4.0) & (labels > 0)])
    return fill_holes(np.isin(labels, hit)) if len(hit) else None


def base_stats(comp: np.ndarray, theta: np.ndarray, unlike: np.ndarray) -> dict:
    """Shape and contrast of a nadir region comp (S, S) bool: extent (98th-percentile deg), centroid offset (share of
    its mean radius), solidity and its share of pixels unlike the floor (unlike, (S, S) bool)."""
    size = comp.shape[0]
    yy, xx = np.nonzero(comp)
    c = 0.5 * size
    r = np.hypot(xx + 0.5 - c, yy + 0.5 - c)
    hull = cv2.convexHull(np.stack([xx, yy], 1).astype(np.int32))
    return {"cap_deg": float(np.percentile(theta[comp], 98)),
            "centroid_offset": float(np.hypot(xx.mean() + 0.5 - c, yy.mean() + 0.5 - c) / (r.mean() + 1e-9)),
            "solidity": float(comp.sum() / max(cv2.contourArea(hull), 1.0)),
            "unlike_floor": float(unlike[comp].mean()),
            "face_pixels": int(comp.sum())}


def is_base(st: dict) -> str | None:
    """Why the region measured by base_stats is not a camera base, or None when it is."""
    if st["cap_deg"] > BASE_MAX_DEG:
        return f"reaches {st['cap_deg']:.1f} deg (> {BASE_MAX_DEG:.0f})"
    if st["centroid_offset"] > BASE_MAX_OFFSET:
        return f"off the nadir (centroid offset {st['centroid_offset']:.2f})"
    if st["solidity"] < BASE_MIN_SOLIDITY:
        return f"not compact (solidity {st['solidity']:.2f})"
    outlined = st.get("outline_edges", 0.0) >= BASE_MIN_OUTLINE
    if st["unlike_floor"] < (BASE_MIN_UNLIKE_OUTLINED if outlined else BASE_MIN_UNLIKE):
        return (f"mostly floor-coloured ({st['unlike_floor']:.0%} unlike the floor, "
                f"{st.get('outline_edges', 0.0):.0%} of its outline an edge)")
    return None


def outline_edges(face: np.ndarray, comp: np.ndarray, floor: np.ndarray, focal: float) -> float:
    """Share of the outline pixels of comp (size, size) bool whose Lab gradient (the face smoothed by 0.3 deg, so
    a carpet's grain does not count; the largest within a pixel) exceeds the 90th percentile of the floor's (floor,
    (size, size) bool)."""
    lab = cv2.cvtColor(cv2.GaussianBlur(face, (0, 0), 0.3 * focal * np.deg2rad(1.0)), cv2.COLOR_RGB2LAB)
    lab = lab.astype(np.float32)
    g = np.sqrt((cv2.Sobel(lab, cv2.CV_32F, 1, 0) ** 2 + cv2.Sobel(lab, cv2.CV_32F, 0, 1) ** 2).sum(-1))
    g = cv2.dilate(g, np.ones((3, 3), np.uint8))
    rim = comp & ~(cv2.erode(comp.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    if not rim.any() or not floor.any():
        return 0.0
    return float((g[rim] > np.percentile(g[floor], 90)).mean())


def attached_legs(comp: np.ndarray, unlike: np.ndarray, theta: np.ndarray, focal: float) -> np.ndarray:
    """Thin parts (narrower than LEG_MAX_DEG) of the pixels unlike the floor (unlike, (S, S) bool) that touch the base
    comp and end before BASE_BG_DEG: the tripod's legs and the mount's thin pieces; a line that goes on (a door
    trim, a long cast shadow) is left. (S, S) bool."""
    k = 2 * int(round(0.5 * focal * np.deg2rad(LEG_MAX_DEG))) + 1
    ell = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    u = unlike & (theta < BASE_BG_DEG)
    thin = u & ~(cv2.morphologyEx(u.astype(np.uint8), cv2.MORPH_OPEN, ell) > 0) & ~comp
    near = cv2.dilate(comp.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k + 4, k + 4))) > 0
    n, labels = cv2.connectedComponents(thin.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(comp)
    touching = np.unique(labels[near & thin])
    far = np.unique(labels[thin & (theta >= BASE_BG_DEG - 1.0)])
    keep = [i for i in np.setdiff1d(touching[touching > 0], far) if _elongated(labels == i)]
    return np.isin(labels, keep)


def radial_legs(dark: np.ndarray, comp: np.ndarray, theta: np.ndarray, focal: float) -> np.ndarray:
    """The tripod's legs as straight dark lines leaving the base comp (S, S) bool: a leg stands in a vertical plane
    through the camera, so on the downward face it runs away from the nadir. Straight runs of the dark pixels (dark,
    (S, S) bool: thin_dark) outside the base (probabilistic Hough) at least LEG_MIN_DEG long, one end within
    LEG_REACH_DEG of the base and within LEG_RADIAL_DEG of the direction away from the nadir, and the runs starting
    within LEG_REACH_DEG of a run taken (a leg Hough cuts in pieces), are the legs, less a run whose line, followed
    outward while it stays dark (a pixel aside, gaps of 3 pixels bridged), reaches BASE_BG_DEG: it goes on (a door
    trim, a floorboard's seam). The dark pixels within LEG_WIDTH_DEG of each leg taken, from its run's inner end to
    where its line ends; (S, S) bool."""
    deg = focal * np.deg2rad(1.0)
    cand = dark & ~comp
    out = np.zeros_like(comp)
    length = deg * LEG_MIN_DEG
    runs = cv2.HoughLinesP((cand & (theta < BASE_BG_DEG)).astype(np.uint8), 1, np.pi / 180, int(0.7 * length),
                           minLineLength=length, maxLineGap=3)
    if runs is None:
        return out
    reach = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(round(deg * LEG_REACH_DEG)) + 1,) * 2)
    wide = cv2.dilate(dark.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    S = comp.shape[0]
    c = 0.5 * S - 0.5
    cos_max = np.cos(np.deg2rad(LEG_RADIAL_DEG))
    half = max(1, int(round(deg * LEG_WIDTH_DEG)))
    lines = []  # (inner end, the run's dark pixels) of the runs along the radial direction that end
    for x0, y0, x1, y1 in runs.reshape(-1, 4):
        a, b = np.array([x0, y0], float), np.array([x1, y1], float)
        if np.hypot(*(a - c)) > np.hypot(*(b - c)):
            a, b = b, a  # b: the outer end
        axis = (b - a) / max(float(np.linalg.norm(b - a)), 1e-9)
        away = 0.5 * (a + b) - c
        if float(axis @ away) < cos_max * float(np.linalg.norm(away)):
            continue
        end = np.rint(_follow(wide, b, axis)).astype(int)
        if theta[end[1], end[0]] >= BASE_BG_DEG - 1.0:
            continue
        run = np.zeros(comp.shape, np.uint8)
        cv2.line(run, (int(round(a[0])), int(round(a[1]))), (int(end[0]), int(end[1])), 1, 2 * half + 1)
        lines.append((np.rint(a).astype(int), (run > 0) & cand))
    grown = comp.copy()
    while lines:  # runs that start at the base, then those that start on a run taken (a leg Hough cut in pieces)
        near = cv2.dilate(grown.astype(np.uint8), reach) > 0
        take = [k for k, (a, _) in enumerate(lines) if near[a[1], a[0]]]
        if not take:
            break
        for k in take:
            out |= lines[k][1]
        grown |= out
        lines = [x for k, x in enumerate(lines) if k not in take]
    return out


def thin_dark(face: np.ndarray, floor: np.ndarray, focal: float) -> np.ndarray:
    """(S, S) bool: the pixels of the downward face (S, S, 3) uint8 whose lightness (Lab L, smoothed by a pixel) lies
    below the lightest within LEG_MAX_DEG by LEG_MIN_DARK of it and by more than 99 % of the floor's pixels (floor,
    (S, S) bool) do: what is thin and dark there (a leg, a foot), not the floor's own texture."""
    light = cv2.GaussianBlur(cv2.cvtColor(face, cv2.COLOR_RGB2LAB)[..., 0].astype(np.float32), (0, 0), 1.0)
    k = 2 * int(round(0.5 * focal * np.deg2rad(LEG_MAX_DEG))) + 1
    top = cv2.morphologyEx(light, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    dark = (top - light) / np.maximum(top, 1.0)
    return dark > max(LEG_MIN_DARK, float(np.percentile(dark[floor], 99.0)) if floor.any() else LEG_MIN_DARK)


def rig_feet(dark: np.ndarray, rig: np.ndarray, theta: np.ndarray, focal: float) -> np.ndarray:
    """The small blobs of the dark pixels (dark, (S, S) bool: thin_dark) that touch the rig (S, S) bool found so far
    (within 2 pixels) within BASE_BG_DEG of the nadir, each at most a disc of LEG_FOOT_DEG across in area: a leg's
    foot, the tip of a knob or a wing the base's outline stops short of. (S, S) bool."""
    cand = dark & ~rig & (theta < BASE_BG_DEG)
    touch = cv2.dilate(rig.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    n, labels = cv2.connectedComponents(cand.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(rig)
    area = np.bincount(labels.ravel(), minlength=n)
    most = np.pi * (0.5 * LEG_FOOT_DEG * focal * np.deg2rad(1.0)) ** 2
    keep = [i for i in np.unique(labels[touch & cand]) if i and area[i] <= most]
    return np.isin(labels, keep)


def _follow(dark: np.ndarray, p: np.ndarray, axis: np.ndarray, gap: int = 3) -> np.ndarray:
    """The last dark pixel (dark, (S, S) bool) met walking from p (x, y) along axis, a pixel aside where the line
    drifts, gaps of up to `gap` pixels bridged, before leaving the face: (x, y)."""
    S = dark.shape[0]
    side = np.array([-axis[1], axis[0]])
    q, last, miss = p.astype(float), p.astype(float), 0
    while miss <= gap:
        q = q + axis
        for step in (0.0, -1.0, 1.0):
            x, y = np.rint(q + step * side).astype(int)
            if not (0 <= x < S and 0 <= y < S):
                return last
            if dark[y, x]:
                q = q + step * side
                last, miss = q.copy(), 0
                break
        else:
            miss += 1
    return last


def side_pieces(comp: np.ndarray, unlike: np.ndarray, theta: np.ndarray, on_floor: np.ndarray,
                focal: float) -> np.ndarray:
    """Separate pieces of the rig beside the base comp (S, S) bool: the components of the pixels unlike the floor
    (unlike, opened by 0.5 deg so the floor's speckle falls apart) within SIDE_GAP_DEG of the base, lying wholly
    within SIDE_MAX_DEG of the nadir, solid (SIDE_MIN_SOLIDITY) and between SIDE_MIN_SHARE and SIDE_MAX_SHARE of the
    base's area, and on the floor plane by depth (on_floor, (S, S) bool: seen where the floor is, as the base is; a
    wall's or a piece of furniture's corner beside the base is not): a side bar, a knob beyond a gap. (S, S) bool."""
    k = 2 * int(round(0.25 * focal * np.deg2rad(1.0))) + 1
    u = cv2.morphologyEx((unlike & ~comp).astype(np.uint8), cv2.MORPH_OPEN,
                         cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    g = 2 * int(round(focal * np.deg2rad(SIDE_GAP_DEG))) + 1
    near = cv2.dilate(comp.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (g, g))) > 0
    n, labels = cv2.connectedComponents(u, connectivity=8)
    area = float(comp.sum())
    out = np.zeros_like(comp)
    for i in np.unique(labels[near & (u > 0)]):
        if i == 0:
            continue
        part = labels == i
        size = int(part.sum())
        if (not (SIDE_MIN_SHARE * area <= size <= SIDE_MAX_SHARE * area) or theta[part].max() >= SIDE_MAX_DEG
                or on_floor[part].mean() < SIDE_MIN_ON_FLOOR):
            continue
        hull = cv2.convexHull(np.argwhere(part)[:, ::-1].astype(np.int32))
        if size >= SIDE_MIN_SOLIDITY * max(cv2.contourArea(hull), 1.0):
            out |= part
    return out


def _elongated(part: np.ndarray) -> bool:
    """Whether a part (S, S) bool is a line: its minimum-area rectangle at least LEG_MIN_ASPECT times as long as wide
    and the part filling at least half of it (a leg, not a ragged patch of carpet texture)."""
    pts = np.argwhere(part)[:, ::-1].astype(np.float32)
    if len(pts) < 5:
        return False
    (_, _), (w, h), _ = cv2.minAreaRect(pts)
    lo, hi = sorted((max(w, 1.0), max(h, 1.0)))
    return hi >= LEG_MIN_ASPECT * lo and len(pts) >= 0.5 * lo * hi


def detect_base(rgb: np.ndarray, depth: np.ndarray | None = None, valid: np.ndarray | None = None,
                floor_m: float | None = None, *, nf: NadirFace | None = None) -> RigDetection:
    """A solid camera base at the nadir (panoworld.depth.rig.base): GrabCut on the downward face, compared with the floor
    that is there (on the floor plane by depth, BASE_BG_DEG-42 deg from the nadir: in a narrow hallway nearer than the
    floor ring); a region that is no compact, centred body unlike that floor and closed by it is kept. nf: their
    nadir_face when already at hand."""
    H, W = rgb.shape[:2]
    nf = nadir_face(rgb, depth, valid, floor_m) if nf is None else nf
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
    stats["outline_edges"] = outline_edges(nf.face, comp, ref, nf.view.focal)
    why = is_base(stats)
    if why is None and (refusal := seen_object(nf, comp, floor_m)) is not None:
        why = refusal.reason
    if why is not None:
        return RigDetection(False, f"the region at the nadir is no camera base: {why}, kept", stats=stats)
    dark = thin_dark(nf.face, ref, nf.view.focal)
    legs = attached_legs(comp, unlike, nf.theta, nf.view.focal) | radial_legs(dark, comp, nf.theta, nf.view.focal)
    legs |= rig_feet(dark, comp | legs, nf.theta, nf.view.focal)
    side = side_pieces(comp, unlike, nf.theta, nf.on_floor, nf.view.focal)
    stats["leg_pixels"], stats["side_pixels"] = int(legs.sum()), int(side.sum())
    mask = face_to_erp_mask(cv2.dilate((comp | legs | side).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0, nf.view, H, W)
    unlike_how = ("unlike the floor around it" if stats["unlike_floor"] >= BASE_MIN_UNLIKE else
                  f"outlined by an edge all round ({stats['outline_edges']:.0%})")
    return RigDetection(True, f"a solid camera base centred on the nadir, {stats['cap_deg']:.1f} deg, {unlike_how}", "base", mask, np.zeros_like(mask), stats, source=floor_source(nf.face, nf),
                        fill="ring")
