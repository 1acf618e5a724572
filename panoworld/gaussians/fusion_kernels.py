"""Numba kernels of voxel fusion (panoworld.gaussians.fusion), each bit for bit its numpy/torch reference, for less CPU."""

from __future__ import annotations

import numpy as np
from numba import njit

_KEY_BITS = 21
_KEY_HALF = 1 << (_KEY_BITS - 1)
_SQRT12 = 12.0**0.5


@njit(cache=True, nogil=True)
def _frame_points(depth, dirs, world_from_cam, max_depth, pts, px, pts_w):
    """frame_points' pass over the pixels; returns the number of valid ones."""
    h, w = depth.shape
    n = 0
    for i in range(h):
        for j in range(w):
            d = np.float64(depth[i, j])
            if not (np.isfinite(d) and d > 0.0 and (max_depth <= 0.0 or d <= max_depth)):
                pts[i, j, 0] = np.nan
                pts[i, j, 1] = np.nan
                pts[i, j, 2] = np.nan
                continue
            for c in range(3):
                pts[i, j, c] = dirs[i, j, c] * d
            px[n] = i * w + j
            for k in range(3):
                a = world_from_cam[k, 0] * pts[i, j, 0]
                b = world_from_cam[k, 1] * pts[i, j, 1]
                e = world_from_cam[k, 2] * pts[i, j, 2]
                # numpy's einsum("mi,ji->mj") sums its 3 products in two SIMD lanes, (0 + a + e) + (0 + b + 0)
                pts_w[n, k] = 0.0 + (((0.0 + a) + e) + ((0.0 + b) + 0.0)) + world_from_cam[k, 3]
            n += 1
    return n


def frame_points(depth: np.ndarray, dirs: np.ndarray, world_from_cam: np.ndarray, max_depth: float = 0.0):
    """ERP depth (H, W) metres and ray directions (H, W, 3) float64 -> (camera points (H, W, 3) float64, NaN where the
    depth is 0, non-finite or beyond max_depth when > 0; flat indices (M,) of the valid pixels; their world points
    (M, 3) = einsum("mi,ji->mj", points, R) + t of world_from_cam (4, 4)), in one pass: frame_observations' numpy
    (its test oracle), bit for bit."""
    h, w = depth.shape
    pts = np.empty((h, w, 3))
    px = np.empty(h * w, np.int64)
    pts_w = np.empty((h * w, 3))
    n = _frame_points(np.ascontiguousarray(depth), np.ascontiguousarray(dirs, np.float64),
                      np.ascontiguousarray(world_from_cam, np.float64), float(max_depth), pts, px, pts_w)
    return pts, px[:n], pts_w[:n]


@njit(cache=True, inline="always")
def _norm3(x, y, z):
    return np.sqrt((x * x + y * y) + z * z)  # np.linalg.norm(axis=-1)'s order


@njit(cache=True, inline="always")
def _pick(f, b, out):
    """_min_step: out = the shorter of f and b (f on a tie; a non-finite length counts as infinite)."""
    nf = _norm3(f[0], f[1], f[2])
    nb = _norm3(b[0], b[1], b[2])
    nf = nf if np.isfinite(nf) else np.inf
    nb = nb if np.isfinite(nb) else np.inf
    src = f if nf <= nb else b
    for c in range(3):
        out[c] = src[c]


@njit(cache=True, nogil=True, error_model="numpy")
def _footprints(pts, px, dirs, a, b, area, cos):
    """frame_footprints' pass over the pixels px."""
    h, w = pts.shape[:2]
    fwd = np.empty(3)
    bwd = np.empty(3)
    for m in range(px.shape[0]):
        i = px[m] // w
        j = px[m] % w
        jn = (j + 1) % w
        jp = (j - 1) % w
        for c in range(3):
            fwd[c] = pts[i, jn, c] - pts[i, j, c]
            bwd[c] = pts[i, j, c] - pts[i, jp, c]
        _pick(fwd, bwd, a[m])
        for c in range(3):
            fwd[c] = pts[i + 1, j, c] - pts[i, j, c] if i < h - 1 else np.nan
            bwd[c] = pts[i, j, c] - pts[i - 1, j, c] if i > 0 else np.nan
        _pick(fwd, bwd, b[m])
        n0 = a[m, 1] * b[m, 2] - a[m, 2] * b[m, 1]  # np.cross
        n1 = a[m, 2] * b[m, 0] - a[m, 0] * b[m, 2]
        n2 = a[m, 0] * b[m, 1] - a[m, 1] * b[m, 0]
        area[m] = _norm3(n0, n1, n2)
        # np.einsum("mc,mc->m")'s order (two SIMD lanes), as in _frame_points
        dot = 0.0 + (((0.0 + n0 * dirs[i, j, 0]) + n2 * dirs[i, j, 2]) + ((0.0 + n1 * dirs[i, j, 1]) + 0.0))
        cos[m] = abs(dot) / area[m]


def frame_footprints(pts: np.ndarray, px: np.ndarray, dirs: np.ndarray):
    """For the flat pixels px (M,) of an ERP grid of camera points pts (H, W, 3) (NaN = invalid) with ray directions
    dirs (H, W, 3): (steps a (M, 3) along the row and b (M, 3) across rows, gaussians._neighbour_steps'; the area
    |a x b| (M,); |cos| of the angle between a x b and the ray (M,)), as frame_observations' numpy computes them (its
    test oracle), bit for bit."""
    m = len(px)
    a, b = np.empty((m, 3)), np.empty((m, 3))
    area, cos = np.empty(m), np.empty(m)
    _footprints(np.ascontiguousarray(pts, np.float64), np.ascontiguousarray(px, np.int64),
                np.ascontiguousarray(dirs, np.float64), a, b, area, cos)
    return a, b, area, cos


@njit(cache=True, nogil=True)
def _keys(points, voxel_size, keys, ijk):
    """voxel_keys' packing of floor(points / voxel_size); returns the largest |ijk|."""
    big = 0
    for m in range(points.shape[0]):
        packed = 0
        for c in range(3):
            v = np.int64(np.floor(points[m, c] / voxel_size))
            ijk[m, c] = v
            big = max(big, abs(v))
            packed = (packed << _KEY_BITS) | (v + _KEY_HALF)
        keys[m] = packed
    return big


@njit(cache=True, nogil=True)
def _frame_sums(keys, order, ijk, points, colors, steps, weights, voxel_size, out_keys, out_w, out_wv, out_n):
    """Per voxel, in the order of `order` (keys sorted, stable): sum w, sum w * (x - c, rgb, 6 second moments), count,
    the moments as gaussians._moment_values computes them (bmm's naive kernel: products summed from 0 in row order)."""
    v = -1
    last = np.int64(0)
    x = np.empty((3, 3))
    val = np.empty(12)
    for t in range(order.shape[0]):
        m = order[t]
        if v < 0 or keys[m] != last:
            v += 1
            last = keys[m]
            out_keys[v] = last
        for c in range(3):
            x[0, c] = points[m, c] - (np.float64(ijk[m, c]) + 0.5) * voxel_size
            x[1, c] = steps[m, 0, c] / _SQRT12
            x[2, c] = steps[m, 1, c] / _SQRT12
            val[c] = x[0, c]
            val[3 + c] = colors[m, c]
        e = 6
        for i in range(3):
            for j in range(i, 3):
                acc = 0.0
                for k in range(3):
                    acc += x[k, i] * x[k, j]
                val[e] = acc
                e += 1
        w = weights[m]
        out_w[v] += w
        for c in range(12):
            out_wv[v, c] += val[c] * w
        out_n[v] += 1
    return v + 1


@njit(cache=True, nogil=True)
def _merge(first, keys, w, wv, n, starts, out_keys, out_w, out_wv, out_n):
    """The sorted runs `first` (keys, w, wv, n) and keys[starts[r]:starts[r + 1]] (unique keys each) merged, summed
    per key in run order (first, then the others), without copying `first` into the others."""
    fk, fw, fwv, fn = first
    runs = starts.shape[0] - 1
    head = starts[:-1].copy()
    f = 0
    v = 0
    while True:
        found = f < fk.shape[0]
        key = fk[f] if found else np.int64(0)
        for r in range(runs):
            if head[r] < starts[r + 1] and (not found or keys[head[r]] < key):
                key = keys[head[r]]
                found = True
        if not found:
            return v
        out_keys[v] = key
        if f < fk.shape[0] and fk[f] == key:
            out_w[v] += fw[f]
            for c in range(fwv.shape[1]):
                out_wv[v, c] += fwv[f, c]
            out_n[v] += fn[f]
            f += 1
        for r in range(runs):  # then the other runs, in order
            m = head[r]
            if m < starts[r + 1] and keys[m] == key:
                out_w[v] += w[m]
                for c in range(wv.shape[1]):
                    out_wv[v, c] += wv[m, c]
                out_n[v] += n[m]
                head[r] = m + 1
        v += 1


def frame_moment_sums(points: np.ndarray, colors: np.ndarray, steps: np.ndarray, weights: np.ndarray,
                      voxel_size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame's observations (points (M, 3), colors (M, 3), steps (M, 2, 3), weights (M,), float64) -> per occupied
    voxel of size voxel_size (sorted unique keys (V,), sum w (V,), sum w * moments (V, 12), count (V,)): equal bit
    for bit to geometry.voxels.voxel_sums(keys, weights, _moment_values(obs, centre)) (its test oracle)."""
    points, colors, steps, weights = (np.ascontiguousarray(a, np.float64) for a in (points, colors, steps, weights))
    m = len(points)
    keys = np.empty(m, np.int64)
    ijk = np.empty((m, 3), np.int64)
    if _keys(points, float(voxel_size), keys, ijk) >= _KEY_HALF:
        raise ValueError(
            f"points reach {float(np.abs(points).max()):.1f} m, beyond {_KEY_HALF} voxels of {voxel_size} m "
            "from the origin; increase voxel_size or drop far depth"
        )
    order = np.argsort(keys, kind="stable")
    out = _alloc(m, 12)
    v = _frame_sums(keys, order, ijk, points, colors, steps, weights, float(voxel_size), *out)
    return tuple(a[:v] for a in out)


def merge_sums(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]):
    """Several (keys, w, wv, n), keys sorted and unique in each, into one, summed per key in the parts' order
    (merge_voxel_sums', bit for bit). The first part (voxel fusion's running total) is read in place."""
    first, rest = parts[0], parts[1:]
    if not rest:
        rest = [tuple(a[:0] for a in first)]
    keys, w, wv, n = (np.concatenate([p[i] for p in rest]) for i in range(4))
    starts = np.cumsum([0] + [len(p[0]) for p in rest])
    out = _alloc(len(first[0]) + len(keys), first[2].shape[1])
    v = _merge(first, keys, w, wv, n, starts, *out)
    return tuple(a[:v] for a in out)


def _alloc(m: int, c: int):
    return np.empty(m, np.int64), np.zeros(m), np.zeros((m, c)), np.zeros(m, np.int64)
