"""A home's NavMesh: the fused mesh's floor under every capture point, one connected component per floor, kept apart."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from panoworld.geometry.erp_mesh import ErpMesh
from panoworld.geometry.navmesh import HOME_SNAP_M, NavMesh
from panoworld.navmesh import NavMeshParams, build_navmesh


def home_navmesh(mesh: ErpMesh, world_from_cam: dict[str, np.ndarray], params: NavMeshParams | None = None
                 ) -> tuple[NavMesh, dict[str, bool]]:
    """NavMesh of the fused mesh holding the floor component of every capture point, and whether each capture point
    stands on it. Floors that connect (open doorways) are one component; floors that do not (layout depth closes
    every doorway) stay separate components of the one NavMesh. info["home"]: capture_components {NAME: component
    (NavMesh.components) or None} and components [{area_m2, capture_points}] (panoworld.trajectory.home walks within
    a component)."""
    names = list(world_from_cam)
    xz = np.array([world_from_cam[n][[0, 2], 3] for n in names])
    reach = float(np.max(np.linalg.norm(xz - xz[0], axis=1))) + 12.0
    params = replace(params or NavMeshParams(), max_erp_height=0, max_range_m=reach)
    nav = build_navmesh(mesh.vertices, mesh.faces, mesh.face_valid, params=params, camera_xz=xz, snap_m=HOME_SNAP_M)
    comp = nav.component_of(xz, HOME_SNAP_M)
    nav.info["home"] = {
        "capture_components": {n: (int(c) if c >= 0 else None) for n, c in zip(names, comp)},
        "components": [{"area_m2": round(float(a), 4), "capture_points": [n for n, c in zip(names, comp) if c == k]}
                       for k, a in enumerate(nav.component_areas())],
    }
    return nav, dict(zip(names, (bool(c) for c in nav.contains(xz))))
