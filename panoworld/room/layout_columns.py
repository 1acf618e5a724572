"""The room's walls per ERP column as seen from the capture point, interpolated across the columns tall objects hide."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panoworld.geometry.polygons import fit_line

PLANE_TOL = 0.03
"""A point lies on the floor (ceiling) plane when its height is within this fraction of the plane's distance."""
WALL_TOL = 0.03
"""A point lies on a column's wall when its horizontal distance is within this fraction of the wall's."""
MAX_SPAN_DEG = 100.0
"""Hidden spans of columns wider than this stay unknown (no wall guessed)."""
LINE_COLS_DEG = 4.0
"""Each side's wall line is fitted to the visible junctions within this many degrees of the hidden span."""

COLOR_EDGE_COLS = 1
"""wall_colors: the wall columns next to a hidden span left out (their pixels mix the wall and the occluder)."""
COLOR_SIGMA_COLS = 1
"""wall_colors: the seen wall colour smoothed over this many columns (sigma) before it is carried across a span
(wider smoothing blends in lit wall and loses the occluder's shadow the columns next to it carry)."""
COLOR_SIGMA_BINS = 1.5
"""wall_colors: ... and over this many height bins (sigma), which also closes the bins no pixel row fell in."""

ROOM_TOL = 1.05
"""A point farther than this times the room's shell along its ray is outside the room (the next room through a
doorway)."""

LINEAR, LEFT, RIGHT = 0, 1, 2
"""WallColumns.owner: a hidden column's colour blends both sides' wall (one wall), or takes the left / right side's
(a corner hidden between two walls)."""


@dataclass
class WallColumns:
    """Per ERP column j: the horizontal distance dist[j] (metres; nan = unknown) from the camera to the room's wall
    along the column's azimuth; visible[j] where the wall meets the ceiling or floor in sight, else interpolated;
    owner[j] how a hidden column takes its colour (LINEAR, LEFT, RIGHT); floor / ceiling: the planes' heights y
    (canonical frame, y down: floor > 0 > ceiling)."""

    dist: np.ndarray
    visible: np.ndarray
    owner: np.ndarray
    floor: float
    ceiling: float


def _horizontal(points: np.ndarray) -> np.ndarray:
    return np.hypot(points[..., 0], points[..., 2])


def _column_azimuth(w: int) -> np.ndarray:
    """Unit horizontal directions (w, 2) as (x, z) of the ERP columns' centres (panoworld.core.conventions: lon 0 = +z)."""
    from panoworld.core.conventions import dir_from_lonlat, erp_lonlat_from_pixel

    d = dir_from_lonlat(*erp_lonlat_from_pixel(np.arange(w) + 0.5, np.full(w, w / 4), w // 2, w))
    return d[:, [0, 2]] / np.linalg.norm(d[:, [0, 2]], axis=1, keepdims=True)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Circular runs [start, end] (inclusive, end may wrap past w) of True in mask (w,), not all True."""
    k = int(np.flatnonzero(~mask)[0])
    m = np.roll(mask, -k)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], m.astype(np.int8), [0]])))
    return [(int(a) + k, int(b) - 1 + k) for a, b in zip(edges[::2], edges[1::2])]


def _ray_line(u: np.ndarray, n: np.ndarray, c: float) -> np.ndarray:
    """Distances along the unit directions u (K, 2) to the line n . q = c (inf where parallel or behind)."""
    cos = u @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = c / cos
    return np.where((np.abs(cos) > 1e-3) & (t > 0), t, np.inf)


def _front_pieces(r: np.ndarray) -> np.ndarray:
    """(w,) bool: the columns of r (w,) (nan = unknown) in pieces of continuous distance (within 2 * WALL_TOL between
    neighbouring columns) that are nearer than the known distance beside them on both sides: objects in front of
    the wall (a pillar reaching the ceiling), not the wall."""
    w = len(r)
    known = np.isfinite(r)
    nxt = np.roll(r, -1)
    joined = known & np.roll(known, -1) & (np.abs(nxt - r) <= 2 * WALL_TOL * np.fmin(r, nxt))
    if joined.all() or not known.any():
        return np.zeros(w, bool)
    front = np.zeros(w, bool)
    starts = np.flatnonzero(known & ~np.roll(joined, 1))
    kidx = np.flatnonzero(known)
    for a in starts:
        b = a
        while joined[b % w]:
            b += 1
        prev = kidx[kidx < a][-1] if (kidx < a).any() else kidx[-1]
        later = kidx[kidx > b % w]  # a run may wrap past the seam: the column after it is then below a
        after = later[0] if later.size else kidx[0]
        cols = np.arange(a, b + 1) % w
        if r[a] < (1 - 2 * WALL_TOL) * r[prev] and r[b % w] < (1 - 2 * WALL_TOL) * r[after]:
            front[cols] = True
    return front


def wall_columns(points: np.ndarray, valid: np.ndarray, floor: float, ceiling: float, *, nearest: bool = False
                 ) -> WallColumns:
    """The walls of the room around the capture point, one distance per ERP column.

    points (h, w, 3): the source view's points (canonical frame, y down), valid (h, w); floor > 0 > ceiling: the
    fitted planes' heights. A column's wall is seen where an upright pixel meets the ceiling (or, without one, the
    floor) with continuous depth: its horizontal distance; pieces of columns nearer than the columns on both sides of
    them are objects against the ceiling or floor, not walls (_front_pieces). The columns between two seen runs
    (hidden by tall objects, up to MAX_SPAN_DEG) take the wall line through both ends when the two runs' lines agree
    (one wall), else the nearer of the two runs' lines extended (a convex corner behind the object).
    """
    h, w = valid.shape
    y = points[..., 1]
    depth = np.linalg.norm(points, axis=-1)
    rho = _horizontal(points)
    on_floor = valid & (np.abs(y - floor) < PLANE_TOL * abs(floor))
    on_ceil = valid & (np.abs(y - ceiling) < PLANE_TOL * abs(ceiling))
    upright = valid & ~on_floor & ~on_ceil
    cont = np.abs(depth[1:] - depth[:-1]) < 0.05 * np.maximum(depth[1:], depth[:-1])
    ceil_j = upright[1:] & on_ceil[:-1] & cont
    floor_j = upright[:-1] & on_floor[1:] & cont
    if nearest:
        r_c = np.where(ceil_j, rho[1:], np.inf).min(axis=0)
        r_f = np.where(floor_j, rho[:-1], np.inf).min(axis=0)
    else:
        r_c = np.where(ceil_j, rho[1:], -np.inf).max(axis=0)
        r_f = np.where(floor_j, rho[:-1], -np.inf).max(axis=0)
    r = np.where(np.isfinite(r_c), r_c, np.where(np.isfinite(r_f), r_f, np.nan))  # +-inf: no junction
    visible = np.isfinite(r) & ~_front_pieces(r)
    dist = np.where(visible, r, np.nan)
    owner = np.full(w, LINEAR, np.int8)
    if visible.all() or not visible.any():
        return WallColumns(dist, visible, owner, floor, ceiling)
    u = _column_azimuth(w)
    q = u * np.where(visible, r, 0.0)[:, None]
    n_line = max(2, int(round(w * LINE_COLS_DEG / 360)))
    runs = _runs(visible)
    max_span = w * MAX_SPAN_DEG / 360
    for (a0, a1), (b0, b1) in zip(runs, runs[1:] + [(runs[0][0] + w, runs[0][1] + w)]):
        span = np.arange(a1 + 1, b0) % w
        if not len(span) or len(span) > max_span:
            continue
        left = np.arange(max(a0, a1 - n_line + 1), a1 + 1) % w
        right = np.arange(b0, min(b1, b0 + n_line - 1) + 1) % w
        nl, cl = fit_line(q[left])
        nr, cr = fit_line(q[right])
        pl, pr = q[a1 % w], q[b0 % w]
        same = abs(nl @ nr) > np.cos(np.deg2rad(10)) and abs(nl @ pr - cl) < 2 * WALL_TOL * np.linalg.norm(pr)
        if same:
            chord = pr - pl
            n = np.array([-chord[1], chord[0]]) / max(np.linalg.norm(chord), 1e-12)
            t = _ray_line(u[span], n, float(n @ pl))
        else:
            tl, tr = _ray_line(u[span], nl, cl), _ray_line(u[span], nr, cr)
            t = np.minimum(tl, tr)
            owner[span] = np.where(tl <= tr, LEFT, RIGHT)
        dist[span] = np.where(np.isfinite(t), t, np.nan)
    return WallColumns(dist, visible, owner, floor, ceiling)


def shell_depth(walls: WallColumns, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth (h, w) along the unit rays dirs (h, w, 3) to the room's shell (the nearest of the column's wall, the
    floor and the ceiling; inf where none is known) and whether that is the wall (h, w) bool."""
    horiz = _horizontal(dirs)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = np.where(np.isfinite(walls.dist)[None], walls.dist[None] / horiz, np.inf)
        t_floor = np.where(dirs[..., 1] > 1e-3, walls.floor / dirs[..., 1], np.inf)
        t_ceil = np.where(dirs[..., 1] < -1e-3, walls.ceiling / dirs[..., 1], np.inf)
    t_wall = np.where(t_wall > 0, t_wall, np.inf)
    t_plane = np.minimum(t_floor, t_ceil)
    return np.minimum(t_wall, t_plane), t_wall < t_plane


def column_of(dirs: np.ndarray, w: int) -> np.ndarray:
    """(N,) int: the ERP column (of w) that the azimuth of each direction dirs (N, 3) falls in (the seam wraps)."""
    from panoworld.core.conventions import erp_pixel_from_dir

    u, _ = erp_pixel_from_dir(dirs, w // 2, w)
    return np.mod(np.floor(u).astype(np.int64), w)


def shell_along(walls: WallColumns, dirs: np.ndarray) -> np.ndarray:
    """shell_depth for any unit rays dirs (N, 3): each takes the wall of the ERP column its azimuth falls in."""
    j = column_of(dirs, len(walls.dist))
    cols = WallColumns(walls.dist[j], walls.visible[j], walls.owner[j], walls.floor, walls.ceiling)
    return shell_depth(cols, dirs[None])[0][0]


def _fill_along(values: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index of the nearest known cell before and after each cell along axis 0 of known (n, m) (-1 / n where none),
    and the nearer one's values (n, m, C); no wrapping."""
    n = known.shape[0]
    idx = np.where(known, np.arange(n)[:, None], -1)
    before = np.maximum.accumulate(idx, axis=0)
    idx = np.where(known, np.arange(n)[:, None], n)
    after = np.minimum.accumulate(idx[::-1], axis=0)[::-1]
    cols = np.broadcast_to(np.arange(known.shape[1]), known.shape)
    near = np.where((before >= 0) & ((after >= n) | (np.arange(n)[:, None] - before <= after - np.arange(n)[:, None])),
                    before, after)
    return before, after, values[np.clip(near, 0, n - 1), cols]


def wall_colors(walls: WallColumns, points: np.ndarray, rgb: np.ndarray, seen: np.ndarray, bins: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """The walls' colour at every column and height: (bins, w, 3) float32 and (bins, w) bool where known.

    The visible wall pixels (seen (h, w), within WALL_TOL of their column's wall and off the floor and ceiling
    planes) are averaged per column and height bin (bins between the ceiling and the floor) and smoothed a little
    (COLOR_SIGMA_COLS, COLOR_SIGMA_BINS), leaving out the COLOR_EDGE_COLS columns next to a hidden span (mixed with
    the occluder); each cell between two seen cells of the same height bin takes them blended by column (owner
    LINEAR), or the left / right one alone (a corner: LEFT / RIGHT); bins seen nowhere in a column take the nearest
    bin of that column. The columns beside an occluder carry its shadow onto the hidden wall, hence little smoothing."""
    import cv2

    h, w = seen.shape
    rho = _horizontal(points)
    dist = np.nan_to_num(walls.dist, nan=-1.0)[None]
    y = points[..., 1]
    on_wall = seen & (dist > 0) & (np.abs(rho - dist) < WALL_TOL * dist)
    on_wall &= (y > walls.ceiling * (1 - PLANE_TOL)) & (y < walls.floor * (1 - PLANE_TOL))
    ii, jj = np.nonzero(on_wall)
    cell = height_bin(walls, y[ii, jj], bins) * w + jj
    count = np.bincount(cell, minlength=bins * w).reshape(bins, w)
    col = np.stack([np.bincount(cell, rgb[ii, jj, c].astype(np.float64), bins * w) for c in range(3)], -1)
    col = col.reshape(bins, w, 3) / np.maximum(count, 1)[..., None]
    seen_cell = count > 0
    for k in range(1, COLOR_EDGE_COLS + 1):
        seen_cell &= np.roll(count > 0, k, axis=1) & np.roll(count > 0, -k, axis=1)
    pad = 4 * COLOR_SIGMA_COLS
    wt = np.concatenate([seen_cell[:, -pad:], seen_cell, seen_cell[:, :pad]], axis=1).astype(np.float32)
    cp = np.concatenate([col[:, -pad:], col, col[:, :pad]], axis=1).astype(np.float32) * wt[..., None]
    num, den = (cv2.GaussianBlur(x, (0, 0), sigmaX=COLOR_SIGMA_COLS, sigmaY=COLOR_SIGMA_BINS)[:, pad:pad + w]
                for x in (cp, wt))
    known = den > 0.05  # seen cells and the small gaps between them
    col = np.where(known[..., None], num / np.maximum(den, 1e-6)[..., None], 0.0)
    # nearest known column to the left / right of every cell, on the columns tiled three times (the seam wraps)
    left, right, _ = _fill_along(np.tile(col, (1, 3, 1)).transpose(1, 0, 2), np.tile(known, 3).T)
    left, right = left.T[:, w:2 * w], right.T[:, w:2 * w]
    ok = (left >= 0) & (right < 3 * w) & (right - left <= w)
    left, right = np.clip(left, 0, 3 * w - 1), np.clip(right, 0, 3 * w - 1)
    a = np.where(right > left, (np.arange(w)[None] + w - left) / np.maximum(right - left, 1), 0.0)
    a = np.where(walls.owner[None] == LEFT, 0.0, np.where(walls.owner[None] == RIGHT, 1.0, a))
    rows = np.arange(bins)[:, None]
    out = (1 - a)[..., None] * col[rows, left % w] + a[..., None] * col[rows, right % w]
    out = np.where(known[..., None], col, out)
    known = known | ok
    before, after, nearest = _fill_along(out, known)
    out = np.where(known[..., None], out, nearest)
    return out.astype(np.float32), known | (((before >= 0) | (after < bins)) & np.isfinite(walls.dist)[None])


def height_bin(walls: WallColumns, y: np.ndarray, bins: int) -> np.ndarray:
    """Height bin (0 at the ceiling, bins - 1 at the floor) of heights y (canonical, y down)."""
    f = (y - walls.ceiling) / (walls.floor - walls.ceiling)
    return np.clip((f * bins).astype(np.int64), 0, bins - 1)
