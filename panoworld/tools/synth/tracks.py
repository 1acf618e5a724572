"""Smooth upright camera tracks through the free space of a furnished floor plan, with exact 3D clearance checks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import interpolate, ndimage, sparse
from scipy.sparse import csgraph

from panoworld.core.errors import PanoWorldError
from panoworld.core.shapes import check_shape
from panoworld.tools.synth.layout import SOLID, FloorPlan
from panoworld.tools.synth.params import TrackParams


class TrackError(PanoWorldError, RuntimeError):
    """No track satisfying the clearance, smoothness and length constraints was found."""


@dataclass(kw_only=True)
class Track:
    """A dense camera track: upright cameras (yaw only) at constant height following the path direction."""

    world_from_cam: np.ndarray
    """(N, 4, 4) float64 poses, OpenCV camera axes."""
    camera_height: float
    """Camera height above the floor in metres (constant over the track)."""


def distance_to_mesh(points: np.ndarray, triangles: np.ndarray, radius: float) -> np.ndarray:
    """Exact distance (N,) from points (N, 3) to the nearest of triangles (F, 3, 3), capped at radius."""
    check_shape("points", points, "N 3")
    check_shape("triangles", triangles, "F 3 3")
    lo, hi = triangles.min(1), triangles.max(1)
    out = np.full(len(points), float(radius))
    for k, p in enumerate(points):
        # Distance to each triangle's bounding box is a lower bound on the distance to the triangle.
        box = np.linalg.norm(np.maximum(0.0, np.maximum(lo - p, p - hi)), axis=1)
        cand = np.flatnonzero(box < radius)
        if len(cand):
            closest = trimesh.triangles.closest_point(triangles[cand], np.repeat(p[None], len(cand), 0))
            out[k] = min(radius, float(np.linalg.norm(closest - p, axis=1).min()))
    return out


def pose_from_xz_heading(xz: np.ndarray, heading: np.ndarray, camera_height: float) -> np.ndarray:
    """Upright poses (N, 4, 4): camera at (x, -height, z) looking along the horizontal unit heading (N, 2) = (x, z)."""
    n = len(xz)
    fx, fz = heading[:, 0], heading[:, 1]
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 0] = np.stack([fz, np.zeros(n), -fx], 1)
    T[:, :3, 1] = [0.0, 1.0, 0.0]
    T[:, :3, 2] = np.stack([fx, np.zeros(n), fz], 1)
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = xz[:, 0], -camera_height, xz[:, 1]
    return T


class TrackPlanner:
    """Shortest paths between random waypoints on the walkable grid, smoothed by a spline and resampled by arc length."""

    def __init__(self, plan: FloorPlan, occ: np.ndarray, triangles: np.ndarray, p: TrackParams, margin: float):
        self.plan, self.p = plan, p
        self.triangles = triangles
        c = plan.cell
        free = (plan.label != SOLID) & ~occ
        self.dist = ndimage.distance_transform_edt(free) * c - c / 2
        walk = self.dist >= p.clearance_m + margin
        comp, n = ndimage.label(walk, structure=np.ones((3, 3)))
        if n == 0:
            raise TrackError("no walkable floor for camera tracks")
        sizes = np.bincount(comp.ravel())
        sizes[0] = 0
        self.walk = comp == int(np.argmax(sizes))
        self.cells = np.argwhere(self.walk)
        index = np.full(walk.shape, -1, np.int64)
        index[tuple(self.cells.T)] = np.arange(len(self.cells))
        self.index = index
        rows, cols, wts = [], [], []
        # Edge weights favour the middle of the free space (cost grows within 1 m of obstacles).
        cost = 1.0 + 3.0 * np.clip(1.0 - self.dist / 1.0, 0.0, None)
        for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a = self.cells
            b = a + [di, dj]
            inside = (b[:, 0] >= 0) & (b[:, 0] < walk.shape[0]) & (b[:, 1] >= 0) & (b[:, 1] < walk.shape[1])
            a, b = a[inside], b[inside]
            ib = index[tuple(b.T)]
            ok = ib >= 0
            a, b, ib = a[ok], b[ok], ib[ok]
            length = np.hypot(di, dj) * c
            rows.append(index[tuple(a.T)])
            cols.append(ib)
            wts.append(length * 0.5 * (cost[tuple(a.T)] + cost[tuple(b.T)]))
        n_cells = len(self.cells)
        self.graph = sparse.csr_matrix(
            (np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n_cells, n_cells)
        )

    def _grid_path(self, src: int, dst: int) -> np.ndarray:
        _, pred = csgraph.dijkstra(self.graph, directed=False, indices=src, return_predecessors=True)
        path = [dst]
        while path[-1] != src:
            path.append(int(pred[path[-1]]))
            if path[-1] < 0:
                raise TrackError("waypoints are not connected")
        return np.array(path[::-1])

    def _polyline(self, rng: np.random.Generator, length: float, long_track: bool = False) -> np.ndarray:
        """World (x, z) polyline (M, 2) through random waypoints with at least the given length."""
        c = self.plan.cell
        weight = np.clip(self.dist[tuple(self.cells.T)], 0, None) ** 4
        cur = int(rng.choice(len(self.cells), p=weight / weight.sum()))
        pts = [self.plan.cell_centers(self.cells[cur : cur + 1])]
        total, heading = 0.0, None
        # 12 waypoints suffice up to ~8 m; long tracks (e.g. 81-frame clips at stride 4) get more, looping the rooms
        for _ in range(max(12, 2 * int(length) + 4) if long_track else 12):
            d = (self.cells - self.cells[cur]) * c
            dn = np.linalg.norm(d, axis=1)
            ok = (dn > 1.2) & (dn < 6.0)
            if heading is not None:
                # Prefer goals that keep going forwards so the spline has no hairpin turns.
                ok &= (d[:, ::-1] @ heading) > 0.2 * dn
            cand = np.flatnonzero(ok)
            if len(cand) == 0:
                cand = np.flatnonzero(dn > 0.6)
                if len(cand) == 0:
                    break
                if long_track and heading is not None:
                    # the most forward quarter of the goals: a turn at a wall rather than a hairpin back
                    cos = (d[cand, ::-1] @ heading) / dn[cand]
                    cand = cand[cos >= np.quantile(cos, 0.75)]
            nxt = int(cand[rng.integers(len(cand))])
            seg = self.plan.cell_centers(self.cells[self._grid_path(cur, nxt)])
            pts.append(seg[1:])
            seg_len = float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
            total += seg_len
            tail = seg[-1] - seg[max(0, len(seg) - 1 - int(1.0 / c))]
            heading = tail / max(np.linalg.norm(tail), 1e-9)
            cur = nxt
            if total >= length:
                break
        return np.concatenate(pts)

    def plan_track(self, rng: np.random.Generator, frames: int) -> Track:
        """One track of `frames` poses; raises TrackError after p.max_attempts failed draws."""
        p = self.p
        c = self.plan.cell
        h_max = min(self.plan.door_height, self.plan.ceiling) - p.clearance_m - 0.05
        if h_max < p.camera_height_m[0]:
            raise TrackError(f"doorways/ceiling at {self.plan.door_height:.2f} m leave no room for a camera at "
                             f"{p.camera_height_m[0]} m with {p.clearance_m} m clearance")
        height = float(rng.uniform(p.camera_height_m[0], min(p.camera_height_m[1], h_max)))
        length = (frames - 1) * p.step_m
        max_turn = p.step_m / 0.4
        rejected = {"short": 0, "turn": 0, "clearance": 0}
        # Tracks up to 8 m first try the plain planner (unchanged outputs for every scene it could already make);
        # longer ones, and shorter ones it failed on, use the long-track mode: more waypoints that keep going
        # forwards, 30 % spare path length for the spline's cut corners, and a camera yaw that may turn slower than
        # the path at tight bends.
        modes = (True,) if length > 8.0 else (False, True)
        for long_track in (m for m in modes for _ in range(p.max_attempts)):
            if frames == 1:
                xz = self._polyline(rng, 0.0, long_track)[:1]
                a = float(rng.uniform(-np.pi, np.pi))
                heading = np.array([[np.sin(a), np.cos(a)]])
            else:
                poly = self._polyline(rng, (1.3 * length if long_track else length) + 1.0, long_track)
                seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
                arc = np.concatenate([[0.0], np.cumsum(seg)])
                if arc[-1] < length + 0.5:
                    rejected["short"] += 1
                    continue
                # Thin the grid path to ~0.3 m knots and fit a smoothing spline through them.
                s_knots = np.linspace(0.0, arc[-1], max(6, int(arc[-1] / 0.3)))
                knots = np.stack([np.interp(s_knots, arc, poly[:, k]) for k in range(2)])
                tck, _ = interpolate.splprep(knots, s=len(s_knots) * 0.06**2, k=3)
                u = np.linspace(0, 1, max(2000, int(40 * arc[-1] / p.step_m)))
                dense = np.stack(interpolate.splev(u, tck), 1)
                darc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
                if darc[-1] < length:
                    rejected["short"] += 1
                    continue
                start = float(rng.uniform(0.0, min(0.5, darc[-1] - length)))
                uu = np.interp(start + np.arange(frames) * p.step_m, darc, u)
                xz = np.stack(interpolate.splev(uu, tck), 1)
                tangent = np.stack(interpolate.splev(uu, tck, der=1), 1)
                # Yaw follows the path direction, low-passed over ~0.3 m so it turns slowly.
                raw = np.unwrap(np.arctan2(tangent[:, 0], tangent[:, 1]))
                yaw = ndimage.gaussian_filter1d(raw, sigma=0.3 / p.step_m, mode="nearest")
                for k in range(1, 7 if long_track else 1):
                    # long looping tracks: the (360-degree) camera turns more slowly than the path at tight bends
                    if np.abs(np.diff(yaw)).max(initial=0.0) <= max_turn:
                        break
                    yaw = ndimage.gaussian_filter1d(raw, sigma=0.3 * 1.5**k / p.step_m, mode="nearest")
                heading = np.stack([np.sin(yaw), np.cos(yaw)], 1)
                if np.abs(np.diff(yaw)).max(initial=0.0) > max_turn:
                    rejected["turn"] += 1
                    continue
            grid = self.plan.to_grid(xz)
            d2 = ndimage.map_coordinates(self.dist, grid.T, order=1, mode="constant", cval=-1.0)
            if (d2 < p.clearance_m + 0.5 * c).any():
                rejected["clearance"] += 1
                continue
            poses = pose_from_xz_heading(xz, heading, height)
            d3 = distance_to_mesh(poses[:, :3, 3], self.triangles, 2 * p.clearance_m)
            if (d3 < p.clearance_m).any():
                rejected["clearance"] += 1
                continue
            return Track(world_from_cam=poses, camera_height=height)
        raise TrackError(f"no track of {frames} frames x {p.step_m} m with {p.clearance_m} m clearance after "
                         f"{p.max_attempts * len(modes)} attempts (rejected: {rejected})")
