"""The ERP rasteriser's numba kernels (vertex pass, per-face raster into per-thread z-buffers, resolve) and their
constants; panoworld.render.rasterize drives them."""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

_NO_HIT = np.uint64(0xFFFFFFFFFFFFFFFF)
# z-buffer key = float32 bits of the ray distance << 32 | face id (positive floats order like their bits): the
# nearest surface wins, ties go to the lower face id, so the result does not depend on the thread count.

# A vertex closer to a pole than this fraction of the top pixel row's angular distance to the pole has no usable
# longitude; its triangles take their longitude range from the other vertices plus a conservative pad.
_POLAR_FRACTION = 0.02
# Bounds (radians) on the errors of the fast atan2 (measured 1.7e-6) and acos (6.8e-5) used for bounding boxes.
_ATAN2_ERR = 2e-5
_ACOS_ERR = 1e-4
# Bounding boxes are padded by this many pixels beyond the approximation errors above (float32 storage of u, v).
_EPS_PX = 1e-2
# Triangles whose bounding box holds more pixels than this get exact per-row longitude spans.
_SPAN_MIN_PIXELS = 48
# At most this many pieces of a row's longitude arcs are kept apart (a thin face seen edge-on, nearly through the
# camera, spans half the panorama in two short pieces; their hull would test every pixel between them).
_MAX_PIECES = 8


# ---------------------------------------------------------------------------------------------- numba kernels

# Helpers compiled once each and inlined by LLVM (forceinline), not by numba's IR inliner: inline="always" copies
# them into the parfor bodies, whose passes then take most of a cold cache's compile (~10 s). error_model="numpy"
# as in a parfor body (x / 0 is inf, not an exception). Helpers taking arrays that run per face or per pixel stay
# inline="always": a separately compiled function increfs each array argument on every call (atomic operations).
_helper = njit(forceinline=True, error_model="numpy")


@_helper
def _atan2_approx(y, x):
    """atan2(y, x) to within _ATAN2_ERR radians (a degree-11 odd polynomial for atan on [0, 1]); for bounding boxes."""
    ax = abs(x)
    ay = abs(y)
    mx = max(ax, ay)
    if mx == 0.0:
        return 0.0
    a = min(ax, ay) / mx
    s = a * a
    r = a * (0.99997726 + s * (-0.33262347 + s * (0.19354346 + s * (-0.11643287 + s * (0.05265332 + s * -0.01172120)))))
    if ay > ax:
        r = 0.5 * math.pi - r
    if x < 0.0:
        r = math.pi - r
    return -r if y < 0.0 else r


@njit(inline="always")
def _vertex(verts, k, cam_from_world, height, width, polar_sin, vdata):
    """Vertex k's camera-frame position, ERP (u, v) (u = NaN near a pole), sin(latitude) and ray distance."""
    x0 = np.float64(verts[k, 0])
    y0 = np.float64(verts[k, 1])
    z0 = np.float64(verts[k, 2])
    x = cam_from_world[0, 0] * x0 + cam_from_world[0, 1] * y0 + cam_from_world[0, 2] * z0 + cam_from_world[0, 3]
    y = cam_from_world[1, 0] * x0 + cam_from_world[1, 1] * y0 + cam_from_world[1, 2] * z0 + cam_from_world[1, 3]
    z = cam_from_world[2, 0] * x0 + cam_from_world[2, 1] * y0 + cam_from_world[2, 2] * z0 + cam_from_world[2, 3]
    rxz = math.sqrt(x * x + z * z)
    r = math.sqrt(rxz * rxz + y * y)
    vdata[k, 0] = x
    vdata[k, 1] = y
    vdata[k, 2] = z
    if rxz <= polar_sin * r:
        vdata[k, 3] = np.nan
    else:
        vdata[k, 3] = (_atan2_approx(x, z) / (2.0 * math.pi) + 0.5) * width
    vdata[k, 4] = (0.5 - _atan2_approx(-y, rxz) / math.pi) * height
    vdata[k, 5] = -y / r if r > 0.0 else 0.0
    vdata[k, 6] = r


@njit(parallel=True, cache=True, nogil=True)
def _vertex_pass(verts, cam_from_world, height, width, polar_sin, vdata):
    """Per vertex: _vertex."""
    for k in prange(verts.shape[0]):
        _vertex(verts, k, cam_from_world, height, width, polar_sin, vdata)


@njit(inline="always")
def _xyz(vdata, k):
    return np.float64(vdata[k, 0]), np.float64(vdata[k, 1]), np.float64(vdata[k, 2])


@_helper
def _wrap(d, width):
    """d (|d| < 1.5 width) wrapped into [-width / 2, width / 2]."""
    if d > 0.5 * width:
        return d - width
    if d < -0.5 * width:
        return d + width
    return d


@_helper
def _acos_approx(x):
    """acos(x) for x in [-1, 1] to within _ACOS_ERR radians (Abramowitz & Stegun 4.4.45)."""
    ax = abs(x)
    r = math.sqrt(1.0 - ax) * (1.5707288 + ax * (-0.2121144 + ax * (0.0742610 + ax * -0.0187293)))
    return math.pi - r if x < 0.0 else r


@njit(inline="always")
def _raster_face(
    f, ia, ib, ic, vdata, height, width, sin_lat, cos_lat, sin_lon, cos_lon, pad_polar, zbuf, bbuf, t32, t_bits, pieces
):
    """Z-buffer one triangle into zbuf (H * W,) uint64 and its barycentrics 1, 2 into bbuf (H * W, 2) float32.

    Candidates: a conservative ERP bounding box (for large faces, per row the intersection of the edges' longitude
    arcs, in up to _MAX_PIECES pieces); each candidate pixel gets the exact cone test of its ray. t32 / t_bits: a
    float32 scratch cell and its uint32 view; pieces: (4, _MAX_PIECES) float64 scratch for the arcs' pieces.
    """
    if vdata[ia, 6] <= 0.0 or vdata[ib, 6] <= 0.0 or vdata[ic, 6] <= 0.0:
        return
    ua = np.float64(vdata[ia, 3])
    ub = np.float64(vdata[ib, 3])
    uc = np.float64(vdata[ic, 3])
    eps = _EPS_PX + _ATAN2_ERR * width / (2.0 * math.pi)
    half = 0.5 * width
    full_width = False
    npolar = int(math.isnan(ua)) + int(math.isnan(ub)) + int(math.isnan(uc))
    ulo = 0.0
    uhi = 0.0
    if npolar == 0:
        dab = _wrap(ub - ua, width)
        dac = _wrap(uc - ua, width)
        dbc = _wrap(uc - ub, width)
        # A triangle around a pole winds once in longitude; a very wide one is just scanned over all columns.
        if abs(dab + dbc - dac) > half or max(abs(dab), abs(dac), abs(dbc)) > 0.45 * width:
            full_width = True
        else:
            ulo = ua + min(0.0, dab, dac) - eps
            uhi = ua + max(0.0, dab, dac) + eps
    elif npolar == 3:
        return
    elif npolar == 2:
        u1 = uc if math.isnan(ua) and math.isnan(ub) else (ub if math.isnan(ua) else ua)
        ulo = u1 - 2.0 * pad_polar - eps
        uhi = u1 + 2.0 * pad_polar + eps
    else:
        if math.isnan(ua):
            u1, u2 = ub, uc
        elif math.isnan(ub):
            u1, u2 = ua, uc
        else:
            u1, u2 = ua, ub
        d12 = _wrap(u2 - u1, width)
        if abs(d12) > 0.45 * width:
            full_width = True
        else:
            ulo = u1 + min(0.0, d12) - pad_polar - eps
            uhi = u1 + max(0.0, d12) + pad_polar + eps
    if full_width:
        j0 = 0
        j1 = width - 1
    else:
        j0 = math.ceil(ulo - 0.5)
        j1 = math.floor(uhi - 0.5)
        if j0 > j1:
            return

    va = np.float64(vdata[ia, 4])
    vb = np.float64(vdata[ib, 4])
    vc = np.float64(vdata[ic, 4])
    vmin = min(va, vb, vc)
    vmax = max(va, vb, vc)
    i0 = max(math.ceil(vmin - 0.5 - eps), 0)
    i1 = min(math.floor(vmax - 0.5 + eps), height - 1)
    ax, ay, az = _xyz(vdata, ia)
    bx, by, bz = _xyz(vdata, ib)
    cx, cy, cz = _xyz(vdata, ic)
    # Great-circle edges bulge in latitude beyond their end points: sin(lat) by at most theta^2 / 8 for an arc of
    # angle theta. theta <= |d lat| + |d lon| bounds it from the bounding box; without a usable longitude range
    # theta^2 / 8 <= 0.31 chord^2 (unit directions) does.
    if npolar == 0 and not full_width:
        theta = (vmax - vmin + 2.0 * eps) * (math.pi / height) + (uhi - ulo) * (2.0 * math.pi / width)
        bulge = 0.125 * theta * theta + 2e-7  # + float32 rounding of the stored sin(lat)
    else:
        ra = np.float64(vdata[ia, 6])
        rb = np.float64(vdata[ib, 6])
        rc = np.float64(vdata[ic, 6])
        c2 = max(
            (ax / ra - bx / rb) ** 2 + (ay / ra - by / rb) ** 2 + (az / ra - bz / rb) ** 2,
            (bx / rb - cx / rc) ** 2 + (by / rb - cy / rc) ** 2 + (bz / rb - cz / rc) ** 2,
            (cx / rc - ax / ra) ** 2 + (cy / rc - ay / ra) ** 2 + (cz / rc - az / ra) ** 2,
        )
        bulge = 0.31 * c2 + 2e-7
    sa = np.float64(vdata[ia, 5])
    sb = np.float64(vdata[ib, 5])
    sc = np.float64(vdata[ic, 5])
    s_hi = max(sa, sb, sc) + bulge
    s_lo = min(sa, sb, sc) - bulge
    if i0 > i1:
        i0 = i1 + 1  # no row centre between the vertices: look only at the two neighbouring rows
    while i0 > 0 and sin_lat[i0 - 1] <= s_hi:
        i0 -= 1
    while i1 < height - 1 and sin_lat[i1 + 1] >= s_lo:
        i1 += 1
    if i0 > i1:
        return

    # Edge normals of the cone spanned by the three vertex rays; d is inside iff d . n_k >= 0 for all k.
    n0x = by * cz - bz * cy
    n0y = bz * cx - bx * cz
    n0z = bx * cy - by * cx
    n1x = cy * az - cz * ay
    n1y = cz * ax - cx * az
    n1z = cx * ay - cy * ax
    n2x = ay * bz - az * by
    n2y = az * bx - ax * bz
    n2z = ax * by - ay * bx
    det = ax * n0x + ay * n0y + az * n0z
    if det == 0.0:
        return
    if det < 0.0:
        n0x, n0y, n0z, n1x, n1y, n1z, n2x, n2y, n2z = -n0x, -n0y, -n0z, -n1x, -n1y, -n1z, -n2x, -n2y, -n2z
        det = -det
    if full_width:
        # Pole directions (0, -1, 0) / (0, 1, 0) inside the cone: the triangle reaches the first / last row.
        if n0y <= 0.0 and n1y <= 0.0 and n2y <= 0.0:
            i0 = 0
        if n0y >= 0.0 and n1y >= 0.0 and n2y >= 0.0:
            i1 = height - 1
    fid = np.uint64(f)
    spans = (i1 - i0 + 1) * (j1 - j0 + 1) > _SPAN_MIN_PIXELS
    a0 = a1 = a2 = c0 = c1 = c2c = 0.0
    lo_box = j0 + 0.5 - eps if not full_width else -1e300
    hi_box = j1 + 0.5 + eps if not full_width else 1e300
    px_per_rad = width / (2.0 * math.pi)
    if spans:
        # Large triangles: per row, edge k admits the arc of longitudes where
        # cos(lat) A_k cos(lon - lon_k) >= n_ky sin(lat), with A_k = |(n_kx, n_kz)| and lon_k = atan2(n_kx, n_kz).
        a0 = math.hypot(n0x, n0z)
        a1 = math.hypot(n1x, n1z)
        a2 = math.hypot(n2x, n2z)
        c0 = _arc_centre(n0x, n0z, width)
        c1 = _arc_centre(n1x, n1z, width)
        c2c = _arc_centre(n2x, n2z, width)
    for i in range(i0, i1 + 1):
        cl = cos_lat[i]
        ny0 = -n0y * sin_lat[i]
        ny1 = -n1y * sin_lat[i]
        ny2 = -n2y * sin_lat[i]
        row = i * width
        if not spans:
            _scan_row(j0, j1, width, row, cl, sin_lon, cos_lon, n0x, n0z, ny0, n1x, n1z, ny1, n2x, n2z, ny2, det, fid,
                      zbuf, bbuf, t32, t_bits)
            continue
        pieces[0, 0] = lo_box
        pieces[1, 0] = hi_box
        n_pieces = np.int64(1)  # not a literal 1: _clip_pieces would compile for Literal[int](1) too
        for a_k, c_k, t_k in ((a0, c0, ny0), (a1, c1, ny1), (a2, c2c, ny2)):
            n_pieces = _clip_pieces(a_k * cl, c_k, t_k, px_per_rad, width, eps, pieces, n_pieces)
            if n_pieces == 0:
                break
        # A pixel in two pieces (a full-width face's pieces may overlap modulo width) is tested twice with the same
        # key: the second test writes nothing.
        for p in range(n_pieces):
            ja = j0
            jb = j1
            lo = pieces[0, p]
            hi = pieces[1, p]
            if hi - lo < width:
                ja = max(j0, math.ceil(lo - 0.5)) if not full_width else math.ceil(lo - 0.5)
                jb = min(j1, math.floor(hi - 0.5)) if not full_width else min(math.floor(hi - 0.5), ja + width - 1)
            _scan_row(ja, jb, width, row, cl, sin_lon, cos_lon, n0x, n0z, ny0, n1x, n1z, ny1, n2x, n2z, ny2, det, fid,
                      zbuf, bbuf, t32, t_bits)


@_helper
def _scan_row(ja, jb, width, row, cl, sin_lon, cos_lon, n0x, n0z, ny0, n1x, n1z, ny1, n2x, n2z, ny2, det, fid, zbuf,
              bbuf, t32, t_bits):
    """The exact cone test of columns ja..jb (wrapped) of one row; z-buffer the pixels inside."""
    for jj in range(ja, jb + 1):
        j = jj
        if j < 0:
            j += width
        elif j >= width:
            j -= width
        sl = sin_lon[j]
        co = cos_lon[j]
        w0 = cl * (n0x * sl + n0z * co) + ny0
        if w0 < 0.0:
            continue
        w1 = cl * (n1x * sl + n1z * co) + ny1
        if w1 < 0.0:
            continue
        w2 = cl * (n2x * sl + n2z * co) + ny2
        if w2 < 0.0:
            continue
        s = w0 + w1 + w2
        if s <= 0.0:
            continue
        inv_s = 1.0 / s
        t32[0] = det * inv_s
        key = (np.uint64(t_bits[0]) << np.uint64(32)) | fid
        if key < zbuf[row + j]:
            zbuf[row + j] = key
            bbuf[row + j, 0] = w1 * inv_s
            bbuf[row + j, 1] = w2 * inv_s


@_helper
def _arc_centre(nx, nz, width):
    """Column (u) where nx sin(lon) + nz cos(lon) peaks: lon = atan2(nx, nz)."""
    return (math.atan2(nx, nz) / (2.0 * math.pi) + 0.5) * width


@_helper
def _clip_pieces(amp, centre, offset, px_per_rad, width, eps, pieces, n):
    """Intersect the n intervals (u) in pieces[0:2, :n] with the set amp * cos(lon - lon_c) + offset >= 0 (an arc
    around column centre, repeating every width columns) -> the number of pieces left, written back into pieces.

    Conservative: the arc is padded by the acos error and eps; an interval as wide as the image (a full-width face
    before its first arc) becomes the arc itself; past _MAX_PIECES pieces the last one takes the hull of the rest.
    """
    if amp <= 1e-300:
        return n if offset >= 0.0 else 0
    kappa = -offset / amp
    if kappa > 1.0 + 1e-12:
        return 0
    if kappa <= -1.0:
        return n
    h = (_acos_approx(min(kappa, 1.0)) + _ACOS_ERR) * px_per_rad + eps
    if h >= 0.5 * width:
        return n
    m = np.int64(0)  # not a literal 0 (one _add_piece compile, not two)
    for p in range(n):
        lo = pieces[0, p]
        hi = pieces[1, p]
        if hi - lo >= width:
            m = _add_piece(pieces, m, centre - h, centre + h)
            continue
        c = 0.5 * (lo + hi)
        c += _wrap(centre - c, width)
        for cc in (c - width, c, c + width):
            a = max(lo, cc - h)
            b = min(hi, cc + h)
            if a <= b:
                m = _add_piece(pieces, m, a, b)
    for p in range(m):
        pieces[0, p] = pieces[2, p]
        pieces[1, p] = pieces[3, p]
    return m


@_helper
def _add_piece(pieces, m, a, b):
    """Append [a, b] to the new pieces (rows 2, 3 of pieces) holding m; when they are full, widen the last one."""
    if m < pieces.shape[1]:
        pieces[2, m] = a
        pieces[3, m] = b
        return m + 1
    pieces[2, m - 1] = min(pieces[2, m - 1], a)
    pieces[3, m - 1] = max(pieces[3, m - 1], b)
    return m


@njit(parallel=True, cache=True, nogil=True)
def _raster_pass(faces, vdata, height, width, sin_lat, cos_lat, sin_lon, cos_lon, pad_polar, chunk_starts, zbufs, bbufs):
    """Rasterise all faces; chunk k of faces goes into the buffers of the thread that runs it."""
    for k in prange(len(chunk_starts) - 1):
        tid = numba.get_thread_id()
        zbuf = zbufs[tid]
        bbuf = bbufs[tid]
        t32 = np.empty(1, np.float32)
        t_bits = t32.view(np.uint32)
        pieces = np.empty((4, _MAX_PIECES), np.float64)
        for f in range(chunk_starts[k], chunk_starts[k + 1]):
            _raster_face(
                f, faces[f, 0], faces[f, 1], faces[f, 2], vdata, height, width,
                sin_lat, cos_lat, sin_lon, cos_lon, pad_polar, zbuf, bbuf, t32, t_bits, pieces,
            )


@njit(inline="always")
def _nearest(zbufs, bbufs, p, t_bits, t32):
    """Merge pixel p of the per-thread buffers (resetting them) -> (key, distance, b1, b2) of the nearest hit."""
    key = zbufs[0, p]
    best = 0
    zbufs[0, p] = _NO_HIT
    for t in range(1, zbufs.shape[0]):
        if zbufs[t, p] < key:
            key = zbufs[t, p]
            best = t
        zbufs[t, p] = _NO_HIT
    t_bits[0] = np.uint32(key >> np.uint64(32))
    return key, t32[0], bbufs[best, p, 0], bbufs[best, p, 1]


@njit(parallel=True, cache=True, nogil=True)
def _resolve_hits(zbufs, bbufs, width, dist, face, bary):
    """Merge the per-thread buffers (and reset them) -> distance (inf), face (-1), barycentrics per pixel."""
    height = dist.shape[0]
    for i in prange(height):
        t32 = np.empty(1, np.float32)
        t_bits = t32.view(np.uint32)
        for j in range(width):
            key, t_hit, b1, b2 = _nearest(zbufs, bbufs, i * width + j, t_bits, t32)
            if key == _NO_HIT:
                dist[i, j] = np.inf
                face[i, j] = -1
                bary[i, j, 0] = 0.0
                bary[i, j, 1] = 0.0
                bary[i, j, 2] = 0.0
                continue
            dist[i, j] = t_hit
            face[i, j] = np.int64(key & np.uint64(0xFFFFFFFF))
            bary[i, j, 0] = 1.0 - b1 - b2
            bary[i, j, 1] = b1
            bary[i, j, 2] = b2


@njit(parallel=True, cache=True, nogil=True)
def _resolve_shaded(zbufs, bbufs, faces, colors, face_valid, width, rgb, depth, mask):
    """Merge the per-thread buffers (and reset them) -> interpolated colour, depth and validity per pixel."""
    height = depth.shape[0]
    for i in prange(height):
        t32 = np.empty(1, np.float32)
        t_bits = t32.view(np.uint32)
        for j in range(width):
            key, t_hit, b1, b2 = _nearest(zbufs, bbufs, i * width + j, t_bits, t32)
            f = np.int64(key & np.uint64(0xFFFFFFFF))
            if key == _NO_HIT or not face_valid[f]:
                rgb[i, j, 0] = 0
                rgb[i, j, 1] = 0
                rgb[i, j, 2] = 0
                depth[i, j] = 0.0
                mask[i, j] = False
                continue
            b0 = 1.0 - b1 - b2
            ia = faces[f, 0]
            ib = faces[f, 1]
            ic = faces[f, 2]
            for ch in range(3):
                c = b0 * colors[ia, ch] + b1 * colors[ib, ch] + b2 * colors[ic, ch] + 0.5
                rgb[i, j, ch] = np.uint8(np.int32(c)) if c < 255.0 else np.uint8(255)
            depth[i, j] = t_hit
            mask[i, j] = True


# Per-cluster variants of _vertex_pass and _raster_pass for the occlusion culling (panoworld.render.cull_kernels). They
# stay beside the helpers they inline: numba's on-disk cache does not notice edits to another file's functions.


@njit(parallel=True, cache=True, nogil=True)
def _vertex_pass_clusters(verts, cam_from_world, height, width, polar_sin, vdata, vptr, vidx, clusters):
    """_vertex for the vertices of the given clusters."""
    for q in prange(len(clusters)):
        c = clusters[q]
        for t in range(vptr[c], vptr[c + 1]):
            _vertex(verts, vidx[t], cam_from_world, height, width, polar_sin, vdata)


@njit(parallel=True, cache=True, nogil=True)
def _raster_clusters(faces, order, starts, clusters, vdata, height, width, sin_lat, cos_lat, sin_lon, cos_lon,
                     pad_polar, zbufs, bbufs):
    """Rasterise the faces of the given clusters, each cluster into the buffers of the thread that runs it."""
    for q in prange(len(clusters)):
        c = clusters[q]
        tid = numba.get_thread_id()
        zbuf = zbufs[tid]
        bbuf = bbufs[tid]
        t32 = np.empty(1, np.float32)
        t_bits = t32.view(np.uint32)
        pieces = np.empty((4, _MAX_PIECES), np.float64)
        for t in range(starts[c], starts[c + 1]):
            f = order[t]
            _raster_face(
                f, faces[f, 0], faces[f, 1], faces[f, 2], vdata, height, width,
                sin_lat, cos_lat, sin_lon, cos_lon, pad_polar, zbuf, bbuf, t32, t_bits, pieces,
            )
