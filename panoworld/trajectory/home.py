"""A home's trajectory: a frame at every capture point, exploration paths around each (plan_explore), NavMesh walks
(A*) from one capture point to the next on the same floor component, and a cut between components."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from panoworld.geometry.navmesh import HOME_SNAP_M, NavMesh
from panoworld.io.trajectory import path_indices
from panoworld.trajectory.common import Plan, TrajectoryParams, planning_hub, planning_mesh
from panoworld.trajectory.explore import _largest_remainder, plan_explore
from panoworld.trajectory.polyline import polyline_length, resample_polyline, smooth_polyline


def visit_order(nav: NavMesh, xz: np.ndarray, comp: np.ndarray) -> tuple[list[int], dict[int, np.ndarray]]:
    """Capture points (K, 2) in visiting order from the first, and the walks {i: polyline (M, 2)} from order[i] to
    order[i + 1]. The next capture point is the nearest by NavMesh path length among those not yet visited on the
    same component (comp (K,): NavMesh.component_of, -1 = none); when none is left there, a cut (no walk) to the
    nearest by straight line of those left."""
    hubs = [planning_hub(nav, p)[0] for p in xz]
    order, walks = [0], {}
    left = set(range(1, len(xz)))
    while left:
        a = order[-1]
        best = None
        for b in sorted(left):
            if comp[a] < 0 or comp[b] != comp[a]:
                continue
            try:
                path = nav.path(hubs[a], hubs[b])
            except ValueError:  # the planning margin split the component here: a cut
                continue
            path = np.concatenate([xz[a][None], path, xz[b][None]])
            if best is None or polyline_length(path) < polyline_length(best[1]):
                best = (b, path)
        if best is None:
            b = min(sorted(left), key=lambda j: float(np.linalg.norm(xz[j] - xz[a])))
        else:
            b = best[0]
            walks[len(order) - 1] = best[1]
        order.append(b)
        left.discard(b)
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


def _approach(nav: NavMesh, pts: np.ndarray, ends: np.ndarray, off: np.ndarray) -> np.ndarray:
    """(M,) bool: the walk points pts (M, 2) off the NavMesh on the straight way between one of its ends (2, 2) and
    the NavMesh (ends standing off it by off (2,)), exempt like an explore path's approach."""
    near = (np.linalg.norm(pts[:, None] - ends[None], axis=2) <= off[None] + 1e-6).any(axis=1)
    return near & ~nav.contains(pts)


def plan_home(nav: NavMesh, captures: dict[str, np.ndarray], params: TrajectoryParams, frames: int) -> Plan:
    """About `frames` positions over the home: a frame at each capture point (exempt from the NavMesh checks, like
    pose 0 of a single panorama), then its plan_explore paths, then the walk to the next capture point on the same
    NavMesh component. Between components (floors that do not connect) there is no walk: a cut, and the next
    capture frame starts new paths, as every capture frame does. The frames after the capture frames are shared in
    proportion to path length (each explore keeps at least one per sector path). A capture point on no component
    (none within HOME_SNAP_M) gets its capture frame only; one off the NavMesh but within HOME_SNAP_M walks
    straight onto it (those poses exempt, like an explore path's approach). info: paths (each with `capture` or `walk`; a path's
    `from` is a pose of its own component, or its own start), capture_frames {NAME: index}, components {NAME:
    component or None}, cuts [[NAME, NAME]], camera_y (per frame: the height of the capture point the frame belongs
    to, walks interpolate)."""
    names = list(captures)
    xz = np.array([captures[n][[0, 2], 3] for n in names])
    ys = np.array([captures[n][1, 3] for n in names])
    comp = nav.component_of(xz, HOME_SNAP_M)
    # walks keep the explore paths' margin to the edge
    plan_nav = planning_mesh(nav, xz[comp >= 0] if (comp >= 0).any() else xz[:1], params.plan_margin_m)
    order, walks = visit_order(plan_nav, xz, comp)
    off = np.array([planning_hub(plan_nav, p)[1] for p in xz])
    plans = {k: _explore(nav, xz[k], params) if comp[k] >= 0 else None for k in order}
    walks = {i: smooth_polyline(plan_nav, w, closed=False, iterations=params.smooth_iterations) for i, w in walks.items()}
    lengths = [_explore_length(plans[k]) for k in order] + [polyline_length(w) for w in walks.values()]
    minimum = [0 if plans[k] is None else len(plans[k].info["paths"]) for k in order] + [1] * len(walks)
    budget = max(frames - len(order), sum(minimum))
    counts = np.maximum(_largest_remainder(np.maximum(np.asarray(lengths), 1e-6), budget), minimum)
    walk_frames = dict(zip(walks, (int(n) for n in counts[len(order):])))
    positions, cam_y, paths, exempt, capture_frames, arrived = [], [], [], [], {}, set()
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
        if i in walks:
            b, n = order[i + 1], walk_frames[i]
            start = sum(len(p) for p in positions)
            pts = resample_polyline(walks[i], n + 2)[1:-1]
            positions.append(pts)
            exempt += [start + int(j) for j in np.flatnonzero(_approach(nav, pts, xz[[k, b]], off[[k, b]]))]
            cam_y.append(np.linspace(ys[k], ys[b], n + 2)[1:-1])
            paths.append({"walk": [names[k], names[b]], "start": start, "stop": start + n, "from": c})
            arrived.add(i + 1)
    covered = {j for p in paths for j in path_indices(p)}
    for i, k in enumerate(order):  # a capture frame no path leaves from: its own path, from the walk that ends there
        c = capture_frames[names[k]]
        if c not in covered:
            paths.append({"capture": names[k], "sector": None, "start": c, "stop": c + 1,
                          "from": c - 1 if i in arrived else c})
    positions = np.concatenate(positions)
    return Plan(positions, float(np.sum(lengths) / max(len(positions) - len(order), 1)), {
        "paths": paths, "capture_frames": capture_frames, "visit_order": [names[k] for k in order],
        "components": {n: (int(c) if c >= 0 else None) for n, c in zip(names, comp)},
        "cuts": [[names[order[i]], names[order[i + 1]]] for i in range(len(order) - 1) if i not in walks],
        "unreached_captures": [n for n, c in zip(names, comp) if c < 0], "camera_y": np.concatenate(cam_y).tolist(),
        "walk_length_m": [round(polyline_length(w), 4) for w in walks.values()],
        "explore_length_m": [round(x, 4) for x in lengths[:len(order)]],
    }, exempt=sorted(set(exempt)))
