"""2-D polylines: length, uniform resampling, subdivision, NavMesh-constrained smoothing, truncation."""

from __future__ import annotations

import numpy as np

from panoworld.geometry.navmesh import NavMesh


def polyline_length(pts: np.ndarray, closed: bool = False) -> float:
    p = np.concatenate([pts, pts[:1]]) if closed else pts
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def resample_polyline(
    pts: np.ndarray, n: int, *, closed: bool = False, spacing: float | None = None, equalize: int = 5
) -> np.ndarray:
    """n points (n, D) at equal arc length along a polyline (K, D), starting at pts[0].

    Open: the last point is the end (or at (n - 1) * spacing when given). Closed: the loop back to pts[0] is
    included and the spacing is length / n, so the last point is one step before the start. `equalize`
    iterations then move the points along the curve so the straight steps between them (chords, shorter
    than arcs at bends) become equal, keeping the first and (open) the last point.
    """
    pts = np.asarray(pts, np.float64)
    p = np.concatenate([pts, pts[:1]]) if closed else pts
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if spacing is None:
        spacing = s[-1] / n if closed else s[-1] / max(n - 1, 1)
    t = np.minimum(np.arange(n) * spacing, s[-1])

    def at(t):
        return np.stack([np.interp(t, s, p[:, k]) for k in range(p.shape[1])], axis=1)

    total = s[-1] if closed else t[-1]
    for _ in range(equalize if n > 2 and total > 0 else 0):
        q = at(t)
        chord = np.linalg.norm((np.concatenate([q[1:], q[:1]]) - q) if closed else np.diff(q, axis=0), axis=1)
        arc = np.diff(np.concatenate([t, [s[-1]]])) if closed else np.diff(t)
        w = arc / np.maximum(chord, 1e-9 * max(total, 1e-9))
        arc = w / w.sum() * total
        t = np.concatenate([[0.0], np.cumsum(arc)[:-1]]) if closed else np.concatenate([[0.0], np.cumsum(arc)])
    return at(t)


def subdivide_polyline(pts: np.ndarray, max_segment: float, closed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Insert points so no segment is longer than max_segment -> (points (K, 2), (K,) index of the source vertex or -1)."""
    p = np.concatenate([pts, pts[:1]]) if closed else pts
    n = np.maximum(np.ceil(np.linalg.norm(np.diff(p, axis=0), axis=1) / max_segment).astype(int), 1)
    out = [p[i] + (p[i + 1] - p[i]) * (np.arange(n[i])[:, None] / n[i]) for i in range(len(n))]
    src = [np.concatenate([[i], np.full(n[i] - 1, -1)]) for i in range(len(n))]
    if not closed:
        out.append(p[-1:])
        src.append(np.array([len(p) - 1]))
    return np.concatenate(out), np.concatenate(src).astype(int)


def smooth_polyline(
    nav: NavMesh, pts: np.ndarray, *, closed: bool, iterations: int, pinned: int | None = 0, max_segment: float = 0.3
) -> np.ndarray:
    """Constrained Chaikin corner cutting: a corner is cut only when the new chord stays inside the NavMesh.

    Segments are first split to at most max_segment so cuts stay local. Open polylines keep both ends;
    `pinned` (a vertex index of pts) is never cut (the start of a closed loop).
    """
    pts, src = subdivide_polyline(np.asarray(pts, np.float64), max_segment, closed)
    keep = np.zeros(len(pts), bool)
    if pinned is not None:
        keep[src == pinned] = True
    for _ in range(iterations):
        n = len(pts)
        if n < 3:
            break
        prev = np.roll(pts, 1, axis=0)
        nxt = np.roll(pts, -1, axis=0)
        a = 0.25 * prev + 0.75 * pts
        b = 0.75 * pts + 0.25 * nxt
        cut = ~keep.copy()
        if not closed:
            cut[[0, -1]] = False
        cut[cut] &= ~nav.blocked(a[cut], b[cut])
        out, out_keep = [], []
        for i in range(n):
            if cut[i]:
                out += [a[i], b[i]]
                out_keep += [False, False]
            else:
                out.append(pts[i])
                out_keep.append(bool(keep[i]))
        pts = np.asarray(out)
        keep = np.asarray(out_keep)
        d = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        dup = np.concatenate([[False], d < 1e-9]) & ~keep
        pts, keep = pts[~dup], keep[~dup]
    return pts


def truncate_polyline(pts: np.ndarray, length: float) -> np.ndarray:
    """The first `length` metres of a polyline (K, 2)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if length >= s[-1]:
        return pts.copy()
    k = int(np.searchsorted(s, length, side="right"))
    t = (length - s[k - 1]) / max(seg[k - 1], 1e-30)
    return np.concatenate([pts[:k], (pts[k - 1] + t * (pts[k] - pts[k - 1]))[None]])


# ---------------------------------------------------------------- planning
