"""Floor polygons in x,z: manifold3d cross sections, even-odd tests, distances to rings, constrained triangulation,
line fits."""

from __future__ import annotations

import numpy as np

from panoworld.core.errors import NoFloorError


def ring_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def cross_section(rings: list[np.ndarray]):
    """manifold3d CrossSection of rings (even-odd), cleaned of self-intersections."""
    from manifold3d import CrossSection, FillRule

    return CrossSection([np.ascontiguousarray(r, dtype=np.float64) for r in rings], FillRule.EvenOdd)


def pick_components(cs, xz: np.ndarray, snap_m: float = np.inf, min_area_m2: float = 0.0
                    ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The connected pieces of a CrossSection holding any of the points xz (K, 2): every piece containing one, and for
    a point in none the nearest piece within snap_m of at least min_area_m2 (a sliver the erosion left beside it
    is no floor to roam), else the nearest piece within snap_m. Returns (rings of the kept pieces, contains (K,) bool,
    distance (K,) of each point to its kept piece, 0 inside). Raises NoFloorError when nothing is kept."""
    xz = np.asarray(xz, np.float64).reshape(-1, 2)
    parts = list(cs.decompose())
    pieces = [[np.asarray(r, np.float64) for r in piece.to_polygons()] for piece in parts]
    if not pieces:
        raise NoFloorError("no walkable floor is left after eroding by the agent radius")
    dist = np.empty((len(pieces), len(xz)))
    for k, rings in enumerate(pieces):
        segs = ring_segments(rings)
        dist[k] = np.where(even_odd(xz, segs), 0.0, segment_distance(xz, segs))
    nearest = dist.argmin(axis=0)
    small = np.array([part.area() < min_area_m2 for part in parts])
    if small.any() and not small.all():
        roomy = np.where(small[:, None], np.inf, dist).argmin(axis=0)
        cols = np.arange(len(xz))
        swap = (dist[nearest, cols] > 0) & (dist[roomy, cols] <= snap_m)
        nearest = np.where(swap, roomy, nearest)
    best = dist[nearest, np.arange(len(xz))]
    keep = sorted({int(k) for k, d in zip(nearest, best) if d <= snap_m})
    if not keep:
        raise NoFloorError(f"no walkable floor piece lies within {snap_m} m of any of the {len(xz)} points "
                           f"(nearest {best.min():.2f} m)")
    return [r for k in keep for r in pieces[k]], best == 0.0, best


def ring_segments(rings: list[np.ndarray]) -> np.ndarray:
    """All ring edges as (S, 2, 2)."""
    return np.concatenate([np.stack([r, np.roll(r, -1, axis=0)], 1) for r in rings], axis=0)


def even_odd(points: np.ndarray, segs: np.ndarray, max_pairs: int = 1 << 22) -> np.ndarray:
    """Point-in-polygon (even-odd rule) of points (N, 2) against ring segments (S, 2, 2) -> (N,) bool.

    The same test as even_odd_reference, bit for bit, on only the (point, segment) pairs whose horizontal ray can
    cross: with the points sorted by y, a segment is tested against the run of points with min(ay, by) <= y <
    max(ay, by), at most max_pairs pairs at a time."""
    points = np.asarray(points, np.float64)
    n = len(points)
    out = np.zeros(n, bool)
    if n == 0 or len(segs) == 0:
        return out
    order = np.argsort(points[:, 1], kind="stable")
    xs, ys = points[order, 0], points[order, 1]
    a, b = segs[:, 0], segs[:, 1]
    lo = np.searchsorted(ys, np.minimum(a[:, 1], b[:, 1]), side="left")
    cnt = np.searchsorted(ys, np.maximum(a[:, 1], b[:, 1]), side="left") - lo
    todo = np.flatnonzero(cnt > 0)
    ends = np.cumsum(cnt[todo])
    crossings = np.zeros(n, np.int64)
    start = 0
    while start < len(todo):
        done = int(ends[start - 1]) if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, done + max_pairs, side="right")))
        s = todo[start:stop]
        c = cnt[s]
        seg = np.repeat(s, c)
        pi = np.repeat(lo[s] - (ends[start:stop] - c - done), c) + np.arange(len(seg))
        ax, ay, bx, by = a[seg, 0], a[seg, 1], b[seg, 0], b[seg, 1]
        xint = ax + (ys[pi] - ay) * (bx - ax) / (by - ay)
        crossings += np.bincount(pi[xs[pi] < xint], minlength=n)
        start = stop
    out[order] = crossings % 2 == 1
    return out


def even_odd_reference(points: np.ndarray, segs: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """even_odd by testing every point against every segment (the test oracle)."""
    out = np.zeros(len(points), bool)
    a, b = segs[:, 0], segs[:, 1]
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk, None, :]
        cond = (a[None, :, 1] > p[..., 1]) != (b[None, :, 1] > p[..., 1])
        dy = np.where(cond, b[None, :, 1] - a[None, :, 1], 1.0)
        xint = a[None, :, 0] + (p[..., 1] - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / dy
        out[s : s + chunk] = (np.count_nonzero(cond & (p[..., 0] < xint), axis=1) % 2) == 1
    return out


def segment_distance(points: np.ndarray, segs: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Distance of points (N, 2) to the nearest of segments (S, 2, 2) -> (N,)."""
    out = np.empty(len(points))
    a, ab = segs[:, 0], segs[:, 1] - segs[:, 0]
    ll = np.maximum((ab**2).sum(1), 1e-30)
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk, None, :]
        t = np.clip(((p - a) * ab).sum(-1) / ll, 0.0, 1.0)
        out[s : s + chunk] = np.sqrt(((a + t[..., None] * ab - p) ** 2).sum(-1).min(axis=1))
    return out


def triangulate_rings(rings: list[np.ndarray], max_area_m2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Constrained quality triangulation ('triangle' pq) of CCW outer rings and CW holes.

    Returns vertices (V, 2), CCW triangles (T, 3), adjacency (T, 3): the triangle across the edge opposite
    vertex k, or -1 on the boundary.
    """
    import triangle
    from manifold3d import triangulate

    verts, segs, holes = [], [], []
    base = 0
    for r in rings:
        n = len(r)
        verts.append(r)
        segs.append(np.stack([np.arange(n), (np.arange(n) + 1) % n], 1) + base)
        base += n
        if ring_area(r) < 0:  # a hole: Triangle needs a point strictly inside it (a zero-area hole needs none)
            ccw = r[::-1].copy()
            tris = np.asarray(triangulate([ccw])).reshape(-1, 3)
            if len(tris):
                biggest = max(tris, key=lambda k: abs(ring_area(ccw[k])))
                holes.append(ccw[biggest].mean(axis=0))
    data = {"vertices": np.concatenate(verts), "segments": np.concatenate(segs)}
    if holes:
        data["holes"] = np.asarray(holes)
    out = triangle.triangulate(data, f"pq25na{max_area_m2:.6f}")
    if "triangles" not in out or len(out["triangles"]) == 0:
        raise NoFloorError("the walkable floor polygon is degenerate (no triangles)")
    return np.asarray(out["vertices"], np.float64), np.asarray(out["triangles"], np.int32), np.asarray(out["neighbors"], np.int32)


def fit_line(p: np.ndarray) -> tuple[np.ndarray, float]:
    """Line n . q = c (n unit) through the 2D points p (K, 2), total least squares."""
    c = p.mean(axis=0)
    if len(p) < 2:
        n = c / max(np.linalg.norm(c), 1e-12)
    else:
        n = np.linalg.svd(p - c, full_matrices=False)[2][-1]
    return n, float(n @ c)
