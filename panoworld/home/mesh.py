"""The home's fused mesh from the depth artifact's panoramas at their registered poses, and its per-source layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.depth import load_depth_artifact
from panoworld.io.jsonio import read_json, write_json
from panoworld.mesh import ErpMesh
from panoworld.register.fuse import fuse_meshes

HOME_MESH_JSON = "home.json"
"""In a home's mesh artifact: {"sources": [{name, world_from_cam, vertex_start, grid: [h, w], near_capture_px (its
pixels dropped as a surface through another capture point)}]}; the fused mesh's
vertices are each source's ERP grid (h * w + 2 poles, world frame) one after the other."""


def load_sources(dirs: dict[str, Path], world_from_cam: dict[str, np.ndarray], *, near: dict | None = None
                 ) -> tuple[list[str], dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(registered names in order, cleaned RGB, depth with invalid pixels 0) of the home's panoramas. A surface
    through another capture point is no geometry (depth_plausible.near_captures_mask: 0 there); near, when given,
    gets {NAME: pixels so dropped}."""
    from panoworld.depth_plausible import near_captures_mask

    names = [n for n in dirs if n in world_from_cam]
    rgbs, depths = {}, {}
    for n in names:
        depth, valid, rgb = load_depth_artifact(dirs[n])
        depth = np.where(valid, depth, 0.0).astype(np.float32)
        others = [np.asarray(world_from_cam[m])[:3, 3] for m in names if m != n]
        drop = near_captures_mask(depth, world_from_cam[n], np.array(others).reshape(-1, 3))
        depth[drop] = 0.0
        depths[n], rgbs[n] = depth, rgb
        if near is not None:
            near[n] = int(drop.sum())
    return names, rgbs, depths


def home_mesh(dirs: dict[str, Path], world_from_cam: dict[str, np.ndarray], *, stride: int
              ) -> tuple[ErpMesh, np.ndarray, list[dict]]:
    """(fused mesh in the world frame, source index per face, sources) of the registered panoramas: every surface
    from the panorama that sees it from nearest (fuse.fuse_meshes), so its vertex colours come from that source."""
    near: dict[str, int] = {}
    names, rgbs, depths = load_sources(dirs, world_from_cam, near=near)
    mesh, face_source = fuse_meshes(names, rgbs, depths, world_from_cam, stride=stride)
    sources, start = [], 0
    for n in names:
        h, w = (len(range(stride // 2, k, stride)) for k in depths[n].shape)
        sources.append({"name": n, "world_from_cam": np.asarray(world_from_cam[n]).round(9).tolist(),
                        "vertex_start": start, "grid": [h, w], "near_capture_px": near[n]})
        start += h * w + 2
    return mesh, face_source, sources


def write_home_mesh_info(out_dir: Path, sources: list[dict]) -> None:
    write_json(Path(out_dir) / HOME_MESH_JSON, {"sources": sources})


def read_home_sources(mesh_artifact: Path) -> list[dict] | None:
    """The sources of a home's mesh artifact (HOME_MESH_JSON), None for a single panorama's mesh."""
    doc = read_json(Path(mesh_artifact) / HOME_MESH_JSON, default=None)
    return None if doc is None else doc["sources"]
