"""The numba kernels of the ERP rasteriser's occlusion culling (face clusters, their bounding spheres, the test of
a cluster against the z-buffer's tiles); panoworld.render.rasterize drives them."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from panoworld.render.raster_kernels import _NO_HIT

# Faces are grouped into spatially compact clusters (Morton order of their centroids), each bounded by a sphere. A
# frame first rasterises the clusters the previous frame saw, then only those clusters whose sphere's footprint
# reaches a pixel whose z-buffered distance is not nearer than the sphere: a skipped cluster has no face that could
# win any pixel, and the z-buffer's keys do not depend on the order faces arrive in, so the result is the same.


@njit(cache=True, nogil=True)
def _morton_keys(points, lo, scale):
    """(N,) int64 Morton codes of points (N, 3) quantised as (p - lo) * scale to 21 bits per axis."""
    out = np.empty(points.shape[0], np.int64)
    for n in range(points.shape[0]):
        key = np.int64(0)
        q0 = np.int64(min(max((points[n, 0] - lo[0]) * scale, 0.0), 2097151.0))
        q1 = np.int64(min(max((points[n, 1] - lo[1]) * scale, 0.0), 2097151.0))
        q2 = np.int64(min(max((points[n, 2] - lo[2]) * scale, 0.0), 2097151.0))
        for b in range(21):
            key |= ((q0 >> b) & 1) << (3 * b)
            key |= ((q1 >> b) & 1) << (3 * b + 1)
            key |= ((q2 >> b) & 1) << (3 * b + 2)
        out[n] = key
    return out


@njit(cache=True, nogil=True)
def _cluster_vertices(faces, order, starts, n_vertices):
    """Each cluster's distinct vertices: (ptr (C + 1,), idx) for the faces order[starts[c]:starts[c + 1]]."""
    stamp = np.full(n_vertices, -1, np.int64)
    ptr = np.zeros(len(starts), np.int64)
    idx = np.empty(3 * len(order), np.int32)
    m = 0
    for c in range(len(starts) - 1):
        for t in range(starts[c], starts[c + 1]):
            f = order[t]
            for e in range(3):
                v = faces[f, e]
                if stamp[v] != c:
                    stamp[v] = c
                    idx[m] = v
                    m += 1
        ptr[c + 1] = m
    return ptr, idx[:m].copy()


@njit(parallel=True, cache=True, nogil=True)
def _cluster_spheres(verts, vptr, vidx, centres, radii):
    """Centre (C, 3) and radius (C,) of a sphere around each cluster's vertices (its bounding box's)."""
    for c in prange(len(radii)):
        lo0 = lo1 = lo2 = np.inf
        hi0 = hi1 = hi2 = -np.inf
        for t in range(vptr[c], vptr[c + 1]):
            v = vidx[t]
            lo0 = min(lo0, np.float64(verts[v, 0]))
            lo1 = min(lo1, np.float64(verts[v, 1]))
            lo2 = min(lo2, np.float64(verts[v, 2]))
            hi0 = max(hi0, np.float64(verts[v, 0]))
            hi1 = max(hi1, np.float64(verts[v, 1]))
            hi2 = max(hi2, np.float64(verts[v, 2]))
        centres[c, 0] = 0.5 * (lo0 + hi0)
        centres[c, 1] = 0.5 * (lo1 + hi1)
        centres[c, 2] = 0.5 * (lo2 + hi2)
        radii[c] = 0.5 * math.sqrt((hi0 - lo0) ** 2 + (hi1 - lo1) ** 2 + (hi2 - lo2) ** 2) * (1.0 + 1e-6) + 1e-6


@njit(parallel=True, cache=True, nogil=True)
def _tile_far(zbufs, width, tile, out):
    """out (ceil(H / tile), ceil(W / tile)) float32: per tile of pixels the largest z-buffered distance over the
    threads' buffers' nearest (inf where a pixel has none)."""
    height = zbufs.shape[1] // width
    for ti in prange(out.shape[0]):
        t32 = np.empty(1, np.float32)
        t_bits = t32.view(np.uint32)
        for tj in range(out.shape[1]):
            out[ti, tj] = 0.0
        for i in range(ti * tile, min(height, ti * tile + tile)):
            for j in range(width):
                key = zbufs[0, i * width + j]
                for t in range(1, zbufs.shape[0]):
                    key = min(key, zbufs[t, i * width + j])
                if key == _NO_HIT:
                    d = np.float32(np.inf)
                else:
                    t_bits[0] = np.uint32(key >> np.uint64(32))
                    d = t32[0]
                if d > out[ti, j // tile]:
                    out[ti, j // tile] = d


@njit(parallel=True, cache=True, nogil=True)
def _may_show(clusters, centres, radii, cam_from_world, tile_far, tile, height, width, out):
    """out[q] True unless cluster clusters[q]'s sphere is hidden: every pixel whose ray can meet it (its angular
    footprint, padded by two pixels) already holds a surface nearer than the sphere (tile_far: _tile_far)."""
    pad = 2.0 * 2.0 * math.pi / width
    n_ti = tile_far.shape[0]
    for q in prange(len(clusters)):
        c = clusters[q]
        x0, y0, z0 = centres[c, 0], centres[c, 1], centres[c, 2]
        x = cam_from_world[0, 0] * x0 + cam_from_world[0, 1] * y0 + cam_from_world[0, 2] * z0 + cam_from_world[0, 3]
        y = cam_from_world[1, 0] * x0 + cam_from_world[1, 1] * y0 + cam_from_world[1, 2] * z0 + cam_from_world[1, 3]
        z = cam_from_world[2, 0] * x0 + cam_from_world[2, 1] * y0 + cam_from_world[2, 2] * z0 + cam_from_world[2, 3]
        rxz = math.sqrt(x * x + z * z)
        d = math.sqrt(rxz * rxz + y * y)
        r = radii[c]
        if d <= 1.001 * r + 1e-6:
            out[q] = True
            continue
        near = (d - r) * (1.0 - 1e-4)
        a = math.asin(r / d) + pad
        lat = math.atan2(-y, rxz)
        i0 = max(0, int(math.floor((0.5 - (lat + a) / math.pi) * height - 0.5)))
        i1 = min(height - 1, int(math.ceil((0.5 - (lat - a) / math.pi) * height - 0.5)))
        if lat + a >= 0.5 * math.pi or lat - a <= -0.5 * math.pi or a >= 0.25 * math.pi:
            j0 = 0
            j1 = width - 1
        else:
            half = math.asin(min(1.0, math.sin(a) / math.cos(lat))) + pad
            u = (math.atan2(x, z) / (2.0 * math.pi) + 0.5) * width
            du = half * width / (2.0 * math.pi)
            j0 = int(math.floor(u - du - 0.5)) + width
            j1 = int(math.ceil(u + du - 0.5)) + width
            if j1 - j0 >= width - 1:
                j0 = 0
                j1 = width - 1
        a0 = j0 % width
        b0 = j1 % width
        a1 = b1 = -1  # a second piece of columns where the footprint wraps around the seam
        if a0 > b0:
            a1, b1 = 0, b0
            b0 = width - 1
        show = False
        for ti in range(i0 // tile, min(n_ti - 1, i1 // tile) + 1):
            for tj in range(a0 // tile, b0 // tile + 1):
                show |= tile_far[ti, tj] >= near
            if a1 >= 0:
                for tj in range(a1 // tile, b1 // tile + 1):
                    show |= tile_far[ti, tj] >= near
            if show:
                break
        out[q] = show


@njit(parallel=True, cache=True, nogil=True)
def _seen_clusters(zbufs, cluster_of, out):
    """out[c] True for each cluster holding the nearest face of some pixel (over the threads' buffers)."""
    n = zbufs.shape[1]
    for p in prange(n):
        key = zbufs[0, p]
        for t in range(1, zbufs.shape[0]):
            key = min(key, zbufs[t, p])
        if key != _NO_HIT:
            out[cluster_of[np.int64(key & np.uint64(0xFFFFFFFF))]] = True
