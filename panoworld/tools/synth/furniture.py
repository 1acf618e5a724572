"""Parametric furniture built from boxes and cylinders, and its collision-free placement on a floor plan."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from scipy import ndimage

from panoworld.core.errors import PanoWorldError
from panoworld.tools.synth.layout import SOLID, FloorPlan
from panoworld.tools.synth.params import FurnitureParams


class FurnitureKind(enum.StrEnum):
    """Library of parametric furniture."""

    TABLE = "table"
    CHAIR = "chair"
    SHELF = "shelf"
    BED = "bed"
    SOFA = "sofa"
    CABINET = "cabinet"
    LAMP = "lamp"
    PILLAR = "pillar"
    PICTURE = "picture"
    CEILING_LIGHT = "ceiling_light"


class Role(enum.StrEnum):
    """Material slot of a furniture part; the scene assigns a concrete material per object and role."""

    WOOD = "wood"
    FABRIC = "fabric"
    FABRIC2 = "fabric2"
    PAINT = "paint"
    METAL = "metal"
    STONE = "stone"
    BOOKS = "books"
    PICTURE = "picture"
    LIGHT = "light"


@dataclass(kw_only=True)
class Part:
    """A mesh piece of a furniture object in its local frame (origin on the floor at the footprint centre, back +z)."""

    role: Role
    """Material slot."""
    mesh: trimesh.Trimesh
    """Geometry in the local frame, y = -height (up = -Y)."""


@dataclass(kw_only=True)
class Placed:
    """One placed object: parts in world coordinates and an optional light it emits."""

    name: str
    """Unique object name, e.g. 'table_03'."""
    kind: FurnitureKind
    """Library entry."""
    parts: list[Part]
    """Parts in world coordinates."""
    room: int
    """Room id."""
    light_at: tuple[float, float, float] | None = None
    """World position of the point light this object carries (lamps, ceiling lights)."""


def _box(role: Role, w: float, h0: float, h1: float, d: float, x: float = 0.0, z: float = 0.0) -> Part:
    """Box of width w (x) and depth d (z) centred at (x, z), spanning heights [h0, h1] above the floor."""
    T = np.eye(4)
    T[:3, 3] = [x, -(h0 + h1) / 2, z]
    return Part(role=role, mesh=trimesh.creation.box(extents=(w, h1 - h0, d), transform=T))


def _cyl(role: Role, r: float, h0: float, h1: float, x: float = 0.0, z: float = 0.0, sections: int = 20) -> Part:
    """Vertical cylinder of radius r centred at (x, z), spanning heights [h0, h1]."""
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # cylinder axis z -> -y
    T[:3, 3] = [x, -(h0 + h1) / 2, z]
    return Part(role=role, mesh=trimesh.creation.cylinder(radius=r, height=h1 - h0, sections=sections, transform=T))


def _legs(role: Role, w: float, d: float, h: float, s: float = 0.05, inset: float = 0.04) -> list[Part]:
    xs, zs = w / 2 - inset - s / 2, d / 2 - inset - s / 2
    return [_box(role, s, 0, h, s, sx * xs, sz * zs) for sx in (-1, 1) for sz in (-1, 1)]


def build_table(rng: np.random.Generator, w: float, d: float) -> list[Part]:
    h = float(rng.uniform(0.72, 0.78))
    leg_role = Role.WOOD if rng.random() < 0.5 else Role.METAL
    return [_box(Role.WOOD, w, h - 0.04, h, d), *_legs(leg_role, w, d, h - 0.03)]


def build_chair(rng: np.random.Generator, w: float, d: float) -> list[Part]:
    seat, back = 0.45, float(rng.uniform(0.82, 0.95))
    seat_role = Role.FABRIC if rng.random() < 0.5 else Role.WOOD
    return [
        _box(seat_role, w, seat - 0.05, seat, d),
        *_legs(Role.WOOD, w, d, seat - 0.04, s=0.04, inset=0.01),
        _box(Role.WOOD, w, seat - 0.01, back, 0.04, 0, d / 2 - 0.02),
    ]


def build_shelf(rng: np.random.Generator, w: float, d: float) -> list[Part]:
    h = float(rng.uniform(1.6, 2.1))
    t = 0.025
    n_levels = int(rng.integers(4, 6))
    parts = [
        _box(Role.WOOD, t, 0, h, d, -w / 2 + t / 2),
        _box(Role.WOOD, t, 0, h, d, w / 2 - t / 2),
        _box(Role.WOOD, w - 1.5 * t, 0, h, t, 0, d / 2 - t / 2),
    ]
    levels = np.linspace(0.05, h - t, n_levels + 1)
    for k, y in enumerate(levels):
        parts.append(_box(Role.WOOD, w - 1.5 * t, y, y + t, d - 0.5 * t, 0, -0.25 * t))
        if k < n_levels and rng.random() < 0.85:
            gap = levels[k + 1] - y - t
            bw = (w - 2 * t) * float(rng.uniform(0.5, 0.95))
            bx = float(rng.uniform(-1, 1)) * ((w - 2 * t) - bw) / 2
            parts.append(_box(Role.BOOKS, bw, y + t, y + t + gap * float(rng.uniform(0.6, 0.85)), d * 0.7, bx, 0.0))
    return parts


def build_bed(rng: np.random.Generator, w: float, d: float) -> list[Part]:
    head = float(rng.uniform(0.9, 1.2))
    parts = [
        _box(Role.WOOD, w, 0, 0.3, d - 0.06, 0, -0.03),
        _box(Role.FABRIC, w - 0.06, 0.29, 0.5, d - 0.12, 0, -0.03),
        _box(Role.WOOD, w, 0, head, 0.06, 0, d / 2 - 0.03),
        _box(Role.FABRIC2, w - 0.02, 0.45, 0.54, (d - 0.12) * 0.62, 0, -0.03 - (d - 0.12) * 0.19),
    ]
    n_pillows = 2 if w > 1.3 else 1
    pw = (w - 0.2) / n_pillows - 0.05
    for k in range(n_pillows):
        x = -w / 2 + 0.1 + (k + 0.5) * (w - 0.2) / n_pillows
        parts.append(_box(Role.FABRIC, pw, 0.48, 0.62, 0.35, x, d / 2 - 0.3))
    return parts


def build_sofa(rng: np.random.Generator, w: float, d: float) -> list[Part]:
    h = float(rng.uniform(0.8, 0.9))
    arm = 0.16
    parts = [
        _box(Role.FABRIC, w, 0.08, 0.4, d),
        _box(Role.FABRIC, w, 0.38, h, 0.2, 0, d / 2 - 0.1),
        _box(Role.FABRIC, arm, 0.38, 0.62, d, -w / 2 + arm / 2),
        _box(Role.FABRIC, arm, 0.38, 0.62, d, w / 2 - arm / 2),
        *_legs(Role.METAL, w, d, 0.09, s=0.04, inset=0.05),
    ]
    n_cush = max(1, int((w - 2 * arm) // 0.6))
    cw = (w - 2 * arm) / n_cush
    for k in range(n_cush):
        parts.append(_box(Role.FABRIC2, cw - 0.02, 0.39, 0.5, d - 0.25, -w / 2 + arm + (k + 0.5) * cw, -0.1))
    return parts


def build_cabinet(rng: np.random.Generator, w: float, d: float) -> list[Part]:
    h = float(rng.choice([rng.uniform(0.75, 1.1), rng.uniform(1.7, 2.0)]))
    body = Role.WOOD if rng.random() < 0.5 else Role.PAINT
    parts = [_box(body, w, 0.0, h, d - 0.02, 0, 0.01), _box(Role.WOOD, w + 0.02, h, h + 0.03, d + 0.01, 0, 0)]
    n_cols = max(1, int(round(w / 0.5)))
    n_rows = 1 if h > 1.5 else int(rng.integers(2, 4))
    cw, rh = w / n_cols, (h - 0.08) / n_rows
    for a in range(n_cols):
        for b in range(n_rows):
            x = -w / 2 + (a + 0.5) * cw
            y0 = 0.06 + b * rh
            parts.append(_box(body, cw - 0.02, y0 + 0.01, y0 + rh - 0.01, 0.02, x, -d / 2 + 0.01))
            hy = y0 + rh / 2 if n_rows > 1 else min(y0 + rh / 2, 1.0)
            parts.append(_box(Role.METAL, 0.12, hy - 0.01, hy + 0.01, 0.03, x, -d / 2 - 0.01))
    return parts


def build_lamp(rng: np.random.Generator, w: float, d: float) -> list[Part]:
    top = float(rng.uniform(1.45, 1.75))
    r = min(w, d) / 2
    return [
        _cyl(Role.METAL, r * 0.7, 0, 0.03),
        _cyl(Role.METAL, 0.015, 0.02, top - 0.25),
        _cyl(Role.FABRIC, r, top - 0.3, top, sections=24),
    ]


def build_pillar(rng: np.random.Generator, w: float, d: float, height: float) -> list[Part]:
    if rng.random() < 0.5:
        return [_cyl(Role.STONE, w / 2, 0, height, sections=32)]
    return [_box(Role.STONE, w, 0, height, d)]


# (footprint width range, depth range) in metres; width runs along the wall for wall-backed objects.
_SIZES = {
    FurnitureKind.TABLE: ((1.0, 1.7), (0.7, 0.95)),
    FurnitureKind.SHELF: ((0.8, 1.6), (0.3, 0.4)),
    FurnitureKind.BED: ((0.95, 1.8), (2.0, 2.15)),
    FurnitureKind.SOFA: ((1.6, 2.4), (0.85, 0.95)),
    FurnitureKind.CABINET: ((0.6, 1.4), (0.4, 0.55)),
    FurnitureKind.LAMP: ((0.36, 0.46), (0.36, 0.46)),
    FurnitureKind.PILLAR: ((0.3, 0.5), (0.3, 0.5)),
}
_BUILDERS = {
    FurnitureKind.TABLE: build_table,
    FurnitureKind.SHELF: build_shelf,
    FurnitureKind.BED: build_bed,
    FurnitureKind.SOFA: build_sofa,
    FurnitureKind.CABINET: build_cabinet,
    FurnitureKind.LAMP: build_lamp,
}
_WALL_BACKED = {FurnitureKind.SHELF, FurnitureKind.BED, FurnitureKind.SOFA, FurnitureKind.CABINET, FurnitureKind.LAMP}
_ROOM_TYPES = [
    [FurnitureKind.BED, FurnitureKind.CABINET, FurnitureKind.LAMP, FurnitureKind.SHELF, FurnitureKind.CABINET],
    [FurnitureKind.SOFA, FurnitureKind.TABLE, FurnitureKind.SHELF, FurnitureKind.LAMP, FurnitureKind.CABINET,
     FurnitureKind.PILLAR],
    [FurnitureKind.TABLE, FurnitureKind.SHELF, FurnitureKind.CABINET, FurnitureKind.LAMP, FurnitureKind.SHELF],
]


def _window_sums(mask: np.ndarray, h: int, w: int) -> np.ndarray:
    """Number of True cells in every h x w window of mask (H, W), indexed by the window's top-left cell."""
    S = cv2.integral(mask.astype(np.uint8))
    return S[h:, w:] - S[:-h, w:] - S[h:, :-w] + S[:-h, :-w]


def _place_parts(parts: list[Part], rot: int, x: float, z: float) -> list[Part]:
    """Rotate local parts by rot * 90 degrees (local +z to world +z, +x, -z, -x) and move them to (x, 0, z)."""
    T = np.eye(4)
    a = rot * np.pi / 2
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [x, 0.0, z]
    return [Part(role=p.role, mesh=p.mesh.copy().apply_transform(T)) for p in parts]


class Placer:
    """Places furniture on a plan's free cells while the camera-walkable floor stays connected across all rooms."""

    def __init__(self, plan: FloorPlan, p: FurnitureParams, clearance: float):
        self.plan = plan
        self.p = p
        self.clearance = clearance
        self.occ = np.zeros(plan.label.shape, bool)
        self.height = np.zeros(plan.label.shape)
        c = plan.cell
        # Keep the approach to every doorway clear of furniture.
        door_zone = ndimage.distance_transform_edt(~plan.door) * c < 0.9
        self.blocked = (plan.label == SOLID) | door_zone
        self.placed: list[Placed] = []
        self._count = 0
        if not self.walkable_ok(self.occ):
            raise PlacementError("the empty floor plan already has no connected walkable floor")

    def walkable(self, occ: np.ndarray) -> np.ndarray:
        """Cells (Hz, Wx) where a camera centre keeps clearance + margin from walls and furniture footprints."""
        free = (self.plan.label != SOLID) & ~occ
        dist = ndimage.distance_transform_edt(free) * self.plan.cell - self.plan.cell / 2
        return dist >= self.clearance + self.p.walk_margin_m

    def walkable_ok(self, occ: np.ndarray) -> bool:
        """True if one 8-connected walkable component reaches every room with at least 1 m^2."""
        comp, n = ndimage.label(self.walkable(occ), structure=np.ones((3, 3)))
        if n == 0:
            return False
        sizes = np.bincount(comp.ravel())
        sizes[0] = 0
        main = comp == int(np.argmax(sizes))
        per_room = np.bincount(self.plan.label[main], minlength=self.plan.n_rooms)
        return bool((per_room * self.plan.cell**2 >= 1.0).all())

    def _name(self, kind: FurnitureKind) -> str:
        self._count += 1
        return f"{kind}_{self._count:02d}"

    def try_place(self, rng: np.random.Generator, kind: FurnitureKind, room: int) -> bool:
        """Try to place one object (a table comes with chairs) in room; False if no valid spot kept the floor walkable."""
        c = self.plan.cell
        (w0, w1), (d0, d1) = _SIZES[kind]
        w, d = float(rng.uniform(w0, w1)), float(rng.uniform(d0, d1))
        if kind == FurnitureKind.BED and w > 1.2:
            w = max(w, 1.4)
        chairs = []
        if kind == FurnitureKind.TABLE:
            n_side = max(1, int((w - 0.3) // 0.6))
            xs = np.linspace(-w / 2, w / 2, n_side + 2)[1:-1]
            chairs = [(x, side) for side in (-1, 1) for x in xs if rng.random() < 0.8]
        foot_d = d + (2 * 0.48 if chairs else 0.0)
        rot = int(rng.integers(4))
        wc, dc = int(np.ceil(w / c)), int(np.ceil(foot_d / c))
        hz, wx = (dc, wc) if rot % 2 == 0 else (wc, dc)
        room_free = (self.plan.label == room) & ~self.blocked & ~self.occ
        if hz >= room_free.shape[0] or wx >= room_free.shape[1]:
            return False
        ok = _window_sums(room_free, hz, wx) == hz * wx
        if kind in _WALL_BACKED:
            solid = self.plan.label == SOLID
            # The row/column just behind the object's back (local +z) must be wall along the whole width.
            if rot == 0:
                back = _window_sums(solid[hz:], 1, wx) == wx
                ok[: back.shape[0]] &= back[: ok.shape[0]]
                ok[back.shape[0] :] = False
            elif rot == 2:
                back = _window_sums(solid, 1, wx)[: ok.shape[0] - 1] == wx
                ok[1:] &= back
                ok[0] = False
            elif rot == 1:
                back = _window_sums(solid[:, wx:], hz, 1) == hz
                ok[:, : back.shape[1]] &= back[:, : ok.shape[1]]
                ok[:, back.shape[1] :] = False
            else:
                back = _window_sums(solid, hz, 1)[:, : ok.shape[1] - 1] == hz
                ok[:, 1:] &= back
                ok[:, 0] = False
        else:
            # Free-standing objects keep a gap to the walls so they do not look glued to them.
            near = ndimage.distance_transform_edt(self.plan.label != SOLID) * c
            ok &= _window_sums(near < 0.3 + c, hz, wx) == 0
        cand = np.argwhere(ok)
        if len(cand) == 0:
            return False
        for k in rng.permutation(len(cand))[:8]:
            i0, j0 = (int(v) for v in cand[k])
            occ = self.occ.copy()
            occ[i0 : i0 + hz, j0 : j0 + wx] = True
            if not self.walkable_ok(occ):
                continue
            x = self.plan.origin_x + (j0 + wx / 2) * c
            z = self.plan.origin_z + (i0 + hz / 2) * c
            # Wall-backed objects sit flush against the wall: shift by the ceil() slack towards their back.
            slack = (dc * c - foot_d) / 2 if kind in _WALL_BACKED else 0.0
            bx, bz = [(0, 1), (1, 0), (0, -1), (-1, 0)][rot]
            x, z = x + bx * slack, z + bz * slack
            self._commit(rng, kind, room, w, d, rot, x, z, chairs, occ, i0, j0, hz, wx)
            return True
        return False

    def _commit(self, rng, kind, room, w, d, rot, x, z, chairs, occ, i0, j0, hz, wx):
        if kind == FurnitureKind.PILLAR:
            parts = build_pillar(rng, w, d, self.plan.ceiling)
        else:
            parts = _BUILDERS[kind](rng, w, d)
        name = self._name(kind)
        top = max(-p.mesh.bounds[0][1] for p in parts)
        light_at = None
        if kind == FurnitureKind.LAMP:
            light_at = (x, -(top + 0.15), z)
        self.placed.append(Placed(name=name, kind=kind, parts=_place_parts(parts, rot, x, z), room=room, light_at=light_at))
        if chairs:
            cw, cd = float(rng.uniform(0.42, 0.48)), float(rng.uniform(0.44, 0.5))
            for cx, side in chairs:
                # A chair's local back (+z) points away from the table; it slides 3 cm under the table top.
                local = build_chair(rng, cw, cd)
                cz = side * (d / 2 + cd / 2 - 0.03)
                flip = 0 if side > 0 else 2
                chair_parts = _place_parts(_place_parts(local, flip, cx, cz), rot, x, z)
                self.placed.append(Placed(name=self._name(FurnitureKind.CHAIR), kind=FurnitureKind.CHAIR,
                                          parts=chair_parts, room=room))
        self.occ = occ
        self.height[i0 : i0 + hz, j0 : j0 + wx] = np.maximum(self.height[i0 : i0 + hz, j0 : j0 + wx], top)

    def furnish(self, rng: np.random.Generator) -> None:
        """Furnish every room with a random room type's furniture, then hang pictures and ceiling lights."""
        for room in range(self.plan.n_rooms):
            kinds = _ROOM_TYPES[int(rng.integers(len(_ROOM_TYPES)))]
            n = int(rng.integers(self.p.per_room[0], self.p.per_room[1] + 1))
            for k in range(n):
                self.try_place(rng, kinds[k % len(kinds)], room)
            self._ceiling_lights(rng, room)
        self._pictures(rng)

    def _ceiling_lights(self, rng: np.random.Generator, room: int) -> None:
        c = self.plan.cell
        cells = np.argwhere((self.plan.label == room) & ~self.plan.door)
        dist = ndimage.distance_transform_edt((self.plan.label == room) & ~self.occ)
        # One light at the most interior cell, a second one far from it in big rooms.
        spots = [cells[int(np.argmax(dist[tuple(cells.T)]))]]
        area = len(cells) * c * c
        if area > 14.0:
            far = np.linalg.norm(cells - spots[0], axis=1) * (dist[tuple(cells.T)] * c > 1.0)
            spots.append(cells[int(np.argmax(far))])
        h = self.plan.ceiling
        for i, j in spots:
            x, z = self.plan.cell_centers(np.array([[i, j]]))[0]
            size = float(rng.uniform(0.3, 0.5))
            part = _box(Role.LIGHT, size, h - 0.04, h, size, x, z)
            self.placed.append(Placed(name=self._name(FurnitureKind.CEILING_LIGHT), kind=FurnitureKind.CEILING_LIGHT,
                                      parts=[part], room=room, light_at=(float(x), -(h - 0.25), float(z))))

    def _pictures(self, rng: np.random.Generator) -> None:
        """Hang framed pictures on full-height straight walls, above any furniture standing in front of them."""
        from panoworld.tools.synth.layout import architecture_quads

        walls = architecture_quads(self.plan)["walls"]
        c = self.plan.cell
        full = np.isclose(-walls.corners[:, :, 1].min(1), self.plan.ceiling) & np.isclose(walls.corners[:, :, 1].max(1), 0)
        hung: list[tuple[int, float, float]] = []
        for room in range(self.plan.n_rooms):
            idx = np.flatnonzero(full & (walls.owner == room))
            n = int(rng.integers(self.p.pictures_per_room[0], self.p.pictures_per_room[1] + 1))
            for _ in range(4 * n):
                if n == 0 or len(idx) == 0:
                    break
                q = int(idx[rng.integers(len(idx))])
                corners, normal = walls.corners[q], walls.normal[q]
                along = 0 if abs(normal[2]) > 0.5 else 2
                u0, u1 = corners[:, along].min(), corners[:, along].max()
                pw, ph = float(rng.uniform(0.4, 1.2)), float(rng.uniform(0.3, 0.9))
                if u1 - u0 < pw + 0.4:
                    continue
                uc = float(rng.uniform(u0 + pw / 2 + 0.2, u1 - pw / 2 - 0.2))
                hc = float(rng.uniform(1.35, 1.75))
                h0, h1 = hc - ph / 2, hc + ph / 2
                if h0 < 0.9 or h1 > self.plan.ceiling - 0.15:
                    continue
                plane = float(corners[0, 2 - along])
                key = q
                if any(k == key and abs(a - uc) < (b + pw) / 2 + 0.1 for k, a, b in hung):
                    continue
                # Furniture height in the strip of cells in front of the picture must stay below its bottom edge.
                sample_u = np.linspace(uc - pw / 2, uc + pw / 2, 9)
                front = plane + np.sign(normal[2 - along]) * c
                pts = np.stack([sample_u, np.full(9, front)], 1) if along == 0 else np.stack([np.full(9, front), sample_u], 1)
                ij = np.round(self.plan.to_grid(pts)).astype(int)
                if (self.height[ij[:, 0], ij[:, 1]] > h0 - 0.05).any():
                    continue
                hung.append((key, uc, pw))
                frame_t, pic_t, border = 0.02, 0.025, float(rng.uniform(0.02, 0.05))
                sgn = float(np.sign(normal[2 - along]))
                parts = [
                    _box(Role.WOOD, pw + 2 * border, h0 - border, h1 + border, frame_t, 0, -frame_t / 2),
                    _box(Role.PICTURE, pw, h0, h1, pic_t, 0, -pic_t / 2),
                ]
                # Local back +z goes into the wall: rotate so local -z points along the wall normal.
                rot = {(2, 1.0): 2, (2, -1.0): 0, (0, 1.0): 3, (0, -1.0): 1}[(2 - along, sgn)]
                x, z = (uc, plane) if along == 0 else (plane, uc)
                self.placed.append(Placed(name=self._name(FurnitureKind.PICTURE), kind=FurnitureKind.PICTURE,
                                          parts=_place_parts(parts, rot, x, z), room=room))
                n -= 1


class PlacementError(PanoWorldError, RuntimeError):
    """Furniture placement cannot keep walkable floor (the caller retries with another seed)."""
