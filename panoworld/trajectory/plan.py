"""Plan a trajectory of the requested kind on a NavMesh."""

from __future__ import annotations

import numpy as np

from panoworld.geometry.navmesh import NavMesh
from panoworld.trajectory.common import PathKind, Plan, TrajectoryParams
from panoworld.trajectory.explore import plan_explore
from panoworld.trajectory.ring import plan_ring
from panoworld.trajectory.sectors import plan_sector


def plan_path(nav: NavMesh, params: TrajectoryParams, start: np.ndarray | None = None) -> Plan:
    """Plan params.frames positions of params.kind on the NavMesh from start (x, z; default the camera, 0, 0)."""
    start = np.zeros(2) if start is None else np.asarray(start, np.float64).reshape(2)
    if params.frames < 2:
        raise ValueError(f"frames={params.frames} but a trajectory needs at least 2")
    if params.stride not in (1, 2, 4):
        raise ValueError(f"stride={params.stride} but it must be 1, 2 or 4")
    if params.step_m <= 0:
        raise ValueError(f"step_m={params.step_m} must be positive")
    planner = {PathKind.SECTOR: plan_sector, PathKind.RING: plan_ring, PathKind.EXPLORE: plan_explore}[params.kind]
    plan = planner(nav, start, params)
    if plan.info.get("start_off_navmesh_m", 0.0) > 0:  # poses on the straight way from the camera to the hub
        hub = np.asarray(plan.info["hub"])
        ab = hub - start
        t = np.clip((plan.positions - start) @ ab / (ab @ ab), 0.0, 1.0)
        on_way = np.linalg.norm(start + t[:, None] * ab - plan.positions, axis=1) < 1e-6
        plan.exempt = sorted({0, *np.flatnonzero(on_way & ~nav.contains(plan.positions)).tolist()})
    if params.kind == PathKind.EXPLORE:
        return plan
    plan.info["requested_length_m"] = (params.frames - (0 if params.kind == PathKind.RING else 1)) * params.step_m * params.stride
    return plan
