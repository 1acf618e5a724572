"""Sector exploration paths: out-and-back petals from the start into each directional sector."""

from __future__ import annotations

import numpy as np

from panoworld.navmesh import NavMesh
from panoworld.trajectory.common import Plan, TrajectoryParams, planning_hub, planning_mesh
from panoworld.trajectory.polyline import polyline_length, resample_polyline, smooth_polyline, truncate_polyline

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


def plan_sector(nav: NavMesh, start: np.ndarray, params: TrajectoryParams) -> Plan:
    """Sector exploration: from the start, out and back to the farthest reachable point of each sector in turn.

    Legs share the step budget (N - 1) equally, capped by each sector's reach; when even full legs cannot fill
    it, the step shrinks (info["step_adapted"]). A leg is the straight ray nearest the sector's centre line that
    is free for its whole length, else the smoothed NavMesh shortest path (A* + funnel) to the sector's farthest
    point. Legs are truncated to a whole number of steps so the tip and the return to the start fall on poses.
    """
    start = np.asarray(start, np.float64).reshape(2)
    n_steps = params.frames - 1
    step = params.step_m * params.stride
    plan_nav = planning_mesh(nav, start, params.plan_margin_m)
    hub, off = planning_hub(plan_nav, start)
    approach = resample_polyline(np.stack([start, hub]), max(int(np.ceil(off / step)), 1) + 1) if off > 0 else start[None]
    targets, reach = sector_reach(plan_nav, hub, params.sectors, params.seed)
    width = 2 * np.pi / params.sectors
    fan = np.array([0.0, 0.1, -0.1, 0.2, -0.2, 0.3, -0.3, 0.4, -0.4]) * width  # centre line first
    legs, rays, lengths, sectors = [], [], [], []
    for k in range(params.sectors):
        lon = k * width + fan
        dirs = np.stack([np.sin(lon), np.cos(lon)], 1)
        free = np.maximum(plan_nav.ray_reach(hub, dirs) - 1e-3, 0.0)
        leg = np.stack([hub, hub])
        if reach[k] >= step:
            leg = smooth_polyline(plan_nav, plan_nav.path(hub, targets[k]), closed=False, iterations=params.smooth_iterations)
        cap = max(free.max(), polyline_length(leg))
        if cap < step:
            continue
        legs.append(leg)
        rays.append((dirs, free))
        lengths.append(cap)
        sectors.append(k)
    budget = n_steps - (len(approach) - 1)
    if not legs or budget <= 0:
        raise ValueError(
            f"no sector reaches {step:.3f} m (one step) from the start: the walkable area is too small "
            f"({nav.area:.2f} m^2); reduce step_m/stride or the agent radius"
        )
    lengths = np.asarray(lengths)
    want = budget + (budget % 2)  # whole out-and-back legs; an odd budget drops the very last pose

    def steps_at(s):
        return np.floor(lengths / s + 1e-9).astype(int)

    s_used = step
    if 2 * steps_at(step).sum() < want:
        lo, hi = 1e-4, step  # largest s with enough whole steps
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if 2 * steps_at(mid).sum() >= want else (lo, mid)
        s_used = lo
    m = _water_fill(steps_at(s_used), want // 2)
    pts = [approach]
    for leg, (dirs, free), mk in zip(legs, rays, m):
        if mk == 0:
            continue
        d = mk * s_used
        ok = np.flatnonzero(free >= d - 1e-9)
        if len(ok):
            out = hub + np.linspace(0.0, d, mk + 1)[:, None] * dirs[ok[0]]
        else:
            out = resample_polyline(truncate_polyline(leg, d), mk + 1)
        pts += [out[1:], out[::-1][1:]]
    positions = np.concatenate(pts)[: params.frames]
    positions[0] = start
    return Plan(
        positions,
        s_used,
        {
            "sectors_visited": [int(k) for k, mk in zip(sectors, m) if mk > 0],
            "sector_reach_m": reach.round(4).tolist(),
            "leg_steps": [int(x) for x in m],
            "step_adapted": bool(s_used < step * (1 - 1e-6)),
            "start_off_navmesh_m": off,
            "hub": hub.tolist(),
        },
    )
