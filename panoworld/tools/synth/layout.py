"""Floor plans on a metric grid (rectangular, L-shaped and multi-room with doorways) and their architectural meshes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panoworld.core.errors import PanoWorldError
from panoworld.tools.synth.params import LayoutParams

SOLID = -1
"""Label of grid cells that are inside walls or outside the building."""


class LayoutError(PanoWorldError, RuntimeError):
    """The random floor plan could not be built (the caller retries with another seed)."""


@dataclass(kw_only=True)
class FloorPlan:
    """Grid floor plan; cell (i, j) covers x in origin_x + [j, j+1) * cell, z in origin_z + [i, i+1) * cell."""

    label: np.ndarray
    """(Hz, Wx) int32 room id of each free cell (doorway cells carry one of their rooms' ids), SOLID elsewhere."""
    top: np.ndarray
    """(Hz, Wx) float64 height of the free space above each cell in metres (ceiling, door height or 0)."""
    door: np.ndarray
    """(Hz, Wx) bool doorway cells."""
    cell: float
    """Cell size in metres."""
    origin_x: float
    """World x of the grid's left edge."""
    origin_z: float
    """World z of the grid's first row edge."""
    ceiling: float
    """Ceiling height above the floor in metres."""
    door_height: float
    """Doorway height above the floor in metres."""
    n_rooms: int
    """Number of rooms."""

    def cell_centers(self, ij: np.ndarray) -> np.ndarray:
        """Integer cells (N, 2) as (i, j) -> world (x, z) of their centres, shape (N, 2)."""
        ij = np.asarray(ij, dtype=np.float64)
        return np.stack([self.origin_x + (ij[:, 1] + 0.5) * self.cell, self.origin_z + (ij[:, 0] + 0.5) * self.cell], 1)

    def to_grid(self, xz: np.ndarray) -> np.ndarray:
        """World (x, z) points (N, 2) -> continuous grid coords (N, 2) as (i, j) with cell centres at integers."""
        xz = np.asarray(xz, dtype=np.float64)
        return np.stack([(xz[:, 1] - self.origin_z) / self.cell - 0.5, (xz[:, 0] - self.origin_x) / self.cell - 0.5], 1)


@dataclass(kw_only=True)
class _Room:
    i0: int
    i1: int
    j0: int
    j1: int


def _cells(m: float, cell: float) -> int:
    return int(round(m / cell))


def generate_floor_plan(rng: np.random.Generator, p: LayoutParams) -> FloorPlan:
    """Random rooms attached side by side through walls of p.wall_thickness_m, each joined to the plan by a doorway."""
    c = p.cell_m
    t = _cells(p.wall_thickness_m, c)
    n_rooms = int(rng.integers(p.n_rooms[0], p.n_rooms[1] + 1))
    canvas = _cells(n_rooms * (p.room_size_m[1] + 2 * p.wall_thickness_m) * 2 + 4.0, c)
    label = np.full((canvas, canvas), SOLID, np.int32)
    door = np.zeros((canvas, canvas), bool)
    rooms: list[_Room] = []
    door_min = _cells(p.door_width_m[0], c)
    for r in range(n_rooms):
        for _ in range(200):
            hz, wx = (_cells(float(rng.uniform(*p.room_size_m)), c) for _ in range(2))
            if r == 0:
                i0, j0 = (canvas - hz) // 2, (canvas - wx) // 2
                pid, parent, side = -1, None, None
            else:
                pid = int(rng.integers(len(rooms)))
                parent = rooms[pid]
                side = int(rng.integers(4))
                # Slide the new room along the parent's side, keeping an overlap wide enough for a door.
                if side < 2:
                    lo, hi = parent.j0 - wx + door_min + 2 * t, parent.j1 - door_min - 2 * t
                    if hi < lo:
                        continue
                    j0 = int(rng.integers(lo, hi + 1))
                    i0 = parent.i1 + t if side == 0 else parent.i0 - t - hz
                else:
                    lo, hi = parent.i0 - hz + door_min + 2 * t, parent.i1 - door_min - 2 * t
                    if hi < lo:
                        continue
                    i0 = int(rng.integers(lo, hi + 1))
                    j0 = parent.j1 + t if side == 2 else parent.j0 - t - wx
            room = _Room(i0=i0, i1=i0 + hz, j0=j0, j1=j0 + wx)
            if room.i0 < t or room.j0 < t or room.i1 > canvas - t or room.j1 > canvas - t:
                continue
            if (label[room.i0 - t : room.i1 + t, room.j0 - t : room.j1 + t] != SOLID).any():
                continue
            mask = np.zeros((hz, wx), bool)
            mask[:] = True
            if rng.random() < p.l_shape_prob:
                ci, cj = (int(n * rng.uniform(0.35, 0.6)) for n in (hz, wx))
                corner = int(rng.integers(4))
                si = slice(0, ci) if corner < 2 else slice(hz - ci, hz)
                sj = slice(0, cj) if corner % 2 == 0 else slice(wx - cj, wx)
                mask[si, sj] = False
            sub = label[room.i0 : room.i1, room.j0 : room.j1]
            sub[mask] = r
            if parent is not None and not _cut_door(rng, label, door, parent, pid, room, side, r, t, p):
                sub[mask] = SOLID
                continue
            rooms.append(room)
            break
        else:
            raise LayoutError(f"could not place room {r} of {n_rooms} after 200 tries")
    free = label != SOLID
    ii, jj = np.nonzero(free)
    pad = t + 2
    i_lo, i_hi, j_lo, j_hi = ii.min() - pad, ii.max() + 1 + pad, jj.min() - pad, jj.max() + 1 + pad
    label, door = label[i_lo:i_hi, j_lo:j_hi], door[i_lo:i_hi, j_lo:j_hi]
    ceiling = float(rng.uniform(*p.ceiling_height_m))
    door_height = float(rng.uniform(*p.door_height_m))
    top = np.where(label != SOLID, ceiling, 0.0)
    top[door] = door_height
    # Centre the plan on the first room so the world origin is inside the building.
    r0 = rooms[0]
    origin_x = -((r0.j0 + r0.j1) / 2 - j_lo) * c
    origin_z = -((r0.i0 + r0.i1) / 2 - i_lo) * c
    return FloorPlan(
        label=label, top=top, door=door, cell=c, origin_x=round(origin_x, 6), origin_z=round(origin_z, 6),
        ceiling=ceiling, door_height=door_height, n_rooms=n_rooms,
    )


def _cut_door(
    rng, label, door, parent: _Room, pid: int, room: _Room, side: int, r: int, t: int, p: LayoutParams
) -> bool:
    """Open a doorway through the wall between parent and room where both sides are free; False if none fits."""
    c = p.cell_m
    width = _cells(float(rng.uniform(*p.door_width_m)), c)
    if side < 2:
        wall_i = slice(parent.i1, parent.i1 + t) if side == 0 else slice(room.i1, room.i1 + t)
        before, after = (wall_i.start - 1, wall_i.stop) if side == 0 else (wall_i.stop, wall_i.start - 1)
        both = (label[before, :] == pid) & (label[after, :] == r) & (label[wall_i, :] == SOLID).all(0)
    else:
        wall_j = slice(parent.j1, parent.j1 + t) if side == 2 else slice(room.j1, room.j1 + t)
        before, after = (wall_j.start - 1, wall_j.stop) if side == 2 else (wall_j.stop, wall_j.start - 1)
        both = (label[:, before] == pid) & (label[:, after] == r) & (label[:, wall_j] == SOLID).all(1)
    # Keep a jamb of one wall thickness on both sides of the opening.
    windows = np.convolve(both.astype(np.int32), np.ones(width + 2 * t, np.int32), mode="valid") == width + 2 * t
    starts = np.flatnonzero(windows)
    if len(starts) == 0:
        return False
    s = int(starts[rng.integers(len(starts))]) + t
    if side < 2:
        label[wall_i, s : s + width] = r
        door[wall_i, s : s + width] = True
    else:
        label[s : s + width, wall_j] = r
        door[s : s + width, wall_j] = True
    return True


def greedy_rectangles(mask: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Cover a boolean grid (H, W) with disjoint rectangles (i0, i1, j0, j1), each grown right then down."""
    todo = mask.copy()
    rects = []
    for i, j in zip(*np.nonzero(mask)):
        if not todo[i, j]:
            continue
        row = todo[i, j:]
        w = int(np.argmin(row)) if not row.all() else len(row)
        h = 1
        while i + h < mask.shape[0] and todo[i + h, j : j + w].all():
            h += 1
        todo[i : i + h, j : j + w] = False
        rects.append((int(i), int(i + h), int(j), int(j + w)))
    return rects


@dataclass(kw_only=True)
class Quads:
    """Axis-aligned planar quads, four corners each."""

    corners: np.ndarray
    """(Q, 4, 3) float64 world corners in winding order."""
    normal: np.ndarray
    """(Q, 3) float64 unit normal each quad must face (into free space)."""
    owner: np.ndarray
    """(Q,) int32 room id the quad belongs to."""


def quads_to_mesh(corners: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quads (Q, 4, 3) -> (vertices (4Q, 3), faces (2Q, 3)) with triangle normals along normal (Q, 3)."""
    q = len(corners)
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    flip = np.einsum("qi,qi->q", np.cross(e1, e2), normal) < 0
    corners = np.where(flip[:, None, None], corners[:, ::-1], corners)
    base = 4 * np.arange(q)[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3)
    return corners.reshape(-1, 3), faces


def architecture_quads(plan: FloorPlan) -> dict[str, Quads]:
    """Quads of 'floor', 'ceiling' (incl. door soffits) and 'walls' (vertical faces between cells of different top)."""
    c, ox, oz = plan.cell, plan.origin_x, plan.origin_z
    top, label = plan.top, plan.label
    out: dict[str, list] = {"floor": [], "ceiling": [], "walls": []}

    def add(kind, corners, normal, owner):
        out[kind].append((np.asarray(corners, np.float64), np.asarray(normal, np.float64), owner))

    for r in range(plan.n_rooms):
        for i0, i1, j0, j1 in greedy_rectangles(label == r):
            x0, x1, z0, z1 = ox + j0 * c, ox + j1 * c, oz + i0 * c, oz + i1 * c
            add("floor", [[x0, 0, z0], [x1, 0, z0], [x1, 0, z1], [x0, 0, z1]], [0, -1, 0], r)
        for h in np.unique(top[label == r]):
            for i0, i1, j0, j1 in greedy_rectangles((label == r) & (top == h)):
                x0, x1, z0, z1 = ox + j0 * c, ox + j1 * c, oz + i0 * c, oz + i1 * c
                add("ceiling", [[x0, -h, z0], [x1, -h, z0], [x1, -h, z1], [x0, -h, z1]], [0, 1, 0], r)
    padded = np.pad(top, 1)
    lab = np.pad(label, 1, constant_values=SOLID)
    # Edges between vertically adjacent cells (constant z) and horizontally adjacent cells (constant x).
    for axis in (0, 1):
        a = padded[:-1, :] if axis == 0 else padded[:, :-1]
        b = padded[1:, :] if axis == 0 else padded[:, 1:]
        la = lab[:-1, :] if axis == 0 else lab[:, :-1]
        lb = lab[1:, :] if axis == 0 else lab[:, 1:]
        n_lines = a.shape[axis]
        for k in range(n_lines):
            ta, tb = (a[k], b[k]) if axis == 0 else (a[:, k], b[:, k])
            oa, ob = (la[k], lb[k]) if axis == 0 else (la[:, k], lb[:, k])
            differ = ta != tb
            if not differ.any():
                continue
            lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
            faces_b = tb > ta
            owner = np.where(faces_b, ob, oa)
            key = np.stack([lo, hi, faces_b.astype(float), owner.astype(float)], 1)
            # Runs of consecutive differing edges with the same (lo, hi, facing, owner) become one quad.
            change = np.ones(len(ta), bool)
            change[1:] = (key[1:] != key[:-1]).any(1) | ~differ[:-1]
            starts = np.flatnonzero(differ & change)
            for s in starts:
                e = s + 1
                while e < len(ta) and differ[e] and not change[e]:
                    e += 1
                # Padded index k is the edge after padded cell k, i.e. at grid line k (unpadded).
                line = k
                u0, u1 = s - 1, e - 1
                y0, y1 = -lo[s], -hi[s]
                sign = 1.0 if faces_b[s] else -1.0
                if axis == 0:
                    z = oz + line * c
                    x0, x1 = ox + u0 * c, ox + u1 * c
                    corners = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
                    normal = [0, 0, sign]
                else:
                    x = ox + line * c
                    z0, z1 = oz + u0 * c, oz + u1 * c
                    corners = [[x, y0, z0], [x, y0, z1], [x, y1, z1], [x, y1, z0]]
                    normal = [sign, 0, 0]
                add("walls", corners, normal, int(owner[s]))
    return {
        k: Quads(
            corners=np.array([v[0] for v in vs]).reshape(-1, 4, 3),
            normal=np.array([v[1] for v in vs]).reshape(-1, 3),
            owner=np.array([v[2] for v in vs], np.int32),
        )
        for k, vs in out.items()
    }
