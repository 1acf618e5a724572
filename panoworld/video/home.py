"""warp-inpaint's background layer for a home's fused mesh: one per source panorama, in the world frame."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import invert_pose, transform_points
from panoworld.geometry.erp_mesh import ErpMesh
from panoworld.video.background_layer import BackgroundLayer, build_background_layer


def source_mesh(mesh: ErpMesh, source: dict) -> ErpMesh:
    """The part of a home's fused mesh that came from one source, as that panorama's ERP grid mesh in its camera
    frame (vertices no face of it uses at the origin, i.e. invalid)."""
    h, w = source["grid"]
    start, n = source["vertex_start"], h * w + 2
    inside = np.all((mesh.faces >= start) & (mesh.faces < start + n), axis=1)
    faces = mesh.faces[inside] - start
    used = np.zeros(n, bool)
    used[faces] = True
    cam = transform_points(invert_pose(np.asarray(source["world_from_cam"])), mesh.vertices[start:start + n].astype(np.float64))
    cam[~used] = 0.0
    return ErpMesh(cam.astype(np.float32), faces.astype(np.int32), mesh.colors[start:start + n], mesh.face_valid[inside])


def home_background_layer(mesh: ErpMesh, sources: list[dict], poses: np.ndarray, **options) -> BackgroundLayer:
    """build_background_layer of every source's part (its band sized by the trajectory poses nearest to that source),
    joined in the world frame with the whole fused mesh's valid faces."""
    centres = np.array([np.asarray(s["world_from_cam"])[:3, 3] for s in sources])
    cams = np.asarray(poses)[:, :3, 3]
    nearest = np.argmin(np.linalg.norm(cams[:, None] - centres[None], axis=2), axis=1)
    vertices, faces, colors = [mesh.vertices], [mesh.faces[mesh.face_valid]], [mesh.colors]
    offset, layer_faces = len(mesh.vertices), 0
    for k, s in enumerate(sources):
        near = cams[nearest == k]
        reach = float(np.linalg.norm(near - centres[k], axis=1).max()) if len(near) else 0.0
        sub = source_mesh(mesh, s)
        layer = build_background_layer(sub, reach, **options)
        if not layer.layer_faces:
            continue
        extra = layer.faces[-layer.layer_faces:]  # the layer's own faces index the sub-mesh grid and its new vertices
        new = len(sub.vertices)
        world = transform_points(np.asarray(s["world_from_cam"]), layer.vertices.astype(np.float64)).astype(np.float32)
        grid_to_fused = np.concatenate([np.arange(new) + s["vertex_start"], offset + np.arange(len(world) - new)])
        vertices.append(world[new:])
        colors.append(layer.colors[new:])
        faces.append(grid_to_fused[extra].astype(np.int32))
        offset += len(world) - new
        layer_faces += layer.layer_faces
    return BackgroundLayer(np.concatenate(vertices), np.concatenate(faces), np.concatenate(colors), layer_faces,
                           np.zeros((1, 2), bool), np.zeros((1, 2), np.float32))
