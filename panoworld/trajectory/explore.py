"""Exploration paths: one path per directional sector, from the camera out towards that sector's far end of the room."""

from __future__ import annotations

import numpy as np

from panoworld.geometry.navmesh import NavMesh
from panoworld.trajectory.common import Plan, TrajectoryParams, approach_path, planning_hub, planning_mesh
from panoworld.trajectory.polyline import polyline_length, resample_polyline, smooth_polyline, truncate_polyline
from panoworld.trajectory.sectors import MIN_SECTOR_DIST_M, GeodesicField, sector_coverage, sector_of

OFF_CENTRE_WEIGHT = 0.75
"""A target outside the central half of its sector must be this much farther to win: paths spread evenly, and every
tip reaches at least this fraction of its sector's extent."""


def sector_extent(field: GeodesicField, start: np.ndarray, n_sectors: int, max_walk_m: float) -> np.ndarray:
    """(n_sectors,) farthest straight-line distance from start of the NavMesh floor in each sector that is connected
    to the hub and within max_walk_m of walking (0 where a sector has no such floor): what a path can reach there."""
    ok = np.isfinite(field.dist) & (field.dist <= max_walk_m)
    r = np.linalg.norm(field.xz - start, axis=1)
    out = np.zeros(n_sectors)
    np.maximum.at(out, sector_of(field.xz[ok], start, n_sectors), r[ok])
    return out


KEEP_M = 1.0
"""A path cut to the step bound keeps at least this much (the issue's 'reach >= 1 m where the floor allows')."""


def cut_lengths(lengths: np.ndarray, budget: float, keep_m: float = KEEP_M) -> np.ndarray:
    """Path lengths summing to at most budget: each keeps the same fraction f of its length (the largest f that fits,
    which maximises the smallest reach fraction), but at least min(length, keep_m); the lengths unchanged when they fit."""
    lengths = np.asarray(lengths, np.float64)
    if lengths.sum() <= budget:
        return lengths.copy()

    def cut(f):
        return np.minimum(lengths, np.maximum(f * lengths, keep_m))

    lo, hi = 0.0, 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cut(mid).sum() <= budget else (lo, mid)
    return cut(lo)


def _largest_remainder(weights: np.ndarray, total: int, minimum: int = 1) -> np.ndarray:
    """Integers >= minimum summing to total, proportional to weights (largest remainders get the leftovers)."""
    n = len(weights)
    base = np.full(n, minimum)
    left = total - base.sum()
    if left <= 0:
        return base
    share = left * weights / weights.sum()
    m = np.floor(share).astype(int)
    rest = left - int(m.sum())
    m[np.argsort(-(share - m), kind="stable")[:rest]] += 1
    return base + m


def plan_explore(nav: NavMesh, start: np.ndarray, params: TrajectoryParams) -> Plan:
    """Sector exploration paths: pose 0 at the camera, then one path per sector walking away from it.

    Each sector's target is its NavMesh point farthest from the camera within params.reach_m of walking (None: any
    connected floor; points outside the central half of the sector count OFF_CENTRE_WEIGHT of their distance); its
    path is the smoothed NavMesh shortest path (A* + funnel) from the camera's walkable hub to that target. Sectors
    whose path is shorter than one step are skipped. When the paths (and the approach) are longer than
    (N - 1) * params.max_step_m, they are cut to one fraction of their length (cut_lengths; info["path_cut_fraction"]).
    The N - 1 poses after pose 0 are shared between the paths in proportion to their lengths and each path is
    resampled uniformly (its first pose one step out from the camera, its last on the target), so every path has
    about the same step, (total path length) / (N - 1); params.step_m and stride do not apply. Paths are ordered
    by sector (0 = straight ahead, then towards +x); info["paths"] gives each one's pose range [start, stop) and its
    predecessor `from` (pose 0). A start off the NavMesh first walks straight to the hub (info["approach_steps"]
    poses, at most MAX_APPROACH_SHARE of them, listed as an `approach` path); the paths then leave from the hub.
    """
    start = np.asarray(start, np.float64).reshape(2)
    n_steps = params.frames - 1
    plan_nav = planning_mesh(nav, start, params.plan_margin_m)
    hub, off = planning_hub(plan_nav, start)
    field = GeodesicField(plan_nav, hub)
    r = np.linalg.norm(field.xz - start, axis=1)
    sec = sector_of(field.xz, start, params.sectors)
    width = 2 * np.pi / params.sectors
    lon = np.arctan2(field.xz[:, 0] - start[0], field.xz[:, 1] - start[1])
    central = np.abs(np.angle(np.exp(1j * (lon - sec * width)))) <= 0.25 * width
    score = r * np.where(central, 1.0, OFF_CENTRE_WEIGHT)
    reach = np.inf if params.reach_m is None else params.reach_m
    usable = (r >= MIN_SECTOR_DIST_M) & np.isfinite(field.dist) & (off + field.dist <= reach)
    extent = sector_extent(field, start, params.sectors, reach - off)
    legs, sectors = [], []
    for k in range(params.sectors):
        cand = np.flatnonzero(usable & (sec == k))
        if len(cand) == 0:
            continue
        target = field.xz[cand[np.argmax(score[cand])]]
        leg = smooth_polyline(plan_nav, plan_nav.path(hub, target), closed=False, iterations=params.smooth_iterations)
        if polyline_length(leg) >= MIN_SECTOR_DIST_M:
            legs.append(leg)
            sectors.append(k)
    lengths = np.array([polyline_length(leg) for leg in legs])
    # paths too long for max_step_m over the N - 1 poses (the approach included): each cut to the same fraction
    full = lengths
    lengths = cut_lengths(full, n_steps * params.max_step_m - off)
    legs = [truncate_polyline(leg, x) for leg, x in zip(legs, lengths)]
    # a start off the NavMesh: one shared straight approach to the hub (<= MAX_APPROACH_SHARE of the poses), then
    # every path leaves from the hub
    approach = approach_path(start, hub, (off + lengths.sum()) / max(n_steps, 1), n_steps) if off > 0 else start[None]
    n_approach = len(approach) - 1
    if not legs or n_steps - n_approach < len(legs):
        raise ValueError(
            f"no sector around the camera has walkable floor {MIN_SECTOR_DIST_M} m away within reach_m={params.reach_m} "
            f"({len(legs)} paths for {params.frames} poses): the walkable area is too small ({nav.area:.2f} m^2) or "
            f"too far ({off:.2f} m); reduce the agent radius"
        )
    counts = _largest_remainder(lengths, n_steps - n_approach)
    positions, paths, tips = [approach], [], []
    if n_approach:
        paths.append({"sector": None, "approach": True, "start": 1, "stop": n_approach + 1})
    for leg, k, n in zip(legs, sectors, counts):
        pts = resample_polyline(leg, int(n) + 1)[1:]
        paths.append({"sector": int(k), "start": int(sum(len(p) for p in positions)), "stop": 0, "from": n_approach})
        positions.append(pts)
        paths[-1]["stop"] = paths[-1]["start"] + len(pts)
        tips.append(float(np.linalg.norm(pts[-1] - start)))
    positions = np.concatenate(positions)
    steps = lengths / counts
    tip_by_sector = np.zeros(params.sectors)
    tip_by_sector[sectors] = tips
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(extent > 0, tip_by_sector / extent, np.nan)
    return Plan(
        positions,
        float(np.mean(steps)),
        {
            "paths": paths,
            "sectors_visited": sectors,
            "sectors_reachable": int((extent >= MIN_SECTOR_DIST_M).sum()),
            "sectors_covered": int(sector_coverage(positions, start, params.sectors, MIN_SECTOR_DIST_M).sum()),
            "sector_extent_m": extent.round(4).tolist(),
            "sector_tip_m": tip_by_sector.round(4).tolist(),
            "reach_fraction_min": float(np.nanmin(frac)) if np.isfinite(frac).any() else None,
            "path_steps_m": steps.round(4).tolist(),
            "path_cut_fraction": float((lengths / np.maximum(full, 1e-9)).min()) if len(full) else 1.0,
            "start_off_navmesh_m": off,
            "approach_steps": n_approach,
            "hub": hub.tolist(),
        },
        exempt=list(range(n_approach + 1)),
    )
