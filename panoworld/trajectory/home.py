"""A home's trajectory: a frame at every capture point, exploration paths around each (plan_explore) and NavMesh
walks (A*) from one capture point to the next."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from panoworld.geometry.navmesh import NavMesh
from panoworld.io.trajectory import path_indices
from panoworld.trajectory.common import Plan, TrajectoryParams, planning_hub, planning_mesh
from panoworld.trajectory.explore import _largest_remainder, plan_explore
from panoworld.trajectory.polyline import polyline_length, resample_polyline, smooth_polyline


def visit_order(nav: NavMesh, xz: np.ndarray) -> tuple[list[int], dict[tuple[int, int], np.ndarray]]:
    """Capture points in walking order from the first (greedy nearest by NavMesh path length) and the walks
    {(a, b): polyline (K, 2)} between consecutive ones."""
    hubs = [planning_hub(nav, p)[0] for p in xz]
    order, walks = [0], {}
    left = set(range(1, len(xz)))
    while left:
        a = order[-1]
        best = None
        for b in sorted(left):
            try:
                path = nav.path(hubs[a], hubs[b])
            except ValueError:  # not connected: the NavMesh stage reports it
                continue
            path = np.concatenate([xz[a][None], path, xz[b][None]])
            if best is None or polyline_length(path) < polyline_length(best[1]):
                best = (b, path)
        if best is None:
            break
        order.append(best[0])
        walks[a, best[0]] = best[1]
        left.discard(best[0])
    return order, walks


HOME_REACH_M = 3.0
"""A home's explore paths walk at most this far from their capture point (other rooms have capture points of their own)."""


def _explore_length(plan: Plan | None) -> float:
    return 0.0 if plan is None else float(sum(polyline_length(plan.positions[path_indices(p)]) for p in plan.info["paths"]))


def _explore(nav: NavMesh, start: np.ndarray, params: TrajectoryParams) -> Plan | None:
    """plan_explore, or None where the floor around this capture point leaves no sector path (the walks still come).
    No reach_m (one panorama: the room's extent) walks HOME_REACH_M here (the rest of the home has its own captures),
    and no max_step_m cut: plan_home shares the frames by path length itself."""
    try:
        return plan_explore(nav, start, replace(params, reach_m=params.reach_m or HOME_REACH_M, max_step_m=np.inf))
    except ValueError:
        return None


def plan_home(nav: NavMesh, captures: dict[str, np.ndarray], params: TrajectoryParams, frames: int) -> Plan:
    """About `frames` positions over the home: a frame at each capture point (exempt from the NavMesh checks, like
    pose 0 of a single panorama), then its plan_explore paths, then the walk to the next capture point. The frames
    after the capture frames are shared in proportion to path length (each explore keeps at least one per sector
    path). info: paths (each with `capture` or `walk`), capture_frames {NAME: index}, camera_y (per frame: the
    height of the capture point the frame belongs to, walks interpolate)."""
    names = list(captures)
    xz = np.array([captures[n][[0, 2], 3] for n in names])
    ys = np.array([captures[n][1, 3] for n in names])
    plan_nav = planning_mesh(nav, xz[0], params.plan_margin_m)  # walks keep the explore paths' margin to the edge
    order, walks = visit_order(plan_nav, xz)
    unreached = [names[k] for k in range(len(names)) if k not in order]
    plans = {k: _explore(nav, xz[k], params) for k in order}
    walks = {ab: smooth_polyline(plan_nav, w, closed=False, iterations=params.smooth_iterations) for ab, w in walks.items()}
    lengths = [_explore_length(plans[k]) for k in order] + [polyline_length(w) for w in walks.values()]
    minimum = [0 if plans[k] is None else len(plans[k].info["paths"]) for k in order] + [1] * len(walks)
    budget = max(frames - len(order), sum(minimum))
    counts = np.maximum(_largest_remainder(np.maximum(np.asarray(lengths), 1e-6), budget), minimum)
    positions, cam_y, paths, exempt, capture_frames = [], [], [], [], {}
    walk_list = list(walks.items())
    for i, k in enumerate(order):
        c = sum(len(p) for p in positions)
        capture_frames[names[k]] = c
        exempt.append(c)
        positions.append(xz[k][None])
        cam_y.append([ys[k]])
        plan = None if plans[k] is None else _explore(nav, xz[k], replace(params, frames=int(counts[i]) + 1))
        if plan is not None:
            shift = lambda j, c=c: c if j == 0 else c + j
            positions.append(plan.positions[1:])
            cam_y.append(np.full(len(plan.positions) - 1, ys[k]))
            for p in plan.info["paths"]:
                paths.append({**p, "capture": names[k], "start": shift(p["start"]), "stop": shift(p["stop"]),
                              "from": shift(int(p.get("from", 0)))})
            exempt += [shift(j) for j in plan.exempt if j > 0]
        if i < len(walk_list):
            (a, b), w = walk_list[i]
            n = int(counts[len(order) + i])
            start = sum(len(p) for p in positions)
            pts = resample_polyline(w, n + 2)[1:-1]
            positions.append(pts)
            cam_y.append(np.linspace(ys[a], ys[b], n + 2)[1:-1])
            paths.append({"walk": [names[a], names[b]], "start": start, "stop": start + n, "from": c})
    covered = {j for p in paths for j in [int(p.get("from", 0))] + list(range(p["start"], p["stop"]))}
    for name, c in capture_frames.items():  # a capture point with no explore path and no walk leaving it (the last)
        if c not in covered:
            paths.append({"capture": name, "sector": None, "start": c, "stop": c + 1, "from": max(c - 1, 0)})
    positions = np.concatenate(positions)
    return Plan(positions, float(np.sum(lengths) / max(len(positions) - len(order), 1)), {
        "paths": paths, "capture_frames": capture_frames, "visit_order": [names[k] for k in order],
        "unreached_captures": unreached, "camera_y": np.concatenate(cam_y).tolist(),
        "walk_length_m": [round(polyline_length(w), 4) for w in walks.values()],
        "explore_length_m": [round(x, 4) for x in lengths[:len(order)]],
    }, exempt=sorted(set(exempt)))
