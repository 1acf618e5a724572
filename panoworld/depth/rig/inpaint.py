"""Hole filling on a view of a plane (the floor on the downward face): its texture's lattice, floor patches, Telea."""

from __future__ import annotations

import cv2
import numpy as np

from panoworld.geometry.blur import gaussian_blur

LATTICE_OFFSETS = 48
"""Most offsets (autocorrelation peaks) averaged by the lattice fill: more keep grout and seams in phase across a
larger hole and average each tile's own colour."""
LATTICE_MIN_CORR = 0.25
"""An autocorrelation peak below this (normalised: 1 = the texture repeats exactly) is no period of the floor."""


def inpaint_plane(face: np.ndarray, hole: np.ndarray, floor_area: np.ndarray, n_sectors: int = 3,
                  candidates: int = 8) -> np.ndarray:
    """Fill hole (size, size) of face (float RGB 0-255). Where the floor's texture repeats (tiles, planks: peaks of
    its autocorrelation, lattice_offsets), the mean of the known floor at every such offset from the pixel: the
    lattice (grout, plank seams) continues in phase and what differs from tile to tile averages out. Elsewhere, per
    azimuth sector around the nadir, the mean of the `candidates` best-matching shifted floor patches (Telea where
    no patch fits). Both are corrected in their low frequencies to the hole's border (_border_matched)."""
    known = floor_area & ~hole
    offsets = lattice_offsets(face, known)
    if len(offsets) >= 2:
        pred, ok = lattice_mean(face, known, offsets)
        use = hole & ok
        face = face.copy()
        face[use] = _border_matched(face, pred, known & ok)[use]
        hole, floor_area = hole & ~use, floor_area & ~use
        if not hole.any():
            return face
    return patch_fill(face, hole, floor_area, n_sectors, candidates)


def lattice_offsets(face: np.ndarray, known: np.ndarray, k: int = LATTICE_OFFSETS,
                    min_corr: float = LATTICE_MIN_CORR) -> list[tuple[int, int, float]]:
    """Up to k offsets (dy, dx, correlation), best first, under which the texture of face on the known pixels
    repeats: local maxima of its autocorrelation (luminance less its local mean; masked, normalised by the overlap,
    by FFT) of at least min_corr, outside the central lobe."""
    S = face.shape[0]
    L = face.mean(-1).astype(np.float32)
    kn = known.astype(np.float32)
    sig = max(2.0, S / 60)
    mu = cv2.GaussianBlur(L * kn, (0, 0), sig) / np.maximum(cv2.GaussianBlur(kn, (0, 0), sig), 1e-3)
    tex = (L - mu) * kn
    n = cv2.getOptimalDFTSize(2 * S)

    def auto(a: np.ndarray) -> np.ndarray:
        f = np.fft.rfft2(a, s=(n, n))
        return np.fft.fftshift(np.fft.irfft2(f * np.conj(f), s=(n, n)))  # offset d at index d + n // 2

    total = float(kn.sum())
    overlap = auto(kn)
    var = float((tex**2).sum()) / max(total, 1.0)
    corr = np.where(overlap > 0.15 * total, auto(tex) / np.maximum(overlap, 1.0) / max(var, 1e-6), -1.0)
    corr = corr.astype(np.float32)  # compared with its own dilation below: one precision
    c = n // 2
    yy, xx = np.mgrid[:n, :n] - c
    win = 2 * max(2, S // 100) + 1
    peak = (corr >= cv2.dilate(corr, np.ones((win, win), np.uint8))) & (corr >= min_corr) & (
        np.hypot(yy, xx) > max(3.0, S / 60))
    iy, ix = np.nonzero(peak)
    best = np.argsort(-corr[iy, ix])[:k]
    return [(int(iy[i] - c), int(ix[i] - c), float(corr[iy[i], ix[i]])) for i in best]


def lattice_mean(face: np.ndarray, known: np.ndarray, offsets: list[tuple[int, int, float]],
                 min_sources: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(the correlation-weighted mean of face at p + d over the offsets d whose source is known, (size, size) bool:
    at least min_sources of them were)."""
    S = face.shape[0]
    acc = np.zeros(face.shape, np.float32)
    wsum = np.zeros(known.shape, np.float32)
    count = np.zeros(known.shape, np.int32)
    for dy, dx, w in offsets:
        src = np.zeros(known.shape, bool)
        src[max(-dy, 0):S - max(dy, 0), max(-dx, 0):S - max(dx, 0)] = known[max(dy, 0):S + min(dy, 0),
                                                                           max(dx, 0):S + min(dx, 0)]
        shifted = np.roll(face, (-dy, -dx), axis=(0, 1))
        acc += (w * src)[..., None] * shifted
        wsum += w * src
        count += src
    return acc / np.maximum(wsum, 1e-6)[..., None], count >= min_sources


def _border_matched(face: np.ndarray, src: np.ndarray, known: np.ndarray) -> np.ndarray:
    """src corrected by its smooth mismatch with face on the known pixels (normalised convolution of the residual
    at two scales; the wider one reaches the middle of a large hole; beyond both, the mean mismatch)."""
    sig = max(1.5, face.shape[0] / 100)
    kn = known.astype(np.float32)
    diff = (face - src) * kn[..., None]
    fill = src + (float(np.mean((face - src)[known])) if known.any() else 0.0)
    for g in (12 * sig, 3 * sig):
        wsum = gaussian_blur(kn, g)[..., None]
        fill = np.where(wsum > 0.02, src + gaussian_blur(diff, g) / np.maximum(wsum, 1e-3), fill)
    return fill


def patch_fill(face: np.ndarray, hole: np.ndarray, floor_area: np.ndarray, n_sectors: int = 3,
                candidates: int = 8) -> np.ndarray:
    """Per azimuth sector around the nadir, the mean of the `candidates` best-matching shifted floor patches, its
    low frequencies corrected to the hole's border (Telea where no patch fits). The mean keeps what the matches
    share (the floor's lattice: grout, plank seams) and averages what they do not (each tile's own colour and
    veins, which nothing around the hole predicts): one copied patch doubles that part of the error."""
    img8 = np.clip(np.rint(face), 0, 255).astype(np.uint8)
    hole8 = hole.astype(np.uint8)
    radius = max(3, face.shape[0] // 60)
    base = cv2.inpaint(img8, hole8, radius, cv2.INPAINT_TELEA).astype(np.float32)
    out = face.copy()
    out[hole] = base[hole]
    S = face.shape[0]
    c = np.arange(S) + 0.5 - 0.5 * S
    sector = ((np.arctan2(*np.meshgrid(c, c)[::-1]) + np.pi) / (2 * np.pi) * n_sectors).astype(int) % n_sectors
    for k in range(n_sectors):  # one patch per sector of the hole: each leg gets floor that fits its own border
        part = hole & (sector == k)
        offsets = _best_offsets(face, part, floor_area & ~hole, candidates)
        if not offsets:
            continue
        src = np.mean([np.roll(face, (-d[0], -d[1]), axis=(0, 1)) for d in offsets], axis=0)
        out[part] = _border_matched(face, src, ~hole)[part]
    return out


def _best_offsets(face: np.ndarray, hole: np.ndarray, floor_area: np.ndarray, k: int = 1) -> list[tuple[int, int]]:
    """Up to k offsets (dy, dx), best first, such that face shifted by them matches face on a band around hole (sum
    of squared differences) and the shifted hole lands on known floor: patch matches by template matching, each a
    separate minimum (at least the band's width from the others)."""
    ys, xs = np.nonzero(hole)
    if len(ys) == 0:
        return []
    S = face.shape[0]
    pad = max(4, S // 40)
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, S)
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, S)
    hole_box = hole[y0:y1, x0:x1]
    band = (cv2.dilate(hole_box.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=pad) > 0) & floor_area[y0:y1, x0:x1]
    tmpl = face[y0:y1, x0:x1].astype(np.float32)
    ssd = cv2.matchTemplate(face.astype(np.float32), tmpl, cv2.TM_SQDIFF,
                            mask=np.repeat(band.astype(np.float32)[..., None], 3, axis=2))
    # Where the hole's pixels would come from must be known floor: no overlap with the hole, inside the floor area.
    bad = (hole | ~floor_area).astype(np.float32)
    overlap = cv2.matchTemplate(bad, hole_box.astype(np.float32), cv2.TM_CCORR)
    ssd = np.where(overlap < 0.5, ssd, np.inf)
    found = []
    for _ in range(k):
        if not np.isfinite(ssd).any():
            break
        iy, ix = np.unravel_index(np.argmin(ssd), ssd.shape)
        found.append((int(iy - y0), int(ix - x0)))
        ssd[max(iy - pad, 0):iy + pad + 1, max(ix - pad, 0):ix + pad + 1] = np.inf
    return found


RIM_PX = 2
"""Width (ERP pixels) of the band inside a rig mask whose pixels are matted rather than replaced (the rig's
anti-aliased edge and the mask's 1 px margin, which hold floor the input shows)."""
MIN_CONTRAST = 30.0
"""Below this distance (sRGB levels) between the rig's and the fill's colour the pixel's alpha is unknowable: filled."""


def matte_rim(observed: np.ndarray, fill: np.ndarray, mask: np.ndarray, rim_px: int = RIM_PX) -> np.ndarray:
    """The mask's rim pixels as floor: (H, W, 3) float, observed (the panorama) where the mask is not, observed plus
    alpha times (fill - rig) on the rim, the fill inside. Per rim pixel the rig's colour R is the local mean of the
    mask's interior, the floor's is the fill F, and alpha the projection of the observed colour on the line F -> R;
    the pixel becomes F plus (1 - alpha) of what the line leaves unexplained: a pixel that shows floor (a dilated
    margin, an anti-aliased edge) keeps its own texture, one that shows rig gets the fill, its edge's own colour
    (a fringe unlike the rig's mean) included."""
    out = np.where(mask[..., None], fill.astype(np.float32), observed.astype(np.float32))
    rows = np.flatnonzero(mask.any(1))
    if len(rows):  # the rows the mask and its rig colour's blur reach: the rest stays as it is
        band = slice(max(0, rows[0] - RIM_BLUR_ROWS), rows[-1] + 1 + RIM_BLUR_ROWS)
        out[band] = _matte_rows(observed[band], fill[band], mask[band], rim_px, out[band])
    return out


RIM_BLUR_ROWS = 16
"""Rows around a mask that matte_rim's blur of the rig's colour (sigma 3 px, a 25-tap kernel) reads."""


def _matte_rows(observed: np.ndarray, fill: np.ndarray, mask: np.ndarray, rim_px: int, out: np.ndarray) -> np.ndarray:
    """matte_rim on a band of rows holding the mask and RIM_BLUR_ROWS around it; out: the band's result outside the
    rim (the fill inside the mask, observed elsewhere), completed on the rim."""
    c = observed.astype(np.float32)
    F = fill.astype(np.float32)
    m8 = mask.astype(np.uint8)
    k = np.ones((3, 3), np.uint8)
    rim = mask & ~(cv2.erode(m8, k, iterations=rim_px) > 0)
    core = cv2.erode(m8, k, iterations=rim_px + 1) > 0
    if not rim.any() or not core.any():
        return out
    wc = cv2.GaussianBlur(core.astype(np.float32), (0, 0), 3.0)
    R = cv2.GaussianBlur(c * core[..., None], (0, 0), 3.0) / np.maximum(wc, 1e-6)[..., None]
    R = np.where((wc > 1e-3)[..., None], R, np.median(c[core], 0))
    d = (R - F)[rim]
    n2 = (d**2).sum(-1)
    alpha = np.clip(((c[rim] - F[rim]) * d).sum(-1) / np.maximum(n2, 1e-6), 0.0, 1.0)
    alpha = np.where(n2 < MIN_CONTRAST**2, 1.0, alpha)[:, None]
    resid = c[rim] - F[rim] - alpha * d  # off the line F -> R: the floor's texture or the rig's own edge (a colour fringe)
    out[rim] = F[rim] + (1.0 - alpha) * resid
    return out


RING_WIDTH_DEG = 8.0
"""Width of the floor annulus just outside a hole that ring_fill takes the floor from."""


def floor_ring(hole: np.ndarray, floor_area: np.ndarray, width_px: float) -> np.ndarray:
    """The floor pixels (size, size) bool within width_px outside hole: the floor the hole is surrounded by."""
    dist = cv2.distanceTransform((~hole).astype(np.uint8), cv2.DIST_L2, 5)
    return floor_area & ~hole & (dist <= width_px)


def ring_fill(face: np.ndarray, hole: np.ndarray, floor_area: np.ndarray, width_px: float,
              seed: int = 0) -> np.ndarray:
    """Fill hole (size, size) of face (float RGB 0-255) from the floor ring around it alone (floor_ring): its low
    frequencies a membrane (harmonic) interpolation of the ring's local mean across the hole (a light gradient or a
    sun band on both sides carries across; _membrane), blended towards straight lines through the ring's light at a
    finer scale where that light runs one way (a sun band's edges stay sharp; _along_band), its texture (face less
    the ring's local mean) laid by overlap-added random ring blocks. Nothing beyond the ring (a wall, the next room, a
    sun band far away) is read; with no ring the hole is left as it is."""
    ring = floor_ring(hole, floor_area, width_px)
    if ring.sum() < 16:
        return face
    ring = _majority_floor(face, ring)
    S = face.shape[0]
    sig = max(1.5, S / 100)
    tex_sig = max(1.0, S / 120)
    local = _spread(face, ring, (tex_sig,))
    blurs: dict = {}
    mean = _spread(face, ring, (3 * sig,), blurs)
    membrane = _membrane(mean, ring, hole, _spread(face, ring, (24 * sig, 12 * sig, 3 * sig), blurs))
    low = _along_band(mean, _spread(face, ring, (sig,), blurs), ring, hole, membrane, sig)
    resid = (face - local) * ring[..., None]
    out = face.copy()
    out[hole] = (low + _quilt(resid, ring, hole, max(8, int(S / 24)) // 2 * 2, seed))[hole]
    return out


CHROMA_SPLIT = 12.0
"""Two colour groups of the ring farther apart than this (Lab a*b* units) are two kinds of surface (_majority_floor)."""
MINORITY_SHARE = 0.35
"""... and the smaller one, below this share of the ring, is left out of the fill's source."""


def _majority_floor(face: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """ring (size, size) bool less its chroma minority: the ring's a*b* split in two groups (k-means); where they are
    more than CHROMA_SPLIT apart and the smaller holds less than MINORITY_SHARE of the ring, the pixels nearer its
    centre are left out (a door jamb lying on the layout's floor plane). A brighter minority stays: the floor
    under more light (a sun band across it, its colours washed out) is still the floor."""
    lab = cv2.cvtColor(np.clip(face, 0, 255).astype(np.uint8), cv2.COLOR_RGB2LAB)[..., 1:].astype(np.float32)
    ab = np.ascontiguousarray(lab[ring])
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.5)
    cv2.setRNGSeed(0)
    _, lab_k, centres = cv2.kmeans(ab, 2, None, crit, 3, cv2.KMEANS_PP_CENTERS)
    lab_k = lab_k.ravel()
    minor = int(np.argmin(np.bincount(lab_k, minlength=2)))
    lum = face[ring].mean(-1)
    if (float(np.linalg.norm(centres[0] - centres[1])) <= CHROMA_SPLIT or np.mean(lab_k == minor) >= MINORITY_SHARE
            or lum[lab_k == minor].mean() > lum[lab_k != minor].mean()):
        return ring
    out = ring.copy()
    out[ring] = lab_k != minor
    return out


MEMBRANE_ITERS = 400
"""Jacobi sweeps of _membrane on its 4x coarser grid, started from the normalised-convolution spread."""


def _membrane(known_val: np.ndarray, known: np.ndarray, hole: np.ndarray, start: np.ndarray) -> np.ndarray:
    """(size, size, 3): known_val on the known pixels, the harmonic (membrane) interpolation of them over the rest
    of the hole's box: on a 4x coarser grid (Jacobi sweeps from start), upsampled. Pixels farther from the hole keep
    start."""
    S = known.shape[0]
    f = 4
    s = max(8, S // f)
    small = cv2.resize(known_val, (s, s), interpolation=cv2.INTER_AREA)
    kn = cv2.resize(known.astype(np.float32), (s, s), interpolation=cv2.INTER_AREA) > 0.5
    inside = cv2.resize(hole.astype(np.float32), (s, s), interpolation=cv2.INTER_AREA) > 0
    free = inside & ~kn
    if not free.any() or not kn.any():
        return start
    u = cv2.resize(start, (s, s), interpolation=cv2.INTER_AREA)
    u[kn] = small[kn]
    solve = cv2.dilate(free.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    for _ in range(MEMBRANE_ITERS):
        u = np.where(free[..., None], cv2.blur(u, (3, 3), borderType=cv2.BORDER_REPLICATE), u)
    up = cv2.resize(u, (S, S), interpolation=cv2.INTER_LINEAR)
    near = cv2.resize(solve.astype(np.uint8), (S, S), interpolation=cv2.INTER_NEAREST) > 0
    return np.where(near[..., None], up, start).astype(np.float32)


BAND_COHERENCE = (0.5, 0.8)
"""Coherence of the ring's light (_isophote_direction: 1 when all its gradients cross one direction, the edges of a
straight sun band; a carpet's grain or a room's light: less) from which the fill starts to follow that direction
and where it follows it wholly."""


def _along_band(val: np.ndarray, line_val: np.ndarray, known: np.ndarray, hole: np.ndarray, membrane: np.ndarray,
                smooth: float) -> np.ndarray:
    """membrane over the free pixels, blended towards the linear interpolation of line_val between the two known
    pixels met along val's isophote direction (a sun band across the hole goes on straight, where the membrane lets
    the shade on either side darken its middle) as far as val's light gradients share one direction
    (BAND_COHERENCE), smoothed across those lines by smooth pixels. val: the ring's light, smooth enough that a
    carpet's grain does not turn the direction; line_val: the same at a finer scale, so a band's edges stay sharp."""
    (dx, dy), coherence = _isophote_direction(val, known)
    share = float(np.clip((coherence - BAND_COHERENCE[0]) / (BAND_COHERENCE[1] - BAND_COHERENCE[0]), 0.0, 1.0))
    free = hole & ~known
    if share == 0.0:
        return membrane
    s = known.shape[0]
    n = int(np.ceil(s * np.sqrt(2))) + 2
    to_rot = cv2.getRotationMatrix2D((0.5 * s, 0.5 * s), float(np.degrees(np.arctan2(dy, dx))), 1.0)
    to_rot[:, 2] += 0.5 * (n - s)  # the isophote direction along the rows of an n x n canvas

    def rot(a: np.ndarray, interp: int) -> np.ndarray:
        return cv2.warpAffine(a, to_rot, (n, n), flags=interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    kv = rot(known.astype(np.uint8), cv2.INTER_NEAREST) > 0
    fr = rot(free.astype(np.uint8), cv2.INTER_NEAREST) > 0
    v = rot(line_val.astype(np.float32), cv2.INTER_LINEAR)
    line, ok = _rowwise_line(v, kv, fr)
    wsum = cv2.GaussianBlur(ok.astype(np.float32), (0, 0), smooth)  # each row's ends carry the ring's texture
    line = cv2.GaussianBlur(line * ok[..., None], (0, 0), smooth) / np.maximum(wsum, 1e-6)[..., None]
    back = lambda a: cv2.warpAffine(a, to_rot, (s, s), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    wline = np.where(free, np.clip(back(wsum), 0.0, 1.0) * share, 0.0)[..., None]  # rows without both ends: no seam
    line = back(line.astype(np.float32))
    return (wline * line + (1 - wline) * membrane).astype(np.float32)


def _isophote_direction(val: np.ndarray, known: np.ndarray) -> tuple[tuple[float, float], float]:
    """((dx, dy) unit direction on the face, coherence): the direction along which the known pixels' light stays the
    same (the structure tensor's, of val's luminance on a 4x coarser grid, over the known pixels) and how much the
    light's gradients share it: (l1 - l2) / (l1 + l2), 1 for a straight sun band's edges, low for a carpet's grain."""
    s = max(8, known.shape[0] // 4)
    lum = cv2.resize(np.ascontiguousarray(val.mean(-1), np.float32), (s, s), interpolation=cv2.INTER_AREA)
    kn = cv2.resize(known.astype(np.float32), (s, s), interpolation=cv2.INTER_AREA) > 0.5
    w = cv2.erode(kn.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
    gx = cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3)
    jxx, jxy, jyy = float((w * gx * gx).sum()), float((w * gx * gy).sum()), float((w * gy * gy).sum())
    if jxx + jyy <= 1e-6:
        return (1.0, 0.0), 0.0
    ev, vec = np.linalg.eigh(np.array([[jxx, jxy], [jxy, jyy]]))
    return (float(vec[0, 0]), float(vec[1, 0])), float((ev[1] - ev[0]) / (ev[1] + ev[0]))


def _rowwise_line(val: np.ndarray, known: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row, each free pixel between a known pixel on its left and one on its right with only free pixels
    between: the linear interpolation of the two; (values, where there were both)."""
    h, w = known.shape
    idx = np.broadcast_to(np.arange(w), (h, w))
    stop = ~free  # a known pixel or a blocker ends a run
    left = np.maximum.accumulate(np.where(stop, idx, -1), axis=1)
    right = np.minimum.accumulate(np.where(stop, idx, w)[:, ::-1], axis=1)[:, ::-1]
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    lk = (left >= 0) & known[rows, np.clip(left, 0, w - 1)]
    rk = (right < w) & known[rows, np.clip(right, 0, w - 1)]
    ok = free & lk & rk
    r, c = np.nonzero(ok)
    li, ri = left[r, c], right[r, c]
    t = ((c - li) / np.maximum(ri - li, 1))[:, None]
    out = np.zeros(val.shape, np.float32)
    out[r, c] = ((1 - t) * val[r, li] + t * val[r, ri]).astype(np.float32)
    return out, ok


def _spread(face: np.ndarray, known: np.ndarray, sigmas: tuple[float, ...], blurs: dict | None = None) -> np.ndarray:
    """face's known pixels spread over every pixel (normalised convolution, coarse to fine; the known mean where
    no scale reaches). blurs: {sigma: (blurred known, blurred values)} of earlier calls on the same face and known
    pixels, reused and added to."""
    kn = known.astype(np.float32)
    val = face * kn[..., None]
    out = np.broadcast_to(face[known].mean(0), face.shape).astype(np.float32)
    blurs = {} if blurs is None else blurs
    for g in sigmas:
        if g not in blurs:
            blurs[g] = gaussian_blur(kn, g)[..., None], gaussian_blur(val, g)
        w, v = blurs[g]
        out = np.where(w > 0.02, v / np.maximum(w, 1e-6), out)
    return out


QUILT_NEAREST = 64
"""Each texture block of the fill is drawn from this many ring blocks nearest to where it goes: the floor's
texture on each side of the hole goes on there (carpet beside carpet, planks beside planks)."""


def _quilt(resid: np.ndarray, ring: np.ndarray, hole: np.ndarray, block: int, seed: int) -> np.ndarray:
    """Texture (size, size, 3) over hole: blocks of resid taken at random among the QUILT_NEAREST nearest positions
    where a block lies wholly in ring (or mostly, for a thin ring), overlap-added with Hann windows at half a block's
    stride and scaled so that the sum of independent blocks keeps the ring's texture contrast."""
    S = hole.shape[0]
    rng = np.random.default_rng(seed)
    cover = cv2.boxFilter(ring.astype(np.float32), -1, (block, block), normalize=True, borderType=cv2.BORDER_CONSTANT)
    half = block // 2
    cy, cx = np.nonzero(cover >= 0.95)
    if len(cy) == 0:
        cy, cx = np.nonzero(cover >= 0.5 * cover.max())
    win = np.outer(np.hanning(block + 2)[1:-1], np.hanning(block + 2)[1:-1]).astype(np.float32)
    acc = np.zeros(resid.shape, np.float32)
    w2 = np.zeros(hole.shape, np.float32)
    pad = np.pad(resid, ((half, half), (half, half), (0, 0)))
    rpad = np.pad(ring.astype(np.float32), half)
    ys, xs = np.nonzero(hole)
    step = max(1, half)
    near = min(len(cy), QUILT_NEAREST)
    for y0 in range(max(ys.min() - block, -half), min(ys.max() + 1, S), step):
        for x0 in range(max(xs.min() - block, -half), min(xs.max() + 1, S), step):
            d2 = (cy - half - y0) ** 2 + (cx - half - x0) ** 2
            k = np.argpartition(d2, near - 1)[rng.integers(near)]
            sy, sx = cy[k], cx[k]  # the block centred there, its top-left corner in the padded arrays
            patch = pad[sy:sy + block, sx:sx + block]
            wk = win * rpad[sy:sy + block, sx:sx + block]
            ty0, tx0 = max(y0, 0), max(x0, 0)
            ty1, tx1 = min(y0 + block, S), min(x0 + block, S)
            if ty1 <= ty0 or tx1 <= tx0:
                continue
            py, px = ty0 - y0, tx0 - x0
            sl = (slice(py, py + ty1 - ty0), slice(px, px + tx1 - tx0))
            acc[ty0:ty1, tx0:tx1] += (wk[sl])[..., None] * patch[sl]
            w2[ty0:ty1, tx0:tx1] += wk[sl] ** 2
    return acc / np.sqrt(np.maximum(w2, 1e-6))[..., None]
