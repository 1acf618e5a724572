"""A soft shadow around the capture rig on the downward face: a radial darkening against a smooth floor-light model."""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from panoworld.depth.rig.shape import FLOOR_LINE_MAX_DEG, opened, thin_kernel

KNOT_DEG = 3.0
"""Spacing (degrees from the nadir) of the knots of the shadow's piecewise-linear radial log-profile."""
SHADOW_MAX_DEG = 24.0
"""The shadow's profile is 1 from here out (the floor-light model alone explains the floor there): a little past a
tripod's feet (17-20 deg). Farther out, the profile would take up the room's own light there, which the
floor-light model (fitted on the face's floor beyond) extrapolates poorly, and relight the floor too bright."""
MIN_DARKENING = 0.15
"""A shadow removes at least this share of the light at its darkest knot (weaker: floor lighting, kept). Detection
measures the rig on the face relit by such a shadow; the removal relights only from RELIGHT_MIN_DARKENING."""
RELIGHT_MIN_DARKENING = 0.25
"""The removal relights the floor only when the shadow removes at least this share of the light: the room's uneven
light alone reads up to about 30 % under a tripod without a shadow (relighting that floor brightens it wrongly), a
rig's soft shadow 30-54 % on the synthetic scenes."""
CAST_RATIO = 0.9
"""Floor pixels darker than this share of the floor around them (Lab L) and connected to the rig are its cast
shadows (inpainted with it); lower values miss the fainter shadows the legs and column cast from the room's lights."""
LIGHT_EXPECTILE = 0.8
"""The light model and shadow profile fit this expectile of the floor's log luminance, not its mean: a shadow
darkens all of the floor's texture, more dark texture near the nadir only lowers its mean (0.5 = the mean; a
blotchy floor can still read as shadowed by about 10 %)."""
MIN_SECTORS = 5
"""Of 8 azimuth sectors, at least this many must be darker inside the shadow (a leg's cast shadow or a wall's is
not around the nadir)."""
RELIGHT_MIN_SECTORS = 6
"""The removal relights the floor only when at least this many of 8 azimuth sectors are darkened like the shadow's
profile (even_sectors): a shadow around the rig dims every side of it; the room's light dimming one side, or the
camera just inside the straight edge of the room's shadow, does not. A camera whose whole nadir lies in a room
shadow passes it too. Detection keeps MIN_SECTORS (it measures the rig on the relit face, which needs the room's
light divided out even where the removal does not relight)."""
SECTOR_RINGS_DEG = (5.0, 10.0, 15.0)
"""Rings (degrees from the nadir) of even_sectors: inside the tripod's feet, where a soft shadow is darkest."""
SECTOR_SHARE = 0.5
"""A sector is darkened like the profile in a ring when its light (sector_light) is darker by at least this share
of the profile's darkening there."""


DISC_FIT_DEG = 90.0
"""The soft disc and the room light are fitted jointly on the downward face's floor out to here (the whole face:
inside 30 deg only, the quadratic took up the disc's darkening as a bowl)."""
DISC_REACH = 0.45
"""The rig's soft disc reaches no farther than this (radius + 2 sigma of its blur), in camera heights (24 deg; a
tripod's feet 17-20 deg): a room's light or shadow reaching farther is left to the quadratic or the residual."""
DISC_BLUR = (0.03, 0.225)
"""Bounds of the disc's blur (Gaussian sigma of the penumbra), in camera heights."""
DISC_DEPTH_MAX = 0.8
"""Largest share of the light the disc may remove at its centre."""


class DiscShadow(NamedTuple):
    """disc_shadow's fit: the light factor 1 - depth * s(r), s a disc of radius `radius` blurred by a Gaussian of
    sigma `blur` (s(0) = 1; a Gaussian when radius is 0), r the floor distance from the nadir in camera heights."""

    depth: float
    """Share of the light removed at the nadir."""
    radius: float
    """The disc's radius before the blur, camera heights."""
    blur: float
    """The penumbra's Gaussian sigma, camera heights."""
    gain_of_fit: float
    """Relative drop of the fit's weighted loss over the room light alone (0: the disc explains nothing)."""

    def factor(self, r: np.ndarray) -> np.ndarray:
        """The disc's light factor at floor distance r (camera heights) from the nadir."""
        return 1.0 - self.depth * _disc(r, self.radius, self.blur)

    def gain(self, theta: np.ndarray) -> np.ndarray:
        """(as theta) float32 the gain >= 1 that divides the disc out at theta degrees from the nadir (1 where it
        removes < 0.5 % of the light)."""
        fac = self.factor(np.tan(np.deg2rad(theta)))
        return np.where(fac < 0.995, 1.0 / fac, 1.0).astype(np.float32)


def _disc(r: np.ndarray, a: float, sigma: float) -> np.ndarray:
    """A disc of radius a blurred by a 2-D Gaussian of sigma, at distance r from its centre, over its value at 0 (the
    non-central chi-square's cdf, tabulated on 256 radii and interpolated)."""
    from scipy.stats import ncx2

    if a < 1e-3 * sigma:
        return np.exp(-0.5 * (r / sigma) ** 2)
    k = (a / sigma) ** 2
    grid = np.linspace(0.0, a + 6.0 * sigma, 256)
    table = ncx2.cdf(k, 2, (grid / sigma) ** 2) / (1.0 - np.exp(-0.5 * k))
    return np.interp(r, grid, table, right=0.0)


def disc_shadow(face: np.ndarray, rig: np.ndarray, floor: np.ndarray, theta: np.ndarray, focal: float,
                max_samples: int = 15000) -> DiscShadow | None:
    """log(floor luminance) = quadratic in floor coordinates (the room's light) + log(1 - d s(r)), s a blurred disc
    reaching at most DISC_REACH around the nadir (the rig's shadow: compact, round), fitted jointly on the floor
    inside DISC_FIT_DEG outside the rig, with 3-MAD trimming, then to the LIGHT_EXPECTILE expectile (variable
    projection: the quadratic by weighted least squares inside a bounded fit of d, the radius's share of the reach
    and the blur); None when too little floor is seen."""
    from scipy.optimize import least_squares

    lum = linear_luminance(face)
    u, v = _floor_coords(face.shape[0], focal)
    use = floor & ~rig & (lum > 2e-3) & (theta < DISC_FIT_DEG)
    if use.sum() < 2000:
        return None
    idx = np.flatnonzero(use)
    idx = idx[:: max(1, len(idx) // max_samples)]
    uu, vv = u.ravel()[idx], v.ravel()[idx]
    r = np.hypot(uu, vv)
    A = np.stack(_quadratic(uu, vv), -1)
    y = np.log(lum.ravel()[idx]).astype(np.float64)
    wts = np.ones(len(y))

    def shape(p: np.ndarray) -> tuple[float, float]:  # (radius, blur): radius + 2 blur <= DISC_REACH
        return p[1] * max(DISC_REACH - 2.0 * p[2], 0.0), p[2]

    def residual(p: np.ndarray) -> np.ndarray:  # every sample's, the quadratic fitted with the weights
        z = y - np.log(1.0 - p[0] * _disc(r, *shape(p)))
        sw = np.sqrt(wts)
        coef, *_ = np.linalg.lstsq(A * sw[:, None], z * sw, rcond=None)
        return z - A @ coef

    def resid(p: np.ndarray) -> np.ndarray:
        return np.sqrt(wts) * residual(p)

    lo, hi = [0.0, 0.0, DISC_BLUR[0]], [DISC_DEPTH_MAX, 1.0, DISC_BLUR[1]]
    starts = [np.array([0.3, t, b]) for t in (0.0, 0.6) for b in (0.08, 0.16)]
    p = min(starts, key=lambda q: float(np.sum(resid(q) ** 2)))
    for it in range(10):
        p = least_squares(resid, p, bounds=(lo, hi), x_scale=[0.1, 0.2, 0.03], max_nfev=20).x
        res = residual(p)
        if it < 4:  # trimming (texture, the legs' own cast shadows), then the upper expectile
            keep = (wts > 0) & _within_3mad(res, res[wts > 0])
            wts = keep.astype(np.float64)
        else:
            wts = np.where(wts > 0, _expectile_weights(res), 0.0)
    loss1 = float(np.sum(resid(p) ** 2))
    loss0 = float(np.sum(resid(np.array([0.0, p[1], p[2]])) ** 2))
    return DiscShadow(float(p[0]), *shape(p), 1.0 - loss1 / max(loss0, 1e-12))


def linear_luminance(face: np.ndarray) -> np.ndarray:
    """Mean linear RGB (size, size) of a uint8 sRGB face (gamma 2.2, the synthetic renderer's and ours)."""
    return ((face.astype(np.float32) / 255.0) ** 2.2).mean(-1)


class FloorLight(NamedTuple):
    """The floor-light fit of shadow_gain: the radial shadow profile and what the floor shows around it."""

    knots: np.ndarray
    """Knot angles (degrees from the nadir) of the profile, 0 to SHADOW_MAX_DEG."""
    profile: np.ndarray
    """Light factor (<= 1) of the radial shadow at each knot; 1 at the last."""
    light: np.ndarray
    """(size, size) the floor's luminance over the fitted floor-light model alone (the shadow left in)."""
    use: np.ndarray
    """(size, size) bool the floor pixels the fit kept (outside the rig, trimmed)."""


def floor_light(face: np.ndarray, rig: np.ndarray, floor: np.ndarray, theta: np.ndarray,
                focal: float) -> FloorLight | None:
    """log(floor luminance) = quadratic in floor coordinates (the room's lights: smooth, broad) + a piecewise-linear
    radial profile with knots every KNOT_DEG up to SHADOW_MAX_DEG (a shadow: compact, around the nadir), fitted by
    least squares on floor pixels outside the rig with 3-MAD trimming (texture, the legs' own cast shadows), then
    refitted to the LIGHT_EXPECTILE expectile; None when too little floor is seen."""
    lum = linear_luminance(face)
    u, v = _floor_coords(face.shape[0], focal)
    poly = _quadratic(u, v)
    knots = np.arange(0.0, SHADOW_MAX_DEG + 1e-6, KNOT_DEG)
    y = np.log(np.maximum(lum, 1e-4)).astype(np.float64)
    use = floor & ~rig & (lum > 2e-3)
    k = len(poly) + len(knots) - 1
    if use.sum() < 20 * k or (use & (theta >= SHADOW_MAX_DEG)).sum() < 200:
        return None
    at = np.flatnonzero(use)  # the fit reads these pixels alone (the trimming only drops some)
    th = theta.reshape(-1)[at]
    hats = [np.clip(1.0 - np.abs(th - kn) / KNOT_DEG, 0.0, None) for kn in knots[:-1]]
    A = np.stack([p.reshape(-1)[at] for p in poly] + hats, -1).astype(np.float64)
    yu = y.reshape(-1)[at]
    keep = np.ones(len(at), bool)
    coef = np.zeros(k)
    for _ in range(4):
        coef = _lstsq(A[keep], yu[keep])
        res = yu - A @ coef
        keep &= _within_3mad(res, res[keep])
    A, yu, res = A[keep], yu[keep], res[keep]
    for _ in range(8):  # the upper expectile: the floor's brighter texture is lit like the rest (see LIGHT_EXPECTILE)
        sw = np.sqrt(_expectile_weights(res))
        coef = _lstsq(A * sw[:, None], yu * sw)
        res = yu - A @ coef
    seen = np.array([(keep & (h > 0.5)).sum() >= 8 for h in hats])  # knots without floor pixels (under the mount)
    prof = np.exp(np.minimum(np.where(seen, coef[len(poly):], 0.0), 0.0))
    light = np.exp(y - sum(c * p for c, p in zip(coef[: len(poly)], poly)))
    use = np.zeros(use.shape, bool)
    use.reshape(-1)[at[keep]] = True
    return FloorLight(knots, np.r_[prof, 1.0], light, use)


def sector_light(fit: FloorLight, theta: np.ndarray, phi: np.ndarray, rings: tuple[float, ...],
                 sectors: int = 8) -> np.ndarray:
    """The floor's light over the floor-light model (fit.light) per ring (between consecutive rings, degrees) and
    azimuth sector: (len(rings) - 1, sectors), the LIGHT_EXPECTILE expectile (as the fit) of the fit's floor pixels
    there (NaN where fewer than 8): a shadow around the rig dims every sector alike, the room's light need not."""
    sector = ((phi + np.pi) / (2 * np.pi) * sectors).astype(int) % sectors
    out = np.full((len(rings) - 1, sectors), np.nan)
    for i, (a, b) in enumerate(zip(rings[:-1], rings[1:])):
        ring = fit.use & (theta >= a) & (theta < b)
        for k in range(sectors):
            v = fit.light[ring & (sector == k)]
            if len(v) >= 8:
                out[i, k] = np.exp(_expectile(np.log(v), LIGHT_EXPECTILE))
    return out


def _floor_coords(size: int, focal: float) -> list[np.ndarray]:
    """(u, v) (size, size) of the downward face's pixel centres on the floor plane, in camera heights."""
    c = (np.arange(size) + 0.5 - 0.5 * size) / focal
    return np.meshgrid(c, c)


def _quadratic(u: np.ndarray, v: np.ndarray) -> list[np.ndarray]:
    """The room light's basis: the monomials of (u, v) up to degree 2."""
    return [u**i * v**j for i in range(3) for j in range(3 - i)]


def _lstsq(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    """np.linalg.lstsq(A, y)[0] for A (n, k), n >> k, by the normal equations (~10x cheaper than its SVD on a face's
    pixels): columns without support (a knot no floor pixel reaches) get 0, as the minimum-norm solution gives them;
    a singular rest falls back to lstsq."""
    G, b = A.T @ A, A.T @ y
    keep = np.diag(G) > 0
    coef = np.zeros(A.shape[1])
    try:
        coef[keep] = np.linalg.solve(G[np.ix_(keep, keep)], b[keep])
    except np.linalg.LinAlgError:
        coef = np.linalg.lstsq(A, y, rcond=None)[0]
    return coef


def _within_3mad(res: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The trimming of the light fits: |res| within 3 robust standard deviations (MAD) of the residuals ref."""
    return np.abs(res) < 3.0 * 1.4826 * np.median(np.abs(ref)) + 1e-6


def _expectile_weights(res: np.ndarray) -> np.ndarray:
    """Least-squares weights of the LIGHT_EXPECTILE expectile at residuals res."""
    return np.where(res > 0, LIGHT_EXPECTILE, 1.0 - LIGHT_EXPECTILE)


def _expectile(v: np.ndarray, tau: float, iters: int = 30) -> float:
    m = float(v.mean())
    for _ in range(iters):
        w = np.where(v > m, tau, 1.0 - tau)
        m = float((w * v).sum() / w.sum())
    return m


def even_sectors(fit: FloorLight, theta: np.ndarray, phi: np.ndarray) -> int:
    """How many of 8 azimuth sectors are darkened like the radial profile (by SECTOR_SHARE of its darkening) in
    every ring of SECTOR_RINGS_DEG, a sector without floor there counting as darkened."""
    rings = SECTOR_RINGS_DEG
    lit = sector_light(fit, theta, phi, rings)
    expect = np.interp(0.5 * (np.array(rings[:-1]) + rings[1:]), fit.knots, fit.profile)[:, None]
    return int((~(1.0 - lit < SECTOR_SHARE * (1.0 - expect)).any(0)).sum())


def relights(stats: dict) -> bool:
    """Whether the removal relights the floor for the shadow shadow_gain measured (its stats): the shadow removes
    >= RELIGHT_MIN_DARKENING of the light and >= RELIGHT_MIN_SECTORS sectors are darkened like it."""
    return (1.0 - stats.get("shadow_min_light", 1.0) >= RELIGHT_MIN_DARKENING
            and stats.get("shadow_even_sectors", 0) >= RELIGHT_MIN_SECTORS)


def shadow_gain(face: np.ndarray, rig: np.ndarray, floor: np.ndarray, theta: np.ndarray, phi: np.ndarray,
                focal: float) -> tuple[np.ndarray, float, dict]:
    """A soft shadow centred under the rig (floor_light's radial profile): (gain (size, size) >= 1 that divides it
    out, its extent in degrees, measurements); no shadow -> gain 1 everywhere, extent 0. A shadow is taken when the
    profile darkens the floor by >= MIN_DARKENING and >= MIN_SECTORS of 8 sectors agree; stats carry
    `shadow_even_sectors` for the removal's relighting (relights)."""
    none = np.ones(theta.shape, np.float32), 0.0, {}
    fit = floor_light(face, rig, floor, theta, focal)
    if fit is None:
        return none
    knots, prof, light, use = fit
    stats = {"shadow_min_light": round(float(prof.min()), 3)}
    if 1.0 - prof.min() < MIN_DARKENING:
        return none[0], 0.0, stats
    dark = np.nonzero(prof < 0.97)[0]
    extent = float(knots[min(dark[-1] + 1, len(knots) - 1)])
    p_map = np.interp(theta, knots, prof)
    zone = use & (p_map < 1.0 - 0.5 * MIN_DARKENING)
    sector = ((phi + np.pi) / (2 * np.pi) * 8).astype(int) % 8
    agree = have = 0
    for k in range(8):
        sel = zone & (sector == k)
        if sel.sum() < 8:
            continue
        have += 1
        expect = float(np.median(p_map[sel]))
        agree += float(np.median(light[sel])) < 1.0 - 0.5 * (1.0 - expect)
    stats.update(shadow_sectors=f"{agree}/{have}", shadow_even_sectors=even_sectors(fit, theta, phi))
    if agree < MIN_SECTORS:
        return none[0], 0.0, stats
    return np.where(theta < extent, 1.0 / p_map, 1.0).astype(np.float32), extent, stats


def local_lightness(L: np.ndarray) -> np.ndarray:
    """The floor's lightness around each pixel of a downward view's Lab L (S, S) uint8: the median over a window of
    about a sixteenth of the view (at least 15 px), which thin legs, their shadows and grout do not move; float32."""
    return cv2.medianBlur(L, min(2 * max(7, L.shape[0] // 16) + 1, 255)).astype(np.float32)


LEG_SHADOW_DARK = (0.06, 0.25)
"""A leg's cast shadow darkens the floor along its line by this share of the local floor's lightness (Lab L) on
average: fainter is the floor's own texture, darker is no shadow of a thin leg."""
LEG_SHADOW_COVER = 0.6
"""Share of a shadow line's visible samples that must be darker than the floor around them (by 4 %): a grout line
or plank seam crossed at an angle is dark only where it crosses."""
_TAU = 0.05  # darkening per sample that a line must beat to grow (the score's offset)


def leg_shadow_lines(face: np.ndarray, theta: np.ndarray, rig: np.ndarray, cap_deg: float, px: float,
                     samples: int = 100, width_px: float = 0.0) -> np.ndarray:
    """The legs' thin cast shadows on a downward view of the floor (face (S, S, 3) uint8, relit; theta degrees from
    the nadir; rig (S, S) bool the rig's mask; px the view's pixels per base pixel; width_px > 0: a line must be dark
    this wide across, not only along its middle): (S, S) bool, the pixels to inpaint with the rig, empty when no such
    shadow is seen.

    The physics: a light casts each straight leg's shadow from its foot on the floor to the shadow of the hub, one
    point H shared by all legs (the view of a plane is a scaled map of it, so these are straight segments). H is
    searched on a grid reaching a view's width past the view; a star is taken when at least two legs' segments are
    visibly dark (LEG_SHADOW_DARK, LEG_SHADOW_COVER) and no visible segment contradicts it (a leg whose segment shows
    plain floor casts no shadow there)."""
    S = face.shape[0]
    out = np.zeros((S, S), bool)
    extent = float(np.percentile(theta[rig], 98)) if rig.any() else 0.0
    n, lab = cv2.connectedComponents((rig & (theta > 0.55 * extent)).astype(np.uint8), connectivity=8)
    sizes = np.bincount(lab.ravel(), minlength=n)[1:]
    feet = []
    for i in np.argsort(sizes)[::-1][:3] + 1:  # the three legs' outer parts; each foot is its farthest pixel
        yy, xx = np.nonzero(lab == i)
        if len(yy) >= 4 * px:
            j = np.argmax(theta[yy, xx])
            feet.append((xx[j] + 0.5, yy[j] + 0.5))
    if len(feet) < 3:
        return out
    L = cv2.cvtColor(face, cv2.COLOR_RGB2LAB)[..., 0]
    local = local_lightness(L)
    dark = np.clip(1.0 - L / np.maximum(local, 1.0), -0.3, 0.5).astype(np.float32)
    visible = (~rig & (theta < cap_deg)).astype(np.uint8)

    def star(hx: np.ndarray, hy: np.ndarray) -> np.ndarray:
        """Score per candidate H (-inf where the star is not accepted)."""
        t = np.linspace(0.0, 1.0, samples, dtype=np.float32)
        total, n_ok = np.zeros(len(hx)), np.zeros(len(hx), int)
        veto = np.zeros(len(hx), bool)
        for fx, fy in feet:
            mx = (fx + (hx[:, None] - fx) * t).astype(np.float32)
            my = (fy + (hy[:, None] - fy) * t).astype(np.float32)
            val = cv2.remap(dark, mx, my, cv2.INTER_LINEAR, borderValue=0.0)
            if width_px > 0:  # dark across its width too: a floor line (grout, a seam) is narrower than a leg's shadow
                d = np.hypot(hx - fx, hy - fy)[:, None] + 1e-6
                ox, oy = (-(hy[:, None] - fy) / d * 0.5 * width_px).astype(np.float32), \
                    ((hx[:, None] - fx) / d * 0.5 * width_px).astype(np.float32)
                for sgn in (-1.0, 1.0):
                    val = np.minimum(val, cv2.remap(dark, mx + sgn * ox, my + sgn * oy, cv2.INTER_LINEAR, borderValue=0.0))
            ok = cv2.remap(visible, mx, my, cv2.INTER_NEAREST, borderValue=0) > 0
            cnt = ok.sum(1)
            seen_px = cnt * np.hypot(hx - fx, hy - fy) / samples  # visible length in view pixels
            mean = (val * ok).sum(1) / np.maximum(cnt, 1)
            cover = ((val > 0.04) & ok).sum(1) / np.maximum(cnt, 1)
            good = (mean >= LEG_SHADOW_DARK[0]) & (mean <= LEG_SHADOW_DARK[1]) & (cover >= LEG_SHADOW_COVER)
            vis = seen_px >= 8 * px
            n_ok += vis & good
            veto |= vis & ~good
            total += (mean - _TAU) * seen_px
        return np.where((n_ok >= 2) & ~veto, total, -np.inf)

    step = 3.0 * px  # the grid of H, refined to half a pixel around the best
    g = np.arange(-S, 2 * S, step, dtype=np.float32) + 0.5
    hx, hy = (a.ravel() for a in np.meshgrid(g, g))
    score = np.concatenate([star(hx[i:i + 20000], hy[i:i + 20000]) for i in range(0, len(hx), 20000)])
    if not np.isfinite(score).any():
        return out
    k = int(np.argmax(score))
    d = np.arange(-step, step + 0.25, 0.5, dtype=np.float32)
    fx_, fy_ = (a.ravel() for a in np.meshgrid(hx[k] + d, hy[k] + d))
    fine = star(fx_, fy_)
    H = (fx_[int(np.argmax(fine))], fy_[int(np.argmax(fine))]) if np.isfinite(fine).any() else (hx[k], hy[k])
    band = np.zeros((S, S), np.uint8)
    for fx, fy in feet:
        cv2.line(band, (int(round(fx * 16)), int(round(fy * 16))), (int(round(H[0] * 16)), int(round(H[1] * 16))), 1,
                 thickness=int(round(3 * px)), lineType=cv2.LINE_8, shift=4)
    return (band > 0) & (dark > 0.03) & (visible > 0)


def cast_shadows(lab: np.ndarray, obj: np.ndarray, theta: np.ndarray, focal: float, cap_deg: float) -> np.ndarray:
    """Floor pixels within cap_deg at least 10 % darker (CAST_RATIO) than the floor around them (Lab L, lab of a
    downward view whose focal is given) and connected to the rig obj: the legs' own cast shadows from the room's
    lights (inpainted with the rig); floor lines narrower than FLOOR_LINE_MAX_DEG are not taken."""
    L = lab[..., 0]
    dark = ((L < CAST_RATIO * local_lightness(L)) & (theta < cap_deg)).astype(np.uint8)
    k = thin_kernel(focal, FLOOR_LINE_MAX_DEG)
    if k > 1:
        dark = opened(dark, k).astype(np.uint8)
    _, labels = cv2.connectedComponents(dark | obj.astype(np.uint8), connectivity=8)
    keep = np.unique(labels[obj])
    return np.isin(labels, keep[keep > 0]) & (dark > 0)
