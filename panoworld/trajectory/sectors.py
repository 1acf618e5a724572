"""Sector exploration paths: out-and-back petals from the start into each directional sector around the camera."""

from __future__ import annotations

import numpy as np

from panoworld.geometry.navmesh import NavMesh
from panoworld.trajectory.common import Plan, TrajectoryParams, approach_path, planning_hub, planning_mesh
from panoworld.trajectory.polyline import polyline_length, resample_polyline, smooth_polyline, truncate_polyline

MIN_SECTOR_DIST_M = 0.1
"""A pose counts for a sector only at least this far from the camera (nearer, every sector is a few centimetres away)."""


def sector_of(xz: np.ndarray, start: np.ndarray, n_sectors: int) -> np.ndarray:
    """Sector index (N,) of points around start: sector k is centred on lon = k * 2 pi / n (lon 0 = +z, +x at pi/2)."""
    d = np.asarray(xz, np.float64).reshape(-1, 2) - start
    lon = np.arctan2(d[:, 0], d[:, 1])
    return np.mod(np.round(lon / (2 * np.pi / n_sectors)), n_sectors).astype(int)


def sector_coverage(xz: np.ndarray, start: np.ndarray, n_sectors: int = 8, min_dist: float = 0.1) -> np.ndarray:
    """(n_sectors,) bool: whether some point lies in the sector at least min_dist from start."""
    xz = np.asarray(xz, np.float64).reshape(-1, 2)
    far = np.linalg.norm(xz - start, axis=1) >= min_dist
    out = np.zeros(n_sectors, bool)
    out[np.unique(sector_of(xz[far], start, n_sectors))] = True
    return out


def sector_reach(nav: NavMesh, start: np.ndarray, n_sectors: int, seed: int = 0, n_candidates: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Farthest NavMesh point of each sector from start: (targets (n, 2), distances (n,), 0 where empty).

    Points within the central half of a sector win over the rest of it, so petals spread evenly.
    """
    cand = np.concatenate([nav.sample_points(n_candidates, seed), nav.vertices])
    cand = cand[nav.contains(cand)]
    d = cand - start
    dist = np.linalg.norm(d, axis=1)
    width = 2 * np.pi / n_sectors
    lon = np.arctan2(d[:, 0], d[:, 1])
    sec = np.mod(np.round(lon / width), n_sectors).astype(int)
    off_centre = np.abs(np.angle(np.exp(1j * (lon - sec * width))))
    score = dist * np.where(off_centre <= 0.25 * width, 1.0, 0.5)
    targets = np.tile(start, (n_sectors, 1))
    reach = np.zeros(n_sectors)
    for k in range(n_sectors):
        m = np.flatnonzero(sec == k)
        if len(m):
            j = m[np.argmax(score[m])]
            targets[k], reach[k] = cand[j], dist[j]
    return targets, reach


def _water_fill(caps: np.ndarray, total: int) -> np.ndarray:
    """Integers m_k <= caps_k with sum(m) = min(total, sum(caps)), as equal as possible (largest caps last)."""
    m = np.zeros(len(caps), int)
    left = min(int(total), int(caps.sum()))
    while left > 0:
        open_ = np.flatnonzero(m < caps)
        give = max(left // len(open_), 1)
        for k in open_[np.argsort(caps[open_])]:
            g = min(give, caps[k] - m[k], left)
            m[k] += g
            left -= g
            if left == 0:
                break
    return m


class GeodesicField:
    """Shortest walking distances on a NavMesh from one point, on a raster of cell centres inside it.

    xz (M, 2) cell centres inside the NavMesh, dist (M,) their 8-connected grid geodesic distance from the source
    (inf where not connected); the grid overestimates continuous distances by at most ~8 %.
    """

    def __init__(self, nav: NavMesh, source: np.ndarray, cell: float = 0.05, max_cells: int = 250_000):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        lo, hi = nav.vertices.min(axis=0), nav.vertices.max(axis=0)
        cell = max(cell, float(np.sqrt(np.prod(hi - lo + 1e-9) / max_cells)))
        nx, nz = (np.floor((hi - lo) / cell).astype(int) + 1).tolist()
        gx, gz = np.meshgrid(lo[0] + (np.arange(nx) + 0.5) * cell, lo[1] + (np.arange(nz) + 0.5) * cell)
        centres = np.stack([gx.ravel(), gz.ravel()], 1)
        inside = nav.contains(centres).reshape(nz, nx)
        idx = np.full((nz, nx), -1, np.int64)
        idx[inside] = np.arange(int(inside.sum()))
        rows, cols, w = [], [], []
        for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a = idx[: nz - di, max(0, -dj): nx - max(0, dj)]  # cell (i, j) and its neighbour (i + di, j + dj)
            b = idx[di:, max(0, dj): nx - max(0, -dj)]
            both = (a >= 0) & (b >= 0)
            rows.append(a[both])
            cols.append(b[both])
            w.append(np.full(int(both.sum()), cell * np.hypot(di, dj)))
        n = int(inside.sum())
        self.xz = centres[inside.ravel()]
        self.cell = cell
        if n == 0:
            self.dist = np.zeros(0)
            return
        graph = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
        src = int(np.argmin(np.linalg.norm(self.xz - np.asarray(source, np.float64).reshape(2), axis=1)))
        self.dist = dijkstra(graph, directed=False, indices=src) + float(np.linalg.norm(self.xz[src] - source))


def sector_reachability(
    nav: NavMesh, start: np.ndarray, hub: np.ndarray, n_sectors: int, budget_m: float, *, min_dist: float = MIN_SECTOR_DIST_M,
    field: GeodesicField | None = None,
) -> dict:
    """Which sectors around the camera (start) an out-and-back leg from hub can enter within budget_m.

    A sector is reachable when the NavMesh has floor in it at least min_dist from start whose walking distance g
    from the hub satisfies |start - hub| + 2 g <= budget_m. Returns {"reachable" (n,) bool, "entry_m" (n,) the
    least such g (inf if none), "deepest_m" (n,) the largest g within the budget, "field"}.
    """
    field = field or GeodesicField(nav, hub)
    off = float(np.linalg.norm(np.asarray(hub) - np.asarray(start)))
    r = np.linalg.norm(field.xz - start, axis=1)
    sec = sector_of(field.xz, start, n_sectors)
    ok = (r >= min_dist) & np.isfinite(field.dist) & (off + 2 * field.dist <= budget_m + 1e-9)
    entry = np.full(n_sectors, np.inf)
    deepest = np.zeros(n_sectors)
    np.minimum.at(entry, sec[ok], field.dist[ok])
    np.maximum.at(deepest, sec[ok], field.dist[ok])
    return {"reachable": np.isfinite(entry), "entry_m": entry, "deepest_m": deepest, "field": field}


def _allocate(caps: np.ndarray, mins: np.ndarray, total: int) -> np.ndarray:
    """Integer steps m_k <= caps_k: first each sector's minimum (cheapest sectors first while the total allows),
    then the rest of total to the shortest shares first (equal totals where caps allow) among the sectors that
    got their minimum (a share below it would not reach into its sector)."""
    m = np.zeros(len(caps), int)
    left = min(int(total), int(caps.sum()))
    for k in np.argsort(mins, kind="stable"):
        need = int(min(mins[k], caps[k]))
        if 0 < need <= left:
            m[k] = need
            left -= need
    open_ = (m > 0) & (m < caps)
    while left > 0 and open_.any():  # one step at a time to the shortest open share: equal totals
        k = int(np.flatnonzero(open_)[np.argmin(m[open_])])
        m[k] += 1
        left -= 1
        open_[k] = m[k] < caps[k]
    return m


def plan_sector(nav: NavMesh, start: np.ndarray, params: TrajectoryParams) -> Plan:
    """Sector exploration: from the start, out and back into each sector around the camera in turn.

    Sectors are params.sectors equal angles centred on the camera (sector 0 straight ahead, +z). The approach
    to the NavMesh (when the camera stands off it) comes first; the remaining step budget goes first to entering
    every reachable sector (sector_reachability, cheapest first), then is shared as equally as each sector's
    depth allows. Each leg is the smoothed NavMesh shortest path (A* + funnel) from the hub to the sector point
    farthest from the camera that its share reaches (points within the central half of a sector count double;
    farther targets when the shares cannot be spent), truncated to a whole number of steps so the tip and the
    return fall on poses. When even full legs cannot fill the budget, the step shrinks (info["step_adapted"]).
    """
    start = np.asarray(start, np.float64).reshape(2)
    n_steps = params.frames - 1
    step = params.step_m * params.stride
    plan_nav = planning_mesh(nav, start, params.plan_margin_m)
    hub, off = planning_hub(plan_nav, start)
    approach = approach_path(start, hub, step, n_steps)
    budget = n_steps - (len(approach) - 1)
    want = budget + (budget % 2)  # whole out-and-back legs; an odd budget drops the very last pose
    total_legs = want // 2
    reach = sector_reachability(plan_nav, start, hub, params.sectors, n_steps * step)
    field, ok = reach["field"], reach["reachable"]
    if not ok.any() or total_legs <= 0:
        raise ValueError(
            f"no sector around the camera is reachable with {params.frames} poses of {step:.3f} m: the walkable area is "
            f"too small ({nav.area:.2f} m^2) or too far ({off:.2f} m); reduce step_m/stride or the agent radius"
        )
    # Shares of the budget on the grid geodesics, then legs towards the best point each share reaches.
    sec = sector_of(field.xz, start, params.sectors)
    r = np.linalg.norm(field.xz - start, axis=1)
    width = 2 * np.pi / params.sectors
    lon = np.arctan2(field.xz[:, 0] - start[0], field.xz[:, 1] - start[1])
    central = np.abs(np.angle(np.exp(1j * (lon - sec * width)))) <= 0.25 * width
    score = r * np.where(central, 1.0, 0.5)
    usable = (r >= MIN_SECTOR_DIST_M) & np.isfinite(field.dist)
    mins = np.where(ok, np.ceil(np.where(ok, reach["entry_m"], 0) / step + 0.5), 0).astype(int)
    caps = np.where(ok, np.floor(reach["deepest_m"] / step), 0).astype(int)
    share = _allocate(caps, np.maximum(mins, 1), total_legs)
    for reach_factor in (1.1, 1.6, 2.5, np.inf):  # longer legs until their whole steps can hold the budget
        legs, lengths, sectors, entry_steps = [], [], [], []
        for k in np.flatnonzero(share > 0):
            cand = np.flatnonzero(usable & (sec == k) & (field.dist <= reach_factor * share[k] * step + step))
            if len(cand) == 0:
                continue
            target = field.xz[cand[np.argmax(score[cand])]]
            leg = smooth_polyline(plan_nav, plan_nav.path(hub, target), closed=False, iterations=params.smooth_iterations)
            if polyline_length(leg) < step:
                continue
            legs.append(leg)
            lengths.append(polyline_length(leg))
            sectors.append(int(k))
            entry_steps.append(int(min(mins[k], share[k])))
        if sum(int(x / step + 1e-9) for x in lengths) >= total_legs:
            break
    if not legs:
        raise ValueError(
            f"no sector reaches {step:.3f} m (one step) from the start: the walkable area is too small "
            f"({nav.area:.2f} m^2); reduce step_m/stride or the agent radius"
        )
    lengths = np.asarray(lengths)

    def steps_at(s):
        return np.floor(lengths / s + 1e-9).astype(int)

    s_used = step
    if steps_at(step).sum() < total_legs:
        lo, hi = 1e-4, step  # largest s with enough whole steps
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if steps_at(mid).sum() >= total_legs else (lo, mid)
        s_used = lo
    m = _allocate(steps_at(s_used), np.asarray(entry_steps), total_legs)
    pts = [approach]
    for leg, mk in zip(legs, m):
        if mk == 0:
            continue
        out = resample_polyline(truncate_polyline(leg, mk * s_used), mk + 1)
        pts += [out[1:], out[::-1][1:]]
    positions = np.concatenate(pts)[: params.frames]
    positions[0] = start
    covered = sector_coverage(positions, start, params.sectors, MIN_SECTOR_DIST_M)
    return Plan(
        positions,
        s_used,
        {
            "sectors_visited": [k for k, mk in zip(sectors, m) if mk > 0],
            "sectors_reachable": int(ok.sum()),
            "sectors_covered": int(covered.sum()),
            "sector_entry_m": [round(float(x), 4) if np.isfinite(x) else None for x in reach["entry_m"]],
            "sector_depth_m": reach["deepest_m"].round(4).tolist(),
            "leg_steps": [int(x) for x in m],
            "step_adapted": bool(s_used < step * (1 - 1e-6)),
            "start_off_navmesh_m": off,
            "approach_steps": len(approach) - 1,
            "hub": hub.tolist(),
        },
    )
