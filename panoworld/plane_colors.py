"""Top-down colour maps of the floor and ceiling planes from the source view, holes filled from what is visible on them."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from panoworld.layout_columns import PLANE_TOL, ROOM_TOL, WallColumns, shell_along

CELL_M = 0.04
"""Side of a map cell (metres): about a source ERP pixel's footprint on a floor 3 m away at 512 columns."""
MEAN_BLEND_M = 1.5
"""A hidden point this far from the nearest visible cell of its map takes half the map's own fill and half the mean
colour of the plane's visible part (Gaussian fall-off)."""
MAX_EXTENT_M = 30.0
"""Maps span the visible plane's points clipped to this many metres around the capture point."""


@dataclass
class PlaneMap:
    """One plane's colour map: cell (i, j) covers x in x0 + j * CELL_M, z in z0 + i * CELL_M at height y."""

    y: float
    x0: float
    z0: float
    color: np.ndarray  # (regions, n, m, 3) float32: inside the room, outside it (the latter only where seen)
    has: np.ndarray  # (regions,) bool


def _push_pull(col: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """col (n, m, 3) known (n, m): the known cells kept, the others filled from ever coarser area averages of the
    known ones (push-pull), and each cell's distance (cells) to the nearest known one."""
    num, den = [col * known[..., None]], [known.astype(np.float32)]
    while min(den[-1].shape) > 1:
        hh, ww = den[-1].shape
        size = (max(ww // 2, 1), max(hh // 2, 1))
        num.append(cv2.resize(num[-1], size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], 3))
        den.append(cv2.resize(den[-1], size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0]))
    est = num[-1] / np.maximum(den[-1], 1e-12)[..., None]
    for n_, d_ in zip(num[-2::-1], den[-2::-1]):
        up = cv2.resize(est, (d_.shape[1], d_.shape[0]), interpolation=cv2.INTER_LINEAR).reshape(*d_.shape, 3)
        a = np.clip(d_ * 4, 0, 1)[..., None]  # a quarter of a cell known is enough to trust the local mean
        est = np.where(a > 0, a * n_ / np.maximum(d_, 1e-12)[..., None] + (1 - a) * up, up)
    dist = cv2.distanceTransform((~known).astype(np.uint8), cv2.DIST_L2, 5)
    return est.astype(np.float32), dist


def _region(walls: WallColumns | None, pts: np.ndarray) -> np.ndarray:
    """1 where points (N, 3) lie beyond the room's shell along their ray, else 0."""
    if walls is None:
        return np.zeros(len(pts), np.int64)
    r = np.linalg.norm(pts, axis=1)
    shell = shell_along(walls, pts / np.maximum(r, 1e-12)[:, None])
    return (r > ROOM_TOL * shell).astype(np.int64)  # unknown shell (inf): inside


def plane_map(points: np.ndarray, rgb: np.ndarray, seen: np.ndarray, y: float, walls: WallColumns | None
              ) -> PlaneMap | None:
    """The colour map of the horizontal plane at height y from the source view's points (h, w, 3), colours (h, w, 3)
    and seen (h, w) pixels lying on it; None when fewer than 50 such pixels."""
    on = seen & (np.abs(points[..., 1] - y) < PLANE_TOL * abs(y))
    on &= cv2.erode(on.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # edge pixels mix the plane and what borders it
    if on.sum() < 50:
        return None
    pts, col = points[on].astype(np.float64), rgb[on].astype(np.float32)
    xz = np.clip(pts[:, [0, 2]], -MAX_EXTENT_M, MAX_EXTENT_M)
    lo = xz.min(axis=0) - 2 * CELL_M
    shape = tuple(((xz.max(axis=0) - lo) / CELL_M).astype(int)[::-1] + 3)  # (n rows along z, m cols along x)
    ij = ((xz - lo) / CELL_M).astype(np.int64)
    cell = ij[:, 1] * shape[1] + ij[:, 0]
    region = _region(walls, pts)
    maps, has = [], []
    mean = col.mean(axis=0)
    for r in (0, 1):
        sel = region == r
        cnt = np.bincount(cell[sel], minlength=shape[0] * shape[1]).reshape(shape)
        if cnt.sum() < 20:
            maps.append(np.broadcast_to(mean, (*shape, 3)).astype(np.float32))
            has.append(False)
            continue
        c = np.stack([np.bincount(cell[sel], col[sel, k], shape[0] * shape[1]) for k in range(3)], -1).reshape(*shape, 3)
        known = cnt > 0
        fill, dist = _push_pull(c / np.maximum(cnt, 1)[..., None], known)
        a = (0.5 ** ((dist * CELL_M / MEAN_BLEND_M) ** 2))[..., None]
        maps.append((a * fill + (1 - a) * col[sel].mean(axis=0)).astype(np.float32))
        has.append(True)
    return PlaneMap(y, float(lo[0]), float(lo[1]), np.stack(maps), np.array(has))


@dataclass
class PlaneColors:
    """The floor's and ceiling's colour maps of one source view (either may be None) and the room's shell."""

    maps: tuple[PlaneMap | None, ...]
    walls: WallColumns | None

    def paint(self, pts: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """rgb (N, 3) of points pts (N, 3, canonical frame) with those lying on a plane recoloured from its map;
        returns (rgb uint8, which points were recoloured)."""
        out = np.asarray(rgb, np.float32).copy()
        done = np.zeros(len(pts), bool)
        for m in self.maps:
            if m is None:
                continue
            on = ~done & (np.abs(pts[:, 1] - m.y) < PLANE_TOL * abs(m.y))
            if not on.any():
                continue
            p = pts[on]
            region = _region(self.walls, p)
            region = np.where(m.has[region], region, 0)
            n, w_ = m.color.shape[1:3]
            j = np.clip(((p[:, 0] - m.x0) / CELL_M).astype(np.int64), 0, w_ - 1)
            i = np.clip(((p[:, 2] - m.z0) / CELL_M).astype(np.int64), 0, n - 1)
            out[on] = m.color[region, i, j]
            done |= on
        return np.clip(np.rint(out), 0, 255).astype(np.uint8), done


def plane_colors(points: np.ndarray, rgb: np.ndarray, valid: np.ndarray) -> PlaneColors:
    """PlaneColors of the source view's grid points (h, w, 3), colours (h, w, 3) and valid (h, w): floor and ceiling
    planes fitted to its depth (panoworld.depth_complete.fit_planes), maps split by the room's shell
    (panoworld.layout_columns) when both planes are found."""
    from panoworld.depth_complete import fit_planes
    from panoworld.layout_columns import wall_columns

    depth = np.linalg.norm(points, axis=-1)
    floor_m, ceiling_m = fit_planes(depth, valid)
    walls = wall_columns(points, valid, floor_m, -ceiling_m, nearest=True) if floor_m and ceiling_m else None
    maps = tuple(None if y is None else plane_map(points, rgb, valid, y, walls)
                 for y in (floor_m, None if ceiling_m is None else -ceiling_m))
    return PlaneColors(maps, walls)
