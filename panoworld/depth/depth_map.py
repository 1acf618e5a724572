"""ERP metric depth: reading provided depth, hole filling, perspective-view merging of monocular depth, floor-based metric scale."""

from __future__ import annotations

import cv2
import numpy as np

from panoworld.core.errors import InputError
from panoworld.depth.options import Rescale
from panoworld.geometry.resize import resize_depth
from panoworld.room.floor import estimate_floor
from panoworld.room.plausible import float16_exact

# ---------------------------------------------------------------- files


def working_size(height: int, max_height: int) -> tuple[int, int]:
    """(H, W) the pipeline works at: the panorama's, or max_height x 2 max_height when it is taller (0 = no limit)."""
    if max_height <= 0 or height <= max_height:
        return height, 2 * height
    return max_height, 2 * max_height


def resize_panorama(rgb: np.ndarray, height: int) -> np.ndarray:
    """Area-average an ERP panorama (H, W, 3) down to (height, 2 height, 3)."""
    if rgb.shape[0] == height:
        return rgb
    return cv2.resize(rgb, (2 * height, height), interpolation=cv2.INTER_AREA)


def valid_depth_mask(depth: np.ndarray) -> np.ndarray:
    """Valid = finite and > 0, shape (H, W) bool."""
    return np.isfinite(depth) & (depth > 0)


def conform_depth(depth: np.ndarray, height: int, width: int, what: str = "depth") -> tuple[np.ndarray, str | None]:
    """Resize depth (h, w) to the panorama's (height, width) as geometry.resize.resize_depth does (area-averaged when
    shrinking and bilinear when enlarging on smooth surfaces, nearest at depth edges; invalid pixels never blend into
    valid ones; 0 where invalid); the aspect must match. Returns (depth, note) where note describes the resize (None if
    none)."""
    h, w = depth.shape
    if (h, w) == (height, width):
        return depth, None
    if w * height != h * width:
        raise InputError(
            f"{what}: depth is {w}x{h} but the panorama is {width}x{height} (WxH), a different aspect; "
            "give a 2:1 ERP depth map aligned with the panorama"
        )
    how = "bilinear" if height > h else "area-averaged"
    out = np.nan_to_num(resize_depth(depth, height, width), nan=0.0)
    if _float16_stored(depth):  # keep the input's precision: its rounding step is what plane tests allow for
        with np.errstate(over="ignore"):
            out = out.astype(np.float16).astype(np.float32)
    return out, f"depth resized from {w}x{h} to {width}x{height} ({how} on smooth surfaces, nearest at depth edges)"


def _float16_stored(depth: np.ndarray) -> bool:
    """Whether depth (H, W) holds float16 values (at least 99 % of its valid values exactly representable as one, the
    rest filled holes: ZInD's layout depth, rounded to 1 mm at 1-2 m)."""
    d = np.asarray(depth, np.float32)
    valid = np.isfinite(d) & (d > 0)
    return bool(valid.any()) and float(float16_exact(d, valid)[0][valid].mean()) >= 0.99


def fill_small_holes(
    depth: np.ndarray, valid: np.ndarray, max_hole_px: int, max_gap_px: int = 0
) -> tuple[np.ndarray, np.ndarray, int]:
    """Fill small holes harmonically in inverse depth; larger invalid regions stay invalid.

    Filled: invalid components of at most max_hole_px pixels (found with the seam wrapped), and invalid pixels in
    a run of at most max_gap_px pixels between valid ones along a row or a column (the gaps between the scan lines
    of sparse LiDAR; interpolation only, never extrapolation past the rim of a dropout).
    depth (H, W), valid (H, W) bool -> (depth with 0 where still invalid, valid, number of pixels filled).
    """
    from scipy import ndimage, sparse  # here: most stages read depth artifacts and never fill holes
    from scipy.sparse import csgraph

    holes = ~valid
    if not holes.any() or not valid.any() or (max_hole_px <= 0 and max_gap_px <= 0):
        return np.where(valid, depth, 0).astype(np.float32), valid, 0
    fill = np.zeros_like(holes)
    if max_hole_px > 0:
        labels, n = ndimage.label(holes)
        # Merge components that meet across the seam (left and right border pixels of the same row).
        both = (labels[:, 0] > 0) & (labels[:, -1] > 0)
        seam = sparse.coo_matrix((np.ones(int(both.sum())), (labels[both, 0], labels[both, -1])), shape=(n + 1, n + 1))
        _, comp = csgraph.connected_components(seam, directed=False)
        labels = comp[labels]
        sizes = np.bincount(labels[holes], minlength=labels.max() + 1)
        fill |= holes & (sizes[labels] <= max_hole_px)
    if max_gap_px > 0:
        fill |= holes & (wrapped_gap_lengths(valid) <= max_gap_px)
    if not fill.any():
        return np.where(valid, depth, 0).astype(np.float32), valid, 0
    inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    filled = _harmonic_fill(inv, fill, valid)
    out_valid = valid | fill
    out = np.where(valid, depth, np.where(fill, 1.0 / np.maximum(filled, 1e-12), 0.0)).astype(np.float32)
    return out, out_valid, int(fill.sum())


def wrapped_gap_lengths(valid: np.ndarray) -> np.ndarray:
    """Per pixel of valid (H, W): the shorter of the invalid runs it lies in along its row (seam wrapped) and its
    column, each bounded by valid pixels on both sides (see _gap_lengths; huge where unbounded or valid)."""
    W = valid.shape[1]
    row_gap = _gap_lengths(np.concatenate([valid[:, -W // 2:], valid, valid[:, : W // 2]], axis=1))
    return np.minimum(row_gap[:, W // 2: W // 2 + W], _gap_lengths(valid.T).T)


def auto_gap_px(
    valid: np.ndarray, *, max_px: int = 8, min_share: float = 0.3, cover: float = 0.9, min_invalid: float = 0.05
) -> tuple[int, float]:
    """Scan-line gap width to interpolate for depth validity valid (H, W): (max_gap_px, share of short gaps).

    Sparse LiDAR leaves most invalid pixels in short runs between valid ones; dense depth with dropouts or
    blind bands does not. When at least min_share of the invalid pixels lie in runs of <= max_px pixels (along a
    row or a column), returns the smallest width whose runs hold `cover` of those pixels, else 0 (no filling).
    Depth with less than min_invalid of its pixels invalid is dense: 0.
    """
    holes = ~valid
    if holes.mean() < min_invalid or not valid.any():
        return 0, 0.0
    g = wrapped_gap_lengths(valid)[holes]
    short = g <= max_px
    share = float(short.mean())
    if share < min_share:
        return 0, share
    counts = np.bincount(g[short], minlength=max_px + 1)
    width = int(np.searchsorted(np.cumsum(counts), cover * short.sum()))
    return max(width, 1), share


def _gap_lengths(valid: np.ndarray) -> np.ndarray:
    """Length of the run of invalid pixels each pixel lies in along axis 1, bounded by valid pixels on both sides;
    a huge number where a run reaches the array's border or the pixel is valid."""
    n = valid.shape[1]
    j = np.arange(n)
    left = np.maximum.accumulate(np.where(valid, j, -(10 * n)), axis=1)
    right = np.minimum.accumulate(np.where(valid, j, 11 * n)[:, ::-1], axis=1)[:, ::-1]
    return np.where(valid, 10 * n, right - left - 1)


def _harmonic_fill(values: np.ndarray, fill: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Solve Laplace's equation on the pixels fill (H, W) with their known (H, W) 4-neighbours' values (H, W) as
    boundary values; other neighbours are left out (a free boundary). Seam wrapped, rows clamped; each fill
    component must touch a known pixel. Returns values with the fill pixels solved."""
    from scipy import sparse
    from scipy.sparse import linalg as sparse_linalg

    H, W = values.shape
    n = int(fill.sum())
    idx = np.full((H, W), -1, np.int64)
    idx[fill] = np.arange(n)
    ii, jj = np.nonzero(fill)
    rows, cols, diag = [], [], np.zeros(n)
    rhs = np.zeros(n)
    for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        ni, nj = ii + di, (jj + dj) % W
        inside = (ni >= 0) & (ni < H)
        p, ni, nj = np.nonzero(inside)[0], ni[inside], nj[inside]
        q = idx[ni, nj]
        unknown = q >= 0
        fixed = known[ni, nj]
        np.add.at(diag, p[unknown | fixed], 1.0)
        rows.append(p[unknown])
        cols.append(q[unknown])
        np.add.at(rhs, p[fixed], values[ni[fixed], nj[fixed]])
    r = np.concatenate(rows + [np.arange(n)])
    c = np.concatenate(cols + [np.arange(n)])
    v = np.concatenate([-np.ones(len(r) - n), diag])
    A = sparse.csr_matrix((v, (r, c)), shape=(n, n))
    out = values.astype(np.float64).copy()
    # Every unknown is near known pixels, so Jacobi-preconditioned CG converges in few iterations.
    x, info = sparse_linalg.cg(A, rhs, rtol=1e-9, maxiter=5000, M=sparse.diags(1.0 / diag))
    out[fill] = x if info == 0 else sparse_linalg.spsolve(A.tocsc(), rhs)
    return out


# ---------------------------------------------------------------- metric scale


# ---------------------------------------------------------------- metric scale policy


PLAUSIBLE_CAMERA_HEIGHT = (0.2, 5.0)
"""Floor distances (m) accepted for depth taken as metric (rescale relative-only): outside it is an error."""
CAPTURE_CAMERA_HEIGHT = (0.9, 2.4)
"""Floor distances (m) of handheld and tripod indoor captures: rescale auto takes provided depth whose floor lies
outside this range as being in other units (DECIMAL_UNITS, else unknown: raw sensor values, a wrong PNG scale) and
rescales it."""
DECIMAL_UNITS = (("millimetres", 1e-3), ("centimetres", 1e-2))
"""Units rescale auto recognises in provided depth whose floor lies outside CAPTURE_CAMERA_HEIGHT: the one that puts
the floor inside it (at most one can) is converted to metres, so the capture keeps its own camera height."""


def metric_rescale(
    depth: np.ndarray, valid: np.ndarray, *, relative: bool, rescale: Rescale, camera_height: float
) -> tuple[np.ndarray, dict]:
    """Rescale depth (H, W) by camera_height / estimated floor distance when the policy asks for it.

    auto: relative depth always; provided or metric depth when its floor lies outside CAPTURE_CAMERA_HEIGHT: by the
    one of DECIMAL_UNITS that puts it inside (depth in millimetres or centimetres), else to camera_height (unknown
    units); depth without a visible floor is kept as given (relative depth then has an arbitrary scale,
    said in info["scale_note"]). Returns (depth, info) with the estimated camera height before and after (None
    when no floor is found), the factor applied and why. InputError if a rescale is required (always,
    relative-only on relative depth) but no floor is visible, or if relative-only takes depth as metric whose
    floor lies outside PLAUSIBLE_CAMERA_HEIGHT (wrong units).
    """
    fit = estimate_floor(depth, valid)
    if not camera_height > 0:
        raise InputError(f"--camera-height {camera_height} must be > 0 metres")
    note, unit = None, None
    if rescale == Rescale.AUTO:
        if fit is None:
            do = False
            note = "no floor visible: depth kept as given" + (" (relative: arbitrary scale)" if relative else "")
        elif relative:
            do, note = True, "relative depth: floor put at camera_height"
        else:
            lo, hi = CAPTURE_CAMERA_HEIGHT
            h = fit.camera_height
            do = not lo <= h <= hi
            unit = next(((name, f) for name, f in DECIMAL_UNITS if lo <= h * f <= hi), None) if do else None
            if not do:
                note = f"floor {h:.3f} m below the camera: metric"
            elif unit is not None:
                note = f"floor {h:.4g} units below the camera: depth in {unit[0]}, converted to metres (floor {h * unit[1]:.3f} m)"
            else:
                note = f"floor {h:.4g} units below the camera, outside {lo}-{hi} m: unknown units, floor put at camera_height"
    else:
        do = rescale == Rescale.ALWAYS or (rescale == Rescale.RELATIVE_ONLY and relative)
    factor = 1.0
    if do:
        if fit is None:
            raise InputError(
                "no horizontal floor found below the camera, so depth cannot be put to metric scale; "
                "pass --rescale never (and metric depth) or a panorama that shows the floor"
            )
        factor = unit[1] if unit is not None else camera_height / fit.camera_height
    elif rescale == Rescale.RELATIVE_ONLY and fit is not None and not PLAUSIBLE_CAMERA_HEIGHT[0] <= fit.camera_height <= PLAUSIBLE_CAMERA_HEIGHT[1]:
        raise InputError(
            f"depth units look wrong: the floor is {fit.camera_height:.4g} units below the camera, not "
            f"{PLAUSIBLE_CAMERA_HEIGHT[0]}-{PLAUSIBLE_CAMERA_HEIGHT[1]} m; if the depth is not in metres pass "
            "--rescale always --camera-height H (or the right --png-scale), or --rescale never to keep it as is"
        )
    info = {
        "camera_height_estimated_before": fit.camera_height if fit else None,
        "camera_height_estimated_after": fit.camera_height * factor if fit else None,
        "floor_support": fit.support if fit else None,
        "rescaled": do,
        "scale_factor": factor,
        **({"units": unit[0]} if unit is not None else {}),
    }
    if note:
        info["scale_note"] = note
    return (depth * np.float32(factor)).astype(np.float32), info
