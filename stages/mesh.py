"""Triangle mesh of the ERP depth (seam closed, pole fans, vertex colours) with stretched faces flagged: mesh.ply (+ mesh.glb)."""

from __future__ import annotations

import enum
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.core.params import param
from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main

NAME = "mesh"
VERSION = "2"
ARTIFACT = "mesh"
INPUTS = {
    "depth": Input("depth", help="depth artifact (depth.npy, valid.png, panorama.png)"),
    "register": Input("register", optional=True, help="register artifact: with two or more panoramas placed, the "
                      "mesh is the home's, fused in the world frame (docs/multi.md)"),
}


class Discontinuity(enum.StrEnum):
    FLAG = "flag"
    """Keep stretched faces with valid = 0: occluders that mark what novel views must generate."""
    DROP = "drop"
    """Delete stretched faces: novel views see through the gaps to the background."""


@dataclass(kw_only=True)
class Params:
    max_edge_ratio: float = param(12.0, gt=1)
    """A face is stretched when an edge exceeds this many pixel footprints at its nearer end (12 ~ surfaces seen
    at under ~5 degrees)."""
    discontinuity: Discontinuity = Discontinuity.FLAG
    """How stretched triangles across depth edges are handled."""
    stride: int = param(1, ge=1, le=64)
    """Use every stride-th ERP pixel per axis as a vertex (exact points, colours averaged per block) to bound memory."""
    glb: bool = False
    """Also write mesh.glb (valid faces, vertex colours, glTF Y-up) for glTF viewers; mesh.ply (what the stages read)
    opens in Blender, MeshLab, CloudCompare and Open3D as it is."""
    home_stride: int = param(2, ge=1, le=64)
    """A home (several panoramas): stride of each panorama's ERP mesh before fusion (memory grows with panoramas)."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from panoworld.geometry.erp_mesh import ErpMesh, erp_mesh_from_depth, save_erp_mesh, save_erp_mesh_glb
    from panoworld.io.depth import load_depth_artifact
    from panoworld.io.home import capture_poses, home_depth_dirs

    poses = capture_poses(inputs.get("register"))
    if len(poses) >= 2:
        return _home_mesh(home_depth_dirs(inputs["depth"]), poses, params, out_dir)
    depth, valid, rgb = load_depth_artifact(inputs["depth"])
    t0 = time.perf_counter()
    mesh = erp_mesh_from_depth(depth, rgb, valid, max_edge_ratio=params.max_edge_ratio, stride=params.stride)
    build_s = time.perf_counter() - t0
    n_stretched = int((~mesh.face_valid).sum())
    if params.discontinuity == Discontinuity.DROP:
        mesh = ErpMesh(mesh.vertices, mesh.faces[mesh.face_valid], mesh.colors, np.ones(len(mesh.faces) - n_stretched, bool))
    save_erp_mesh(mesh, out_dir / "mesh.ply")
    if params.glb:
        save_erp_mesh_glb(mesh, out_dir / "mesh.glb")
    written = int(np.count_nonzero(np.bincount(mesh.faces.ravel(), minlength=len(mesh.vertices))))
    return {
        "num_vertices": len(mesh.vertices),
        "vertices_written": written,
        "invalid_pixels_dropped": len(mesh.vertices) - written,
        "num_faces": len(mesh.faces),
        "num_faces_stretched": n_stretched,
        "stretched_kept_as_occluders": params.discontinuity == Discontinuity.FLAG,
        "grid": [len(range(params.stride // 2, n, params.stride)) for n in depth.shape],
        "build_s": build_s,
    }


def _home_mesh(dirs, poses, params: Params, out_dir: Path) -> dict:
    from panoworld.geometry.erp_mesh import save_erp_mesh, save_erp_mesh_glb
    from panoworld.io.home import write_home_mesh_info
    from panoworld.mesh.home import home_mesh

    if dirs is None:
        raise StageInputError("the register artifact places several panoramas but the depth artifact holds one; "
                              "rerun the depth stage on the home's panoramas/")
    t0 = time.perf_counter()
    mesh, face_source, sources = home_mesh(dirs, poses, stride=params.home_stride)
    build_s = time.perf_counter() - t0
    save_erp_mesh(mesh, out_dir / "mesh.ply")
    write_home_mesh_info(out_dir, sources)
    if params.glb:
        save_erp_mesh_glb(mesh, out_dir / "mesh.glb")
    return {
        "num_vertices": len(mesh.vertices),
        "vertices_written": int(np.count_nonzero(np.bincount(mesh.faces.ravel(), minlength=len(mesh.vertices)))),
        "num_faces": len(mesh.faces),
        "num_faces_stretched": 0,
        "stretched_kept_as_occluders": False,
        "grid": sources[0]["grid"],
        "home": {"sources": [s["name"] for s in sources],
                 "faces_per_source": np.bincount(face_source, minlength=len(sources)).tolist(),
                 "doorway_px": {s["name"]: s["doorway_px"] for s in sources if s["doorway_px"]}},
        "build_s": build_s,
    }


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
