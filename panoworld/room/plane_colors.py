"""The next room's colours as the doorway shows them: a top-down map of the floor seen beyond the room's walls, and
the colour of the walls and the ceiling seen beyond them."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from panoworld.room.layout_columns import PLANE_TOL, ROOM_TOL, WallColumns, shell_along

CELL_M = 0.04
"""Side of a map cell (metres): about a source ERP pixel's footprint on a floor 3 m away at 512 columns."""
REACH_M = 1.5
"""A hidden point this far from the nearest visible cell of the map takes half the map's colour and half the colour
it had (Gaussian fall-off): far from any floor seen, a point on the floor plane may be something else (a wall the
background layer continued the floor through). A longer reach paints more of the next room's floor and more walls
that the layer took for floor."""
MAX_EXTENT_M = 30.0
"""The map spans the visible floor's points clipped to this many metres around the capture point."""
MIN_CELLS = 20
"""Fewer floor cells seen beyond the room's shell: no map (nothing recoloured)."""
MIN_PIXELS = 40
"""Fewer wall (ceiling) pixels seen beyond the room's shell: no colour for the next room's walls (ceiling): its
hidden points keep theirs."""
NEXT_CEILING = False
"""walls_ceiling: the next room's hidden ceiling takes the colour of the ceiling seen beyond the shell too (off: the
part of a ceiling a doorway shows is often its far, darker end)."""
LAMP_LUMA = 245
"""Pixels this bright (8-bit luma) are lamps, not the surface's colour."""


def push_pull(col: np.ndarray, known: np.ndarray) -> np.ndarray:
    """col (n, m, 3) with the known (n, m) cells kept and the others filled from ever coarser area averages of the
    known ones (push-pull: each cell from the nearest scale at which something is known around it)."""
    num, den = [col * known[..., None]], [known.astype(np.float32)]
    while min(den[-1].shape) > 1:
        hh, ww = den[-1].shape
        size = (max(ww // 2, 1), max(hh // 2, 1))
        num.append(cv2.resize(num[-1], size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], 3))
        den.append(cv2.resize(den[-1], size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0]))
    est = num[-1] / np.maximum(den[-1], 1e-12)[..., None]
    for n_, d_ in zip(num[-2::-1], den[-2::-1]):
        up = cv2.resize(est, (d_.shape[1], d_.shape[0]), interpolation=cv2.INTER_LINEAR).reshape(*d_.shape, 3)
        a = np.clip(d_ * 4, 0, 1)[..., None]  # a quarter of a cell's area known: its own mean
        est = a * n_ / np.maximum(d_, 1e-12)[..., None] + (1 - a) * up
    return est.astype(np.float32)


def beyond_shell(walls: WallColumns, pts: np.ndarray) -> np.ndarray:
    """Where points (N, 3) lie farther than ROOM_TOL x the room's shell along their ray (unknown shell: inside)."""
    r = np.linalg.norm(pts, axis=1)
    return r > ROOM_TOL * shell_along(walls, pts / np.maximum(r, 1e-12)[:, None])


@dataclass
class FloorBeyond:
    """The next room's colours beyond the room's shell (walls): the colour map of the floor (height y; cell (i, j)
    covers x in x0 + j * CELL_M, z in z0 + i * CELL_M; weight: the map's share of a point's colour there, REACH_M;
    color None: the floor is left alone), and one colour (3,) for its walls and one for its ceiling (height
    `ceiling`; None: left alone)."""

    y: float
    x0: float
    z0: float
    color: np.ndarray | None  # (n, m, 3) float32
    weight: np.ndarray | None  # (n, m) float32
    walls: WallColumns
    ceiling: float = 0.0
    wall_rgb: np.ndarray | None = None
    ceiling_rgb: np.ndarray | None = None

    def paint(self, pts: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """rgb (N, 3) of points pts (N, 3, canonical frame) with those beyond the room's shell recoloured: on the floor
        plane blended towards the map, on the ceiling plane the ceiling's colour, between them the walls' colour;
        returns (rgb uint8, which points were changed)."""
        out = np.asarray(rgb, np.float32).copy()
        y = pts[:, 1]
        floor = np.abs(y - self.y) < PLANE_TOL * abs(self.y)
        ceil = np.abs(y - self.ceiling) < PLANE_TOL * abs(self.ceiling)
        wall = ~floor & ~ceil & (y > self.ceiling) & (y < self.y)
        todo = (floor & (self.color is not None)) | (ceil & (self.ceiling_rgb is not None)) | (
            wall & (self.wall_rgb is not None))
        todo[todo] = beyond_shell(self.walls, pts[todo])
        on = todo & floor
        if self.color is not None and on.any():
            n, m = self.weight.shape
            j = np.clip(((pts[on, 0] - self.x0) / CELL_M).astype(np.int64), 0, m - 1)
            i = np.clip(((pts[on, 2] - self.z0) / CELL_M).astype(np.int64), 0, n - 1)
            a = self.weight[i, j][:, None]
            out[on] = a * self.color[i, j] + (1 - a) * out[on]
        for part, col in ((ceil, self.ceiling_rgb), (wall, self.wall_rgb)):
            if col is not None:
                out[todo & part] = col
        return np.clip(np.rint(out), 0, 255).astype(np.uint8), todo


def _seen_beyond(walls: WallColumns, points: np.ndarray, on: np.ndarray) -> np.ndarray:
    """The on (h, w) pixels less one pixel at their edges (which mix with what borders them) beyond the room's shell."""
    on = on & (cv2.erode(on.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    on[on] = beyond_shell(walls, points[on].astype(np.float64))
    return on


def _median_beyond(walls: WallColumns, points: np.ndarray, rgb: np.ndarray, on: np.ndarray) -> np.ndarray | None:
    """Median colour (3,) of the on (h, w) pixels seen beyond the room's shell (_seen_beyond), lamps left out; None
    when fewer than MIN_PIXELS."""
    on = _seen_beyond(walls, points, on & (rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
                                           < LAMP_LUMA))
    return np.median(rgb[on], axis=0).astype(np.float32) if on.sum() >= MIN_PIXELS else None


def floor_beyond(points: np.ndarray, rgb: np.ndarray, valid: np.ndarray, *, floor: bool = True,
                 walls_ceiling: bool = False) -> FloorBeyond | None:
    """The FloorBeyond colours of the source view's grid points (h, w, 3), colours (h, w, 3) and valid (h, w): its
    floor and ceiling planes (panoworld.room.floor.fit_planes), the room's shell with a doorway's lintel as the
    wall (panoworld.room.layout_columns.wall_columns, nearest junction) and the pixels seen beyond it. floor: the map of
    the floor pixels there (less one pixel at their edges, which mix the floor and what borders it); walls_ceiling:
    the median colour of the ceiling pixels there and of the walls' (upright pixels on the wall the farthest
    junction of their column finds: the next room's wall seen through the doorway, not the furniture in front of
    it; _median_beyond). None without both planes or with nothing to paint."""
    from panoworld.room.floor import fit_planes
    from panoworld.room.layout_columns import WALL_TOL, wall_columns

    depth = np.linalg.norm(points, axis=-1)
    floor_m, ceiling_m = fit_planes(depth, valid)
    if floor_m is None or ceiling_m is None:
        return None
    walls = wall_columns(points, valid, floor_m, -ceiling_m, nearest=True)
    wall_rgb = ceiling_rgb = None
    y = points[..., 1]
    if walls_ceiling:
        far = wall_columns(points, valid, floor_m, -ceiling_m).dist
        rho = np.hypot(points[..., 0], points[..., 2])
        upright = valid & (y > -ceiling_m * (1 - PLANE_TOL)) & (y < floor_m * (1 - PLANE_TOL))
        upright &= np.abs(rho - far[None]) < WALL_TOL * np.nan_to_num(far, nan=-1.0)[None]
        wall_rgb = _median_beyond(walls, points, rgb, upright)
        ceiling_rgb = _median_beyond(walls, points, rgb, valid & (np.abs(y + ceiling_m) < PLANE_TOL * ceiling_m)
                                     ) if NEXT_CEILING else None
    fm = _floor_map(walls, points, rgb, valid) if floor else None
    if fm is None and wall_rgb is None and ceiling_rgb is None:
        return None
    x0, z0, color, weight = fm if fm is not None else (0.0, 0.0, None, None)
    return FloorBeyond(floor_m, x0, z0, color, weight, walls, -ceiling_m, wall_rgb, ceiling_rgb)


def _floor_map(walls: WallColumns, points: np.ndarray, rgb: np.ndarray, valid: np.ndarray
               ) -> tuple[float, float, np.ndarray, np.ndarray] | None:
    """FloorBeyond's floor map (x0, z0, color, weight) from the floor pixels seen beyond the shell; None if too few."""
    on = _seen_beyond(walls, points, valid & (np.abs(points[..., 1] - walls.floor) < PLANE_TOL * walls.floor))
    if on.sum() < MIN_CELLS:
        return None
    xz = np.clip(points[on][:, [0, 2]].astype(np.float64), -MAX_EXTENT_M, MAX_EXTENT_M)
    lo = xz.min(axis=0) - 3 * REACH_M  # beyond the margin the map's weight is < 0.002
    shape = tuple(((xz.max(axis=0) + 3 * REACH_M - lo) / CELL_M).astype(int)[::-1] + 1)  # (rows: z, columns: x)
    ij = ((xz - lo) / CELL_M).astype(np.int64)
    cell = ij[:, 1] * shape[1] + ij[:, 0]
    cnt = np.bincount(cell, minlength=shape[0] * shape[1]).reshape(shape)
    col = np.stack([np.bincount(cell, rgb[on][:, k].astype(np.float64), shape[0] * shape[1]) for k in range(3)], -1)
    known = cnt > 0
    if known.sum() < MIN_CELLS:
        return None
    fill = push_pull((col.reshape(*shape, 3) / np.maximum(cnt, 1)[..., None]).astype(np.float32), known)
    dist = cv2.distanceTransform((~known).astype(np.uint8), cv2.DIST_L2, 5) * CELL_M
    return float(lo[0]), float(lo[1]), fill, (0.5 ** ((dist / REACH_M) ** 2)).astype(np.float32)
