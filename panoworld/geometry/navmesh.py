"""The NavMesh: triangulated walkable floor with geometry queries, A* + funnel path finding and file I/O."""

from __future__ import annotations

import heapq
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from panoworld.core.conventions import GLTF_FROM_WORLD, transform_points
from panoworld.core.errors import NoFloorError
from panoworld.core.shapes import check_shape
from panoworld.geometry.polygons import (
    cross_section,
    even_odd,
    pick_components,
    ring_area,
    ring_segments,
    segment_distance,
    triangulate_rings,
)

HOME_SNAP_M = 1.0
"""A home's capture point on no floor piece (its floor eroded, or unseen under the rig) belongs to the nearest piece
within this distance; farther, to none (a piece that far is another room's, behind a wall)."""
NAVMESH_JSON = "navmesh.json"
RUN_ONLY_INFO = ("timings_s",)
"""Build facts that differ from run to run: reported in the stage manifest, never in navmesh.json (deterministic)."""
NAVMESH_OBJ = "navmesh.obj"
NAVMESH_GLB = "navmesh.glb"
FORMAT_VERSION = 1


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


@dataclass
class NavMesh:
    """Triangulated walkable floor in world x,z at height floor_y (the agent's centre may be anywhere inside)."""

    vertices: np.ndarray
    """(V, 2) float64 x,z."""
    triangles: np.ndarray
    """(T, 3) int32, counter-clockwise in (x, z)."""
    adjacency: np.ndarray
    """(T, 3) int32: triangle across the edge opposite vertex k, -1 on the boundary."""
    rings: list[np.ndarray]
    """Boundary rings (K, 2): counter-clockwise outer rings and clockwise holes."""
    floor_y: float
    """Floor height in the world frame (up = -Y, so the camera height is floor_y - camera y)."""
    agent: dict = field(default_factory=dict)
    """agent_radius_m, agent_height_m, step_height_m, band_top_m used to build it."""
    info: dict = field(default_factory=dict)
    """Build facts (cell size, camera on NavMesh, timings...)."""
    grid: Any = field(default=None, repr=False)
    """The heightfield (panoworld.navmesh.FloorGrid) it was built from (only after build_navmesh, not stored on disk)."""

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, np.float64)
        self.triangles = np.asarray(self.triangles, np.int32)
        self.adjacency = np.asarray(self.adjacency, np.int32)
        self.rings = [np.asarray(r, np.float64) for r in self.rings]
        self._segs = ring_segments(self.rings)
        tri = self.vertices[self.triangles]
        self._tri = tri
        self._centroids = tri.mean(axis=1)
        self._tri_area = 0.5 * _cross(tri[:, 0], tri[:, 1], tri[:, 2])
        self._labels: np.ndarray | None = None

    # -- geometry queries

    @property
    def area(self) -> float:
        return float(self._tri_area.sum())

    @property
    def segments(self) -> np.ndarray:
        """Boundary edges (S, 2, 2)."""
        return self._segs

    def polygons(self) -> list[dict]:
        """Outer rings with the holes inside them: [{"outer": (K, 2), "holes": [(K, 2), ...]}]."""
        outers = [r for r in self.rings if ring_area(r) > 0]
        holes = [r for r in self.rings if ring_area(r) <= 0]
        out = [{"outer": o, "holes": []} for o in outers]
        for h in holes:
            for k, o in enumerate(outers):
                if even_odd(h[:1], ring_segments([o]))[0]:
                    out[k]["holes"].append(h)
                    break
        return out

    def contains(self, xz: np.ndarray) -> np.ndarray:
        """Points (N, 2) x,z -> (N,) bool, inside the walkable area (even-odd rule on the boundary rings)."""
        return even_odd(_check_xz(xz), self._segs)

    def clearance(self, xz: np.ndarray) -> np.ndarray:
        """Signed distance (N,) of points (N, 2) to the NavMesh boundary: positive inside, negative outside."""
        xz = _check_xz(xz)
        d = segment_distance(xz, self._segs)
        return np.where(self.contains(xz), d, -d)

    def locate(self, xz: np.ndarray, eps: float = 1e-9, chunk: int = 1024) -> np.ndarray:
        """Index (N,) of the triangle containing each point (N, 2), -1 outside."""
        xz = _check_xz(xz)
        out = np.full(len(xz), -1, np.int64)
        a, b, c = self._tri[:, 0], self._tri[:, 1], self._tri[:, 2]
        for s in range(0, len(xz), chunk):
            p = xz[s : s + chunk, None, :]
            inside = (_cross(a, b, p) >= -eps) & (_cross(b, c, p) >= -eps) & (_cross(c, a, p) >= -eps)
            hit = inside.any(axis=1)
            out[s : s + chunk] = np.where(hit, inside.argmax(axis=1), -1)
        return out

    def closest_point(self, xz: np.ndarray) -> np.ndarray:
        """Nearest point (N, 2) on the NavMesh (the point itself when inside), nudged 1 mm inside."""
        xz = _check_xz(xz)
        out = xz.copy()
        outside = ~self.contains(xz)
        if outside.any():
            a, ab = self._segs[:, 0], self._segs[:, 1] - self._segs[:, 0]
            p = xz[outside][:, None, :]
            t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab**2).sum(1), 1e-30), 0, 1)
            q = a + t[..., None] * ab
            k = ((q - p) ** 2).sum(-1).argmin(axis=1)
            q = q[np.arange(len(k)), k]
            tri = self.locate(q, eps=1e-7)
            tri = np.where(tri >= 0, tri, 0)
            out[outside] = q + 1e-3 * _unit(self._centroids[tri] - q)
        return out

    def blocked(self, a: np.ndarray, b: np.ndarray, chunk: int = 512) -> np.ndarray:
        """Whether each segment a[k] -> b[k] (N, 2) leaves the NavMesh -> (N,) bool.

        Blocked when the boundary meets the segment anywhere but at its end points (crossing or touching a
        boundary vertex) or its midpoint lies outside; ends may lie on the boundary, and segments may run along it.
        """
        a, b = _check_xz(a), _check_xz(b)
        out = np.zeros(len(a), bool)
        s0, s1 = self._segs[None, :, 0], self._segs[None, :, 1]
        for s in range(0, len(a), chunk):
            p, q = a[s : s + chunk, None], b[s : s + chunk, None]
            d1, d2 = _cross(p, q, s0), _cross(p, q, s1)
            d3, d4 = _cross(s0, s1, p), _cross(s0, s1, q)
            out[s : s + chunk] = ((d1 * d2 <= 0) & (d3 * d4 < 0)).any(axis=1)
        mid = 0.5 * (a[~out] + b[~out])
        out[~out] = self.clearance(mid) < -1e-9  # on the boundary counts as inside
        return out

    def segment_inside(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Whether each segment a[k] -> b[k] (N, 2) lies inside the NavMesh (ends inside, never leaving it)."""
        a, b = _check_xz(a), _check_xz(b)
        return self.contains(a) & self.contains(b) & ~self.blocked(a, b)

    def polyline_inside(self, pts: np.ndarray) -> np.ndarray:
        """(K - 1,) bool per segment of a polyline (K, 2)."""
        pts = _check_xz(pts)
        return self.segment_inside(pts[:-1], pts[1:])

    def ray_reach(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance (M,) from an inside point along unit directions (M, 2) to the first boundary crossing."""
        o = np.asarray(origin, np.float64).reshape(2)
        d = np.asarray(dirs, np.float64).reshape(-1, 2)
        a, e = self._segs[:, 0], self._segs[:, 1] - self._segs[:, 0]
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
        w = a[None] - o
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / denom
            u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / denom
        hit = (np.abs(denom) > 1e-15) & (t >= 0) & (u >= 0) & (u <= 1)
        return np.where(hit, t, np.inf).min(axis=1)

    def sample_points(self, n: int, rng: np.random.Generator | int | None = None, min_clearance: float = 0.0) -> np.ndarray:
        """n points (n, 2) uniformly over the area, optionally at least min_clearance from the boundary."""
        rng = np.random.default_rng(rng)
        out = np.zeros((0, 2))
        p = self._tri_area / self._tri_area.sum()
        for _ in range(50):
            m = max(2 * (n - len(out)), 16)
            t = rng.choice(len(p), size=m, p=p)
            r1, r2 = np.sqrt(rng.random(m)), rng.random(m)
            tri = self._tri[t]
            pts = (1 - r1)[:, None] * tri[:, 0] + (r1 * (1 - r2))[:, None] * tri[:, 1] + (r1 * r2)[:, None] * tri[:, 2]
            if min_clearance > 0:
                pts = pts[segment_distance(pts, self._segs) >= min_clearance]
            out = np.concatenate([out, pts])
            if len(out) >= n:
                return out[:n]
        raise ValueError(f"could not sample {n} points with clearance >= {min_clearance} m (NavMesh too narrow)")

    def components(self) -> np.ndarray:
        """Connected component (T,) of each triangle (across shared edges), numbered in order of first triangle."""
        if self._labels is None:
            from scipy.sparse import coo_matrix
            from scipy.sparse.csgraph import connected_components

            t, k = np.nonzero(self.adjacency >= 0)
            n = len(self.triangles)
            graph = coo_matrix((np.ones(len(t)), (t, self.adjacency[t, k])), shape=(n, n))
            _, labels = connected_components(graph, directed=False)
            _, first = np.unique(labels, return_index=True)
            self._labels = np.argsort(np.argsort(first))[labels]
        return self._labels

    def component_areas(self) -> np.ndarray:
        """Area (C,) of each connected component (components())."""
        labels = self.components()
        return np.bincount(labels, weights=self._tri_area, minlength=int(labels.max(initial=-1)) + 1)

    def component_of(self, xz: np.ndarray, snap_m: float = 0.0) -> np.ndarray:
        """Connected component (N,) holding each point (N, 2), or for a point outside the one nearest to it within
        snap_m, else -1 (path() joins two points only within one component)."""
        xz = _check_xz(xz)
        tri = self.locate(xz, eps=1e-7)
        comp = np.where(tri >= 0, self.components()[np.maximum(tri, 0)], -1)
        off = np.flatnonzero(comp < 0)
        if len(off) and snap_m > 0:
            near = self.closest_point(xz[off])
            tri = self.locate(near, eps=1e-7)
            ok = (tri >= 0) & (np.linalg.norm(near - xz[off], axis=1) <= snap_m)
            comp[off[ok]] = self.components()[tri[ok]]
        return comp

    def offset(self, delta_m: float, keep_xz: np.ndarray | None = None) -> NavMesh:
        """A new NavMesh grown (delta > 0) or shrunk (delta < 0) exactly (manifold3d offset, round joins).

        Shrinking can split it; keep_xz (2,) or (K, 2) keeps only the pieces containing (or nearest to) those points.
        """
        from manifold3d import JoinType

        cs = cross_section(self.rings).offset(delta_m, JoinType.Round, circular_segments=16)
        if cs.is_empty() or cs.area() <= 0:
            raise NoFloorError(f"nothing is left of the NavMesh after offsetting by {delta_m} m")
        if keep_xz is None:
            rings = [np.asarray(r, np.float64) for r in cs.to_polygons()]
        else:
            rings = pick_components(cs, np.asarray(keep_xz, np.float64).reshape(-1, 2))[0]
        v, t, adj = triangulate_rings(rings, self.info.get("max_triangle_area_m2", 0.25))
        return NavMesh(v, t, adj, rings, self.floor_y, dict(self.agent), {**self.info, "offset_m": delta_m})

    # -- path finding

    def path(self, a_xz: np.ndarray, b_xz: np.ndarray) -> np.ndarray:
        """Shortest path (K, 2) from a to b inside the NavMesh: A* over triangle adjacency + funnel string pulling.

        Raises ValueError when an end point lies outside or the two are not connected.
        """
        a = np.asarray(a_xz, np.float64).reshape(2)
        b = np.asarray(b_xz, np.float64).reshape(2)
        ta, tb = self.locate(np.stack([a, b]))
        if ta < 0 or tb < 0:
            bad = "start" if ta < 0 else "goal"
            raise ValueError(f"path {bad} {(a if ta < 0 else b).round(3).tolist()} lies outside the NavMesh")
        corridor = self._astar(int(ta), int(tb), b)
        if corridor is None:
            raise ValueError(f"no path on the NavMesh from {a.round(3).tolist()} to {b.round(3).tolist()}")
        return self._shortcut(self._funnel(corridor, a, b))

    def _shortcut(self, pts: np.ndarray) -> np.ndarray:
        """Drop polyline vertices while the direct segment stays inside (A* corridors need not be the shortest)."""
        out = [0]
        while out[-1] < len(pts) - 1:
            i = out[-1]
            js = np.arange(i + 1, len(pts))
            ok = ~self.blocked(np.repeat(pts[i][None], len(js), 0), pts[js])
            out.append(int(js[np.flatnonzero(ok)].max()) if ok.any() else i + 1)
        return pts[out]

    def _astar(self, start: int, goal: int, goal_xz: np.ndarray) -> list[int] | None:
        c = self._centroids
        g = {start: 0.0}
        parent = {start: -1}
        heap = [(float(np.linalg.norm(c[start] - goal_xz)), start)]
        closed = set()
        while heap:
            _, t = heapq.heappop(heap)
            if t == goal:
                out = [t]
                while parent[out[-1]] >= 0:
                    out.append(parent[out[-1]])
                return out[::-1]
            if t in closed:
                continue
            closed.add(t)
            for nb in self.adjacency[t]:
                nb = int(nb)
                if nb < 0 or nb in closed:
                    continue
                ng = g[t] + float(np.linalg.norm(c[nb] - c[t]))
                if ng < g.get(nb, np.inf):
                    g[nb] = ng
                    parent[nb] = t
                    heapq.heappush(heap, (ng + float(np.linalg.norm(c[nb] - goal_xz)), nb))
        return None

    def _funnel(self, corridor: list[int], a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Simple stupid funnel algorithm (Mononen) over the portals of a triangle corridor."""
        portals = [(a, a)]
        for t0, t1 in zip(corridor[:-1], corridor[1:]):
            k = int(np.flatnonzero(self.adjacency[t0] == t1)[0])
            tri = self.triangles[t0]
            right = self.vertices[tri[(k + 1) % 3]]
            left = self.vertices[tri[(k + 2) % 3]]
            portals.append((left, right))
        portals.append((b, b))

        def area2(p, q, r):  # > 0 when r is clockwise (to the right) of p -> q
            return (r[0] - p[0]) * (q[1] - p[1]) - (q[0] - p[0]) * (r[1] - p[1])

        def same(p, q):
            return float(np.sum((p - q) ** 2)) < 1e-18

        pts = [a]
        apex = left = right = a
        apex_i = left_i = right_i = 0
        i = 1
        while i < len(portals):
            pl, pr = portals[i]
            if area2(apex, right, pr) <= 0.0:
                if same(apex, right) or area2(apex, left, pr) > 0.0:
                    right, right_i = pr, i
                else:
                    pts.append(left)
                    apex, apex_i = left, left_i
                    left = right = apex
                    left_i = right_i = apex_i
                    i = apex_i + 1
                    continue
            if area2(apex, left, pl) >= 0.0:
                if same(apex, left) or area2(apex, right, pl) < 0.0:
                    left, left_i = pl, i
                else:
                    pts.append(right)
                    apex, apex_i = right, right_i
                    left = right = apex
                    left_i = right_i = apex_i
                    i = apex_i + 1
                    continue
            i += 1
        if not same(pts[-1], b):
            pts.append(b)
        out = np.asarray(pts)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(out, axis=0), axis=1) > 1e-12])
        return out[keep]

    # -- I/O

    def to_json(self) -> dict:
        return {
            "format_version": FORMAT_VERSION,
            "frame": "canonical (camera of view 0 at the origin; x right, y down, z forward; up = -Y)",
            "floor_y": self.floor_y,
            "agent": self.agent,
            "cell_m": self.info.get("cell_m"),
            "area_m2": self.area,
            "polygons": [
                {"outer": p["outer"].tolist(), "holes": [h.tolist() for h in p["holes"]]} for p in self.polygons()
            ],
            "vertices": self.vertices.tolist(),
            "triangles": self.triangles.tolist(),
            "adjacency": self.adjacency.tolist(),
            "info": {k: v for k, v in self.info.items() if k not in RUN_ONLY_INFO},
        }

    def mesh3d(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (V, 3) at y = floor_y, faces (T, 3)) in the world frame, normals up (-Y)."""
        v = np.stack([self.vertices[:, 0], np.full(len(self.vertices), self.floor_y), self.vertices[:, 1]], 1)
        return v, self.triangles.copy()

    def save(self, out_dir: Path, glb: bool = True) -> list[str]:
        """Write navmesh.json, navmesh.obj (world frame) and navmesh.glb (glTF, Y up); returns the file names."""
        import trimesh

        out_dir = Path(out_dir)
        (out_dir / NAVMESH_JSON).write_text(json.dumps(self.to_json()))
        v, f = self.mesh3d()
        lines = ["# PanoWorld NavMesh: walkable floor, world frame (y down, up = -Y), metres"]
        lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
        (out_dir / NAVMESH_OBJ).write_text("\n".join(lines) + "\n")
        names = [NAVMESH_JSON, NAVMESH_OBJ]
        if glb:
            m = trimesh.Trimesh(transform_points(GLTF_FROM_WORLD, v), f, process=False)
            m.visual.face_colors = np.array([60, 200, 90, 160], np.uint8)
            (out_dir / NAVMESH_GLB).write_bytes(m.export(file_type="glb"))
            names.append(NAVMESH_GLB)
        return names


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-30)


def _check_xz(xz: np.ndarray) -> np.ndarray:
    xz = np.asarray(xz, np.float64)
    if xz.ndim == 1 and xz.shape == (2,):
        xz = xz[None]
    check_shape("xz", xz, "N 2")
    return xz


def load_navmesh(path: Path | str) -> NavMesh:
    """Read a NavMesh from a navmesh artifact directory or a navmesh.json file."""
    path = Path(path)
    if path.is_dir():
        path = path / NAVMESH_JSON
    try:
        d = json.loads(path.read_text())
        rings = []
        for p in d["polygons"]:
            rings.append(np.asarray(p["outer"], np.float64))
            rings.extend(np.asarray(h, np.float64) for h in p["holes"])
        return NavMesh(
            np.asarray(d["vertices"], np.float64).reshape(-1, 2),
            np.asarray(d["triangles"], np.int32).reshape(-1, 3),
            np.asarray(d["adjacency"], np.int32).reshape(-1, 3),
            rings,
            float(d["floor_y"]),
            dict(d.get("agent", {})),
            dict(d.get("info", {})),
        )
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a readable NavMesh ({type(e).__name__}: {e})") from None

