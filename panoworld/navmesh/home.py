"""A home's NavMesh: the fused mesh's floor around the first capture point, reaching every other capture point."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from panoworld.geometry.erp_mesh import ErpMesh
from panoworld.geometry.navmesh import NavMesh
from panoworld.navmesh import NavMeshParams, build_navmesh


def home_navmesh(mesh: ErpMesh, world_from_cam: dict[str, np.ndarray], params: NavMeshParams | None = None
                 ) -> tuple[NavMesh, dict[str, bool]]:
    """NavMesh of the fused mesh around the first capture point, and whether each capture point stands on it."""
    names = list(world_from_cam)
    xz = np.array([world_from_cam[n][[0, 2], 3] for n in names])
    reach = float(np.max(np.linalg.norm(xz - xz[0], axis=1))) + 12.0
    params = replace(params or NavMeshParams(), max_erp_height=0, max_range_m=reach)
    nav = build_navmesh(mesh.vertices, mesh.faces, mesh.face_valid, params=params, camera_xz=tuple(xz[0]))
    return nav, dict(zip(names, (bool(c) for c in nav.contains(xz))))
