"""Walkable-floor NavMesh from a scene mesh: floor height, heightfield, erosion, boundary rings (the NavMesh type: panoworld.geometry.navmesh)."""

from panoworld.navmesh.build import build_navmesh
from panoworld.navmesh.heightfield import (
    MIN_CAMERA_HEIGHT_M,
    FloorGrid,
    NavMeshParams,
    band_top,
    check_mesh,
    downsample_erp_mesh,
    erosion_m,
    erp_grid_shape,
    estimate_floor_y,
    floor_grid,
    simplify_tolerance_m,
)
from panoworld.navmesh.polygons import polygons_from_mask

__all__ = [
    "MIN_CAMERA_HEIGHT_M", "FloorGrid",
    "NavMeshParams", "band_top", "build_navmesh", "check_mesh", "downsample_erp_mesh",
    "erosion_m", "erp_grid_shape", "estimate_floor_y", "floor_grid", "polygons_from_mask",
    "simplify_tolerance_m",
]
