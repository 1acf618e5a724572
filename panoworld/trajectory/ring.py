"""Ring paths: a closed loop through the start around a nearby centre, 1-4 laps."""

from __future__ import annotations

import numpy as np

from panoworld.geometry.navmesh import NavMesh
from panoworld.trajectory.common import Plan, TrajectoryParams, planning_hub, planning_mesh
from panoworld.trajectory.polyline import polyline_length, resample_polyline, smooth_polyline


def _ring_candidate(nav: NavMesh, hub: np.ndarray, center: np.ndarray, radius: float, n_dirs: int, margin: float):
    """Star-shaped loop around center through hub: (loop points (n_dirs, 2) with loop[0] = hub, roundness) or None."""
    if not nav.contains(center)[0]:
        return None
    theta0 = np.arctan2(*(hub - center)[::-1])
    theta = theta0 + np.arange(n_dirs) * 2 * np.pi / n_dirs
    dirs = np.stack([np.cos(theta), np.sin(theta)], 1)
    reach = nav.ray_reach(center, dirs)
    if reach[0] < radius - 1e-9:
        return None
    rho = np.clip(np.minimum(radius, reach - margin), 0.0, None)
    rho[0] = radius
    loop = center + rho[:, None] * dirs
    loop[0] = hub
    return loop, float(np.mean(rho / radius))


def _ring_loop(plan_nav: NavMesh, hub: np.ndarray, loop_target: float, step: float, margin: float):
    """The best star-shaped loop through hub of length <= loop_target: (loop (K, 2), roundness, radius, centre, length)."""

    def candidate(radius: float, phi: float):
        c = hub + radius * np.array([np.cos(phi), np.sin(phi)])
        cand = _ring_candidate(plan_nav, hub, c, radius, 48, margin)
        return None if cand is None else (cand[0], cand[1], radius, c, polyline_length(cand[0], closed=True))

    r0 = loop_target / (2 * np.pi)
    cands = []
    for scale in (1.6, 1.3, 1.0, 0.85, 0.7, 0.55, 0.4, 0.3, 0.2, 0.12):
        if r0 * scale < 1.5 * step:
            break
        for phi in np.arange(16) * 2 * np.pi / 16:
            cand = candidate(r0 * scale, phi)
            if cand is not None:
                cands.append((phi, cand))
    if not cands:
        return None
    fits = [pc for pc in cands if pc[1][4] <= loop_target] or [min(cands, key=lambda pc: pc[1][4])]
    phi, best = max(fits, key=lambda pc: (round(pc[1][4] / loop_target, 2), pc[1][1]))
    longer = [c[2] for p_, c in cands if p_ == phi and c[4] > loop_target and c[2] > best[2]]
    if longer and best[4] <= loop_target:  # bisect the radius towards the target length on this bearing
        lo, hi = best[2], min(longer)
        for _ in range(12):
            cand = candidate(0.5 * (lo + hi), phi)
            if cand is not None and cand[4] <= loop_target:
                best, lo = cand, cand[2]
            else:
                hi = 0.5 * (lo + hi)
    return best


def plan_ring(nav: NavMesh, start: np.ndarray, params: TrajectoryParams) -> Plan:
    """A closed loop through the start around a nearby centre, run for 1-4 laps so the step stays as requested.

    For each lap count k the loop should be N * step / k long: centres on 16 bearings at distances R (around
    that length / 2 pi) from the start are tried; each loop has radius R, pulled in where the NavMesh is nearer;
    the longest loop not longer than the target (rounder on ties) wins and its radius is bisected towards the
    target. The fewest laps whose loop reaches 97 % of its target win (else the longest steps). Chords that would
    leave the NavMesh follow its shortest path instead; the loop is smoothed (the start stays a vertex) and the
    laps are resampled to N poses, the last one step before the first.
    """
    start = np.asarray(start, np.float64).reshape(2)
    step = params.step_m * params.stride
    target_len = params.frames * step
    plan_nav = planning_mesh(nav, start, params.plan_margin_m)
    hub, off = planning_hub(plan_nav, start)
    margin = max(params.plan_margin_m, 0.5 * step)
    options = []
    for laps in (1, 2, 3, 4):
        loop_target = (target_len - 2 * off) / laps
        best = _ring_loop(plan_nav, hub, loop_target, step, margin) if loop_target > 0 else None
        if best is not None:
            options.append((laps, best, best[4] / loop_target))
            if best[4] >= 0.97 * loop_target:
                break
    if not options:
        raise ValueError(
            f"no loop of radius >= {1.5 * step:.3f} m fits around the start in the walkable area ({nav.area:.2f} m^2); "
            "reduce step_m/stride or the agent radius, or use kind=sector"
        )
    laps, (loop, roundness, radius, center, _), _ = next((o for o in options if o[2] >= 0.97), max(options, key=lambda o: o[2]))
    pieces = []
    for a, b in zip(loop, np.roll(loop, -1, axis=0)):
        if plan_nav.blocked(a[None], b[None])[0] or not plan_nav.contains(b)[0]:
            pieces.append(plan_nav.path(a, plan_nav.closest_point(b)[0])[:-1])
        else:
            pieces.append(a[None])
    loop = smooth_polyline(plan_nav, np.concatenate(pieces), closed=True, iterations=params.smooth_iterations, pinned=0)
    loop_length = polyline_length(loop, closed=True)
    tour = np.concatenate([loop] * laps)
    if off > 0:  # leave the camera to the NavMesh and come back the same way
        tour = np.concatenate([start[None], tour, hub[None]])
    length = polyline_length(tour, closed=True)
    spacing = length / params.frames
    positions = resample_polyline(tour, params.frames, closed=True)
    positions[0] = start
    return Plan(
        positions,
        spacing,
        {
            "ring_center": center.round(4).tolist(),
            "ring_radius_m": radius,
            "ring_roundness": roundness,
            "ring_laps": laps,
            "loop_length_m": loop_length,
            "step_adapted": bool(spacing < 0.98 * step),
            "start_off_navmesh_m": off,
            "hub": hub.tolist(),
        },
    )
