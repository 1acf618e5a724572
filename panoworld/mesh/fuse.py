"""One mesh from several registered panoramas: each one's ERP mesh in the world frame, every surface point kept only
from the panorama that sees it from nearest (no doubled walls), its NavMesh is panoworld.navmesh.home."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import transform_points
from panoworld.geometry.erp_mesh import ErpMesh, erp_mesh_from_depth
from panoworld.geometry.panoramas import nearest_source


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


