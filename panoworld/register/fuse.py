"""One mesh from several registered panoramas: each one's ERP mesh in the world frame, every surface point kept only
from the panorama that sees it from nearest (no doubled walls), and the NavMesh over it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from panoworld.conventions import erp_pixel_from_dir, invert_pose, transform_points
from panoworld.mesh import ErpMesh, erp_mesh_from_depth
from panoworld.navmesh import NavMeshParams, build_navmesh
from panoworld.navmesh.navmesh import NavMesh


def _nearest_depth(depth: np.ndarray, pts_cam: np.ndarray) -> np.ndarray:
    h, w = depth.shape
    u, v = erp_pixel_from_dir(pts_cam, h, w)
    return depth[np.clip(np.floor(v).astype(int), 0, h - 1), np.floor(u).astype(int) % w]


def nearest_source(k: int, pts_world: np.ndarray, names: list[str], depths: dict[str, np.ndarray],
                   world_from_cam: dict[str, np.ndarray], *, tol: float = 0.03) -> np.ndarray:
    """(M,) bool for surface points (M, 3) seen by panorama names[k]: no other panorama j sees the same surface (its
    depth along the ray agrees within tol in log range) from nearer (ties: the lower index keeps it)."""
    r_k = np.linalg.norm(pts_world - world_from_cam[names[k]][:3, 3], axis=1)
    keep = np.ones(len(pts_world), bool)
    for j, other in enumerate(names):
        if j == k:
            continue
        p = transform_points(invert_pose(world_from_cam[other]), pts_world)
        r_j = np.linalg.norm(p, axis=1)
        d_j = _nearest_depth(np.asarray(depths[other], np.float64), p)
        seen = np.isfinite(d_j) & (d_j > 0) & (np.abs(np.log(np.maximum(r_j, 1e-6) / np.maximum(d_j, 1e-6))) < tol)
        nearer = (r_j < r_k) | ((r_j == r_k) & (j < k))
        keep &= ~(seen & nearer)
    return keep


def fuse_meshes(names: list[str], rgbs: dict[str, np.ndarray], depths: dict[str, np.ndarray],
                world_from_cam: dict[str, np.ndarray], *, stride: int = 4, tol: float = 0.03) -> tuple[ErpMesh, np.ndarray]:
    """(fused mesh in the world frame, source panorama index of each face). A vertex of panorama k is dropped when
    another panorama j sees the same surface (its depth along the ray agrees within tol in log range) from nearer
    (ties: the lower index keeps it); a non-stretched face survives when one of its vertices does."""
    names = [n for n in names if n in world_from_cam]
    meshes = {n: erp_mesh_from_depth(np.asarray(depths[n], np.float32), rgbs[n], stride=stride) for n in names}
    verts, faces, colors, valid, source = [], [], [], [], []
    offset = 0
    for k, n in enumerate(names):
        m = meshes[n]
        pts_world = transform_points(world_from_cam[n], m.vertices.astype(np.float64))
        keep = nearest_source(k, pts_world, names, depths, world_from_cam, tol=tol)
        # Faces with any kept vertex survive: neighbouring sources overlap by one face instead of leaving a crack.
        # Stretched faces (across one view's depth edges) are dropped: another view sees what they hide.
        kept = keep[m.faces].any(1) & m.face_valid
        f, fv = m.faces[kept], m.face_valid[kept]
        verts.append(pts_world.astype(np.float32))
        faces.append(f + offset)
        colors.append(m.colors)
        valid.append(fv)
        source.append(np.full(len(f), k, np.int32))
        offset += len(pts_world)
    mesh = ErpMesh(np.concatenate(verts), np.concatenate(faces).astype(np.int32), np.concatenate(colors),
                   np.concatenate(valid))
    return mesh, np.concatenate(source)


def home_navmesh(mesh: ErpMesh, world_from_cam: dict[str, np.ndarray], params: NavMeshParams | None = None
                 ) -> tuple[NavMesh, dict[str, bool]]:
    """NavMesh of the fused mesh around the first capture point, and whether each capture point stands on it."""
    names = list(world_from_cam)
    xz = np.array([world_from_cam[n][[0, 2], 3] for n in names])
    reach = float(np.max(np.linalg.norm(xz - xz[0], axis=1))) + 12.0
    params = replace(params or NavMeshParams(), max_erp_height=0, max_range_m=reach)
    nav = build_navmesh(mesh.vertices, mesh.faces, mesh.face_valid, params=params, camera_xz=tuple(xz[0]))
    return nav, dict(zip(names, (bool(c) for c in nav.contains(xz))))
