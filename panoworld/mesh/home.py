"""The home's fused mesh from the depth artifact's panoramas at their registered poses, and its per-source layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.core.parallel import cpu_threads
from panoworld.geometry.erp_mesh import ErpMesh
from panoworld.mesh.fuse import fuse_meshes
from panoworld.room.doorways import open_doorways
from panoworld.room.home_sources import home_sources


def home_mesh(dirs: dict[str, Path], world_from_cam: dict[str, np.ndarray], *, stride: int
              ) -> tuple[ErpMesh, np.ndarray, list[dict]]:
    """(fused mesh in the world frame, source index per face, sources) of the registered panoramas: every surface
    from the panorama that sees it from nearest (fuse.fuse_meshes), so its vertex colours come from that source. A
    surface through another capture point is none (room.home_sources), nor a wall across a doorway that
    another panorama's floor continues through (room.doorways.open_doorways)."""
    names, rgbs, depths, near = home_sources(dirs, world_from_cam)
    doors = open_doorways(names, rgbs, depths, world_from_cam, workers=cpu_threads(2))
    mesh, face_source = fuse_meshes(names, rgbs, depths, world_from_cam, stride=stride)
    sources, start = [], 0
    for n in names:
        h, w = (len(range(stride // 2, k, stride)) for k in depths[n].shape)
        sources.append({"name": n, "world_from_cam": np.asarray(world_from_cam[n]).round(9).tolist(),
                        "vertex_start": start, "grid": [h, w], "near_capture_px": near[n],
                        "doorway_px": doors[n]})
        start += h * w + 2
    return mesh, face_source, sources


