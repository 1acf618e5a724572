"""Build a NavMesh from a scene mesh: floor, heightfield, erosion, the components under the cameras, triangulation."""

from __future__ import annotations

import time

import numpy as np

from panoworld.core.errors import NoFloorError
from panoworld.geometry.navmesh import NavMesh
from panoworld.geometry.polygons import cross_section, pick_components, triangulate_rings
from panoworld.navmesh.heightfield import (
    NavMeshParams,
    band_top,
    check_mesh,
    downsample_erp_mesh,
    erosion_m,
    estimate_floor_y,
    floor_grid,
    simplify_tolerance_m,
)
from panoworld.navmesh.polygons import polygons_from_mask


def build_navmesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    face_valid: np.ndarray | None = None,
    *,
    params: NavMeshParams | None = None,
    camera_xz: tuple[float, float] | np.ndarray = (0.0, 0.0),
    snap_m: float = np.inf,
) -> NavMesh:
    """NavMesh of the walkable floor of a mesh (V, 3) / (F, 3) in the canonical frame (camera at the origin).

    face_valid (F,) False marks stretched triangles (treated as unseen, never floor). Keeps the connected
    walkable region under the camera, or the nearest one within snap_m (info["camera_on_navmesh"] = False, with the
    distance). camera_xz (K, 2) of several cameras (a home's capture points) keeps the region under each of them:
    the NavMesh then has one connected component per floor that holds a camera, kept apart (info["cameras_on_navmesh"],
    info["cameras_distance_to_navmesh_m"]; the first camera is "the camera"). Raises NoFloorError when no walkable floor
    exists, or none within snap_m of a camera.
    """
    params = params or NavMeshParams()
    t0 = time.perf_counter()
    vertices = np.asarray(vertices, np.float32)
    faces = np.asarray(faces, np.int64)
    face_valid = check_mesh(vertices, faces, face_valid)
    timings = {}
    mesh_faces = len(faces)
    vertices, faces, face_valid, stride = downsample_erp_mesh(vertices, faces, face_valid, params.max_erp_height)
    timings["downsample_s"] = time.perf_counter() - t0
    t = time.perf_counter()
    floor_y, floor_area = estimate_floor_y(vertices, faces, face_valid, params=params)
    timings["floor_s"] = time.perf_counter() - t
    t = time.perf_counter()
    cams = np.asarray(camera_xz, np.float64).reshape(-1, 2)
    grid = floor_grid(vertices, faces, face_valid, floor_y, params=params, camera_xz=cams)
    timings["heightfield_s"] = time.perf_counter() - t
    if not grid.free.any():
        raise NoFloorError(
            f"no floor cell is at least {params.agent_radius_m} m (agent radius) away from obstacles and unseen areas"
        )
    t = time.perf_counter()
    tol = simplify_tolerance_m(params)
    rings = polygons_from_mask(grid.free, grid, tol)
    if not rings:
        raise NoFloorError("the eroded walkable floor has no polygon")
    comp_rings, on_mesh, cam_dist = pick_components(cross_section(rings), cams, snap_m,
                                                    params.min_floor_area_m2 if np.isfinite(snap_m) else 0.0)
    timings["polygons_s"] = time.perf_counter() - t
    t = time.perf_counter()
    v, tri, adj = triangulate_rings(comp_rings, params.max_triangle_area_m2)
    timings["triangulate_s"] = time.perf_counter() - t
    agent = {
        "agent_radius_m": params.agent_radius_m,
        "agent_height_m": params.agent_height_m,
        "step_height_m": params.step_height_m,
        "band_top_m": band_top(floor_y, params),
    }
    info = {
        "cell_m": params.cell_m,
        "camera_height_m": floor_y,
        "floor_area_seen_m2": float(grid.walkable.sum() * params.cell_m**2),
        "floor_histogram_peak_m2": floor_area,
        "erosion_m": erosion_m(params),
        "simplify_m": tol,
        "max_triangle_area_m2": params.max_triangle_area_m2,
        "grid_shape": list(grid.free.shape),
        "assumed_walkable": grid.assumptions,
        "camera_on_navmesh": bool(on_mesh[0]),
        "camera_distance_to_navmesh_m": float(cam_dist[0]),
        **({"cameras_on_navmesh": on_mesh.tolist(), "cameras_distance_to_navmesh_m": cam_dist.round(4).tolist()}
           if len(cams) > 1 else {}),
        "mesh_faces": int(mesh_faces),
        "erp_downsample": stride,
        "faces_used": int(len(faces)),
        "timings_s": {**timings, "total_s": time.perf_counter() - t0},
    }
    return NavMesh(v, tri, adj, comp_rings, floor_y, agent, info, grid)

