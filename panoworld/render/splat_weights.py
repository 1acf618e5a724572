"""numba kernel of render_gs.rasterize_tiles(weights=...): the compositing weights of tile-binned Gaussians, pixel by pixel."""

from __future__ import annotations

import numpy as np
from numba import njit

_F = np.float32
_HALF = _F(-0.5)
_HALF_PX = _F(0.5)
_ONE = _F(1.0)
_ZERO = _F(0.0)
_ALPHA_MIN = _F(1.0 / 255.0)
_ALPHA_MAX = _F(0.99)
_T_MIN = _F(1e-4)


@njit(cache=True, nogil=True)
def tile_weights(xy, conic, opacity, sorted_g, starts, counts, ntx, H, W, tile, chunk, need):
    """Compositing weights (flat pixel index int32, Gaussian index int32, weight > 0 float32) of every pixel, as rasterize_tiles computes
    them: per tile its depth-sorted Gaussians in chunks of `chunk`; within a chunk the transmittance is the chunk's
    starting one times the running product of (1 - alpha) (float64, rounded to float32, as torch.cumprod on CPU);
    a pixel stops at the chunk where it falls below T_MIN. All arithmetic in float32 in torch's order. need (H * W,)
    bool: only those pixels (empty: all)."""
    nmax = 0
    total = 0
    for t in range(counts.shape[0]):  # not counts.max() / sum(): numpy overloads are seconds to compile cold
        nmax = max(nmax, counts[t])
        total += counts[t]
    cap = max(1024, 16 * int(total))
    pix_out = np.empty(cap, np.int32)
    gid_out = np.empty(cap, np.int32)
    w_out = np.empty(cap, np.float32)
    n = 0
    alphas = np.empty(chunk, np.float32)
    gx = np.empty(nmax, np.float32)
    gy = np.empty(nmax, np.float32)
    ga = np.empty(nmax, np.float32)
    gb = np.empty(nmax, np.float32)
    gc = np.empty(nmax, np.float32)
    go = np.empty(nmax, np.float32)
    gcut = np.empty(nmax, np.float32)
    for t in range(counts.shape[0]):
        cnt = counts[t]
        if cnt == 0:
            continue
        s0 = starts[t]
        for i in range(cnt):  # the tile's Gaussians, contiguous
            g = sorted_g[s0 + i]
            gx[i], gy[i] = xy[g, 0], xy[g, 1]
            ga[i], gb[i], gc[i] = conic[g, 0], conic[g, 1], conic[g, 2]
            go[i] = opacity[g]
            # below this power alpha < 1/255 whatever exp's last bit: exp is skipped
            gcut[i] = np.log(_ALPHA_MIN / max(opacity[g], _F(1e-30))) - 0.01
        bx = (t % ntx) * tile
        by = (t // ntx) * tile
        for p in range(tile * tile):
            x = bx + p % tile
            y = by + p // tile
            if x >= W or y >= H or (need.shape[0] and not need[y * W + x]):
                continue
            px = _F(x) + _HALF_PX
            py = _F(y) + _HALF_PX
            T = _ONE
            k = 0
            while k < cnt:
                m = min(chunk, cnt - k)
                for j in range(m):
                    i = k + j
                    dx = px - gx[i]
                    dy = py - gy[i]
                    power = _HALF * (ga[i] * dx * dx + gc[i] * dy * dy) - gb[i] * dx * dy
                    if power < gcut[i] or power > _ZERO:
                        alphas[j] = _ZERO
                    else:
                        a = min(go[i] * _F(np.exp(power)), _ALPHA_MAX)
                        alphas[j] = a if a >= _ALPHA_MIN else _ZERO
                if n + m > cap:  # grow the outputs
                    cap = (n + m) * 3 // 2
                    pix_out = _grow(pix_out, cap)
                    gid_out = _grow(gid_out, cap)
                    w_out = _grow(w_out, cap)
                cum = 1.0
                prev = _ONE
                t_min = T
                t_incl = T
                for j in range(m):
                    cum *= np.float64(_ONE - alphas[j])
                    cp = _F(cum)
                    t_incl = T * cp
                    if t_incl >= _T_MIN:
                        w = alphas[j] * (T * prev)
                        if w > _ZERO:
                            pix_out[n] = y * W + x
                            gid_out[n] = sorted_g[s0 + k + j]
                            w_out[n] = w
                            n += 1
                        t_min = min(t_min, t_incl)
                    prev = cp
                if t_incl < _T_MIN:  # the chunk's padding (alpha 0) leaves the product as its last Gaussian left it
                    break
                T = t_min
                k += chunk
    return pix_out[:n], gid_out[:n], w_out[:n]


@njit(cache=True, nogil=True)
def _tile_ranges(xy, extent, H, W, tile, out):
    """Per Gaussian the tile range (j0, j1, i0, i1) its alpha >= 1/255 box covers, in float32 as render_gs.bin_tiles."""
    for g in range(xy.shape[0]):
        for c, size in ((0, W), (1, H)):
            lo = np.ceil(xy[g, c] - extent[g, c] - _HALF_PX)
            hi = np.floor(xy[g, c] + extent[g, c] - _HALF_PX)
            top = _F(size - 1)
            out[g, 2 * c] = np.int64(min(max(lo, _ZERO), top)) // tile
            out[g, 2 * c + 1] = np.int64(min(max(hi, _ZERO), top)) // tile


@njit(cache=True, nogil=True)
def _bin(ranges, by_depth, ntx, n_tiles):
    counts = np.zeros(n_tiles, np.int64)
    for g in range(ranges.shape[0]):
        j0, j1, i0, i1 = ranges[g, 0], ranges[g, 1], ranges[g, 2], ranges[g, 3]
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                counts[i * ntx + j] += 1
    starts = np.empty(n_tiles, np.int64)  # exclusive prefix sum, by a loop: np.cumsum / sum are ~0.7 s more to compile
    total = 0
    for t in range(n_tiles):
        starts[t] = total
        total += counts[t]
    fill = starts.copy()
    sorted_g = np.empty(total, np.int64)
    for g in by_depth:  # in depth order, so each tile's list is sorted by depth (rank)
        j0, j1, i0, i1 = ranges[g, 0], ranges[g, 1], ranges[g, 2], ranges[g, 3]
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                t = i * ntx + j
                sorted_g[fill[t]] = g
                fill[t] += 1
    return sorted_g, counts, starts


def bin_tiles_numba(xy: np.ndarray, extent: np.ndarray, z: np.ndarray, H: int, W: int, tile: int):
    """render_gs.bin_tiles' (ntx, nty, Gaussian indices sorted by (tile, depth), per-tile counts, starts) from
    projected centres xy (P, 2), box half-extents (P, 2) and depths z (P,) float32, by a counting sort: equal to it
    (its test oracle), for a fraction of its time."""
    ntx, nty = -(-W // tile), -(-H // tile)
    ranges = np.empty((len(xy), 4), np.int64)
    _tile_ranges(np.ascontiguousarray(xy, np.float32), np.ascontiguousarray(extent, np.float32), H, W, tile, ranges)
    sorted_g, counts, starts = _bin(ranges, np.argsort(z, kind="stable"), ntx, ntx * nty)
    return ntx, nty, sorted_g, counts, starts


@njit(cache=True, nogil=True)
def _grow(a, cap):
    out = np.empty(cap, a.dtype)
    for k in range(a.shape[0]):  # a loop: slice assignment compiles numba's shape-mismatch message (~4 s cold)
        out[k] = a[k]
    return out


@njit(cache=True, nogil=True)
def weighted_sums(pix, gid, w, values, size):
    """Per pixel the float64 sums of w x values[gid] (values (G, C) float32) and of w: (size, C + 1)."""
    c = values.shape[1]
    out = np.zeros((size, c + 1), np.float64)
    for k in range(pix.shape[0]):
        p, wk = pix[k], np.float64(w[k])
        for j in range(c):
            out[p, j] += wk * values[gid[k], j]
        out[p, c] += wk
    return out


@njit(cache=True, nogil=True)
def view_candidate_indices(offsets, r2, scale2, rot, fx, fy, cx, cy, H, W, near, kx, ky, lowpass):
    """splats.view_candidates' test in one pass (float64 arithmetic on the float32 inputs): the ascending indices of
    the Gaussians (offsets (N, 3), r2 (N,), scale2 (N,)) whose bound box, kx / ky the Jacobian clamp's factor per
    axis, meets the pinhole view rotated by rot (3, 3) cam_from_world."""
    out = np.empty(offsets.shape[0], np.int64)
    m = 0
    front = near * 0.999
    for i in range(offsets.shape[0]):
        if not r2[i] > 0:
            continue
        ox, oy, oz = np.float64(offsets[i, 0]), np.float64(offsets[i, 1]), np.float64(offsets[i, 2])
        pz = ox * rot[2, 0] + oy * rot[2, 1] + oz * rot[2, 2]
        if not pz > front:
            continue
        s2, rr = np.float64(scale2[i]), np.float64(r2[i])
        inv_z = fx / pz
        ext = np.sqrt(rr * (kx * s2 * inv_z * inv_z + lowpass)) * 1.01 + 1.0
        u = (ox * rot[0, 0] + oy * rot[0, 1] + oz * rot[0, 2]) * inv_z + cx
        if u < 0.5 - ext or u > W - 0.5 + ext:
            continue
        inv_z = fy / pz
        ext = np.sqrt(rr * (ky * s2 * inv_z * inv_z + lowpass)) * 1.01 + 1.0
        v = (ox * rot[1, 0] + oy * rot[1, 1] + oz * rot[1, 2]) * inv_z + cy
        if v < 0.5 - ext or v > H - 0.5 + ext:
            continue
        out[m] = i
        m += 1
    return out[:m].copy()
