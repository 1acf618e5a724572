"""Walkable-floor NavMesh from a scene mesh: floor height, heightfield, erosion, polygons, triangulation, A* + funnel."""

from panoworld.navmesh.build import build_navmesh
from panoworld.navmesh.heightfield import (
    MIN_CAMERA_HEIGHT_M,
    FloorGrid,
    NavMeshParams,
    NoFloorError,
    band_top,
    check_mesh,
    downsample_erp_mesh,
    erosion_m,
    erp_grid_shape,
    estimate_floor_y,
    floor_grid,
    simplify_tolerance_m,
)
from panoworld.navmesh.navmesh import FORMAT_VERSION, NAVMESH_GLB, NAVMESH_JSON, NAVMESH_OBJ, NavMesh, load_navmesh
from panoworld.navmesh.polygons import cross_section, polygons_from_mask, triangulate_rings

__all__ = [
    "FORMAT_VERSION", "MIN_CAMERA_HEIGHT_M", "NAVMESH_GLB", "NAVMESH_JSON", "NAVMESH_OBJ", "FloorGrid", "NavMesh",
    "NavMeshParams", "NoFloorError", "band_top", "build_navmesh", "check_mesh", "cross_section", "downsample_erp_mesh",
    "erosion_m", "erp_grid_shape", "estimate_floor_y", "floor_grid", "load_navmesh", "polygons_from_mask",
    "simplify_tolerance_m", "triangulate_rings",
]
