"""No room to move (a camera in a shallow closet): a smaller agent, else a stationary NavMesh at the camera, with the reason."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from panoworld.core.errors import NoFloorError
from panoworld.geometry.navmesh import NavMesh
from panoworld.geometry.polygons import triangulate_rings
from panoworld.navmesh.build import build_navmesh
from panoworld.navmesh.heightfield import NavMeshParams, band_top, check_mesh, estimate_floor_y

MIN_ROOM_M2 = 0.1
"""A walkable area under this is no room to move: the planners need floor 0.1 m away from the camera in some sector."""
SMALLER_AGENT_RADII_M = (0.15, 0.1)
"""Agent radii tried, in order, below the requested one when it has no room (a camera held by hand needs ~0.1 m)."""
STATIONARY_RADIUS_M = 0.02
"""Radius of the NavMesh disk at the camera when no agent fits anywhere: the path stays at the camera and turns."""


def build_navmesh_with_room(vertices: np.ndarray, faces: np.ndarray, face_valid: np.ndarray | None,
                            params: NavMeshParams) -> NavMesh:
    """build_navmesh, and when the floor has no room for the agent (NoFloorError or under MIN_ROOM_M2): the same
    with SMALLER_AGENT_RADII_M, else a stationary disk at the camera. info["no_room"] then holds the reason, the
    decision ("smaller agent" | "stationary") and the radii; the agent record holds the radius actually used."""
    reason, last = _attempt(vertices, faces, face_valid, params)
    if reason is None:
        return last
    tried = []
    for r in (r for r in SMALLER_AGENT_RADII_M if r < params.agent_radius_m):
        why, nav = _attempt(vertices, faces, face_valid, replace(params, agent_radius_m=r))
        tried.append({"agent_radius_m": r, "problem": why})
        if why is None:
            nav.info["no_room"] = {"reason": reason, "decision": "smaller agent", "requested_agent_radius_m":
                                   params.agent_radius_m, "agent_radius_m": r, "tried": tried}
            return nav
    nav = stationary_navmesh(vertices, faces, face_valid, params, last)
    nav.info["no_room"] = {"reason": reason, "decision": "stationary", "requested_agent_radius_m": params.agent_radius_m,
                           "agent_radius_m": nav.agent["agent_radius_m"], "tried": tried}
    return nav


def _attempt(vertices, faces, face_valid, params: NavMeshParams) -> tuple[str | None, NavMesh | None]:
    """(None, NavMesh) when the floor has room for the agent, else (why not, the NavMesh if one was built)."""
    try:
        nav = build_navmesh(vertices, faces, face_valid, params=params)
    except NoFloorError as e:
        return f"no walkable floor for an agent of radius {params.agent_radius_m} m: {e}", None
    if nav.area < MIN_ROOM_M2:
        return (f"the walkable floor is {nav.area:.3f} m^2 for an agent of radius {params.agent_radius_m} m "
                f"(under {MIN_ROOM_M2} m^2: no room to move)"), nav
    return None, nav


def stationary_navmesh(vertices, faces, face_valid, params: NavMeshParams, tiny: NavMesh | None) -> NavMesh:
    """A disk of STATIONARY_RADIUS_M at the camera, at the floor height found (else one camera_height below)."""
    if tiny is not None:
        floor_y, info = tiny.floor_y, dict(tiny.info)
    else:
        try:
            v32, f64 = np.asarray(vertices, np.float32), np.asarray(faces, np.int64)
            floor_y = float(estimate_floor_y(v32, f64, check_mesh(v32, f64, face_valid), params=params)[0])
        except (NoFloorError, ValueError):
            floor_y = 1.6
        info = {"cell_m": params.cell_m, "camera_height_m": floor_y, "assumed_walkable": {}, "erp_downsample": 1,
                "faces_used": int(len(faces)), "timings_s": {}}
    theta = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring = STATIONARY_RADIUS_M * np.stack([np.cos(theta), np.sin(theta)], 1)
    v, tri, adj = triangulate_rings([ring], 1.0)
    info.update(camera_on_navmesh=True, camera_distance_to_navmesh_m=0.0, camera_height_m=floor_y)
    agent = {"agent_radius_m": min(params.agent_radius_m, SMALLER_AGENT_RADII_M[-1]),
             "agent_height_m": params.agent_height_m, "step_height_m": params.step_height_m,
             "band_top_m": band_top(floor_y, params)}
    return NavMesh(v, tri, adj, [ring], floor_y, agent, info)
