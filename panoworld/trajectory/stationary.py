"""The path when there is no room to move: every pose at the camera, turning once around (rotation only)."""

from __future__ import annotations

import numpy as np

from panoworld.trajectory.common import Plan, TrajectoryParams


def stationary_plan(params: TrajectoryParams, reason: str) -> Plan:
    """N poses at the camera; info["yaw_rad"] turns them uniformly once around (pose 0 = identity). Every pose is
    the capture position itself, so all are exempt from the NavMesh and clearance checks."""
    n = params.frames
    yaw = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    info = {"rotation_only": True, "no_room": reason, "yaw_rad": yaw.tolist(), "start_off_navmesh_m": 0.0,
            "sectors_reachable": 0}
    return Plan(np.zeros((n, 2)), 0.0, info, exempt=list(range(n)))
