"""Simulation-ready asset: scene.usdc (3DGS particles, collider, NavMesh, spawns, cameras), collider.obj, asset.json."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from panoworld.core.errors import ArtifactError
from panoworld.core.params import param
from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main

NAME = "asset"
VERSION = "2"
ARTIFACT = "asset"
INPUTS = {
    "gaussians": Input("gaussians", help="gaussians artifact (gaussians.ply, canonical frame)"),
    "mesh": Input("mesh", help="mesh artifact (mesh.ply): its valid faces become the collider"),
    "navmesh": Input("navmesh", help="navmesh artifact (navmesh.json): floor height, agent, guide mesh"),
    "trajectory": Input("trajectory", help="trajectory artifact (trajectory.json): the animated camera(s)"),
    "register": Input("register", optional=True, help="register artifact: a home's capture points become spawn points"),
}


@dataclass(kw_only=True)
class Params:
    collider_max_triangles: int = param(100_000, ge=0)
    """Triangle budget of the collision mesh (quadric decimation of the mesh's valid faces, welded; 0 = keep them all;
    the NavMesh's floor triangles, added so that the assumed-walkable blind spot under the rig is solid, come on top).
    The budget grows while the decimated surface strays farther than collider_max_error_m: 100k suits one panorama and
    a home's fused mesh alike; a real LiDAR capture's noisy, holed mesh keeps more (README, Using the scene in a
    simulator)."""
    collider_max_error_m: float = param(0.05, ge=0)
    """How far (m) the decimated collider may stray from the mesh beyond the mesh's own noise (99th percentiles of the
    distance to the plane of the mesh's nearest vertex, asset.collider.surface_error): farther, and the mesh is
    decimated again with a quarter more faces than a stalled decimation kept (else twice the budget), up to keeping
    every face. A decimation asked for fewer faces than it can reach stalls and collapses whole corners of a room
    into the free space agents walk. 0 = the budget alone."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    try:
        import fast_simplification  # noqa: F401
        import pxr  # noqa: F401  (usd-core)
    except ImportError as e:
        raise StageInputError(f"the asset stage needs the sim extra ({e.name} is missing): "
                              "pip install -e '.[sim]'") from None
    from panoworld.asset import build_asset
    from panoworld.geometry.erp_mesh import load_erp_mesh
    from panoworld.geometry.navmesh import load_navmesh
    from panoworld.io.home import capture_poses
    from panoworld.io.splat_ply import read_gaussians_ply

    t_read = time.perf_counter()
    mesh_path = Path(inputs["mesh"]) / "mesh.ply"
    try:
        mesh = load_erp_mesh(inputs["mesh"])
    except Exception as e:  # plyfile raises many types on corrupt files
        raise StageInputError(f"{mesh_path}: unreadable mesh ({type(e).__name__}: {e}); rerun the mesh stage") from None
    try:
        nav = load_navmesh(inputs["navmesh"])
    except ValueError as e:
        raise StageInputError(f"{e}; rerun the navmesh stage") from None
    try:
        gaussians = read_gaussians_ply(Path(inputs["gaussians"]) / "gaussians.ply")
    except ValueError as e:
        raise StageInputError(f"{e}; rerun the gaussians stage") from None
    captures = capture_poses(inputs.get("register"))  # InputError naming panoramas.json when unreadable
    t0 = time.perf_counter()
    info = build_asset(out_dir, mesh=mesh, nav=nav, trajectory_dir=Path(inputs["trajectory"]), gaussians=gaussians,
                       max_triangles=params.collider_max_triangles, max_error_m=params.collider_max_error_m,
                       captures=captures)
    info["read_s"] = t0 - t_read
    if info["compliance_errors"]:
        raise ArtifactError(f"{out_dir}/scene.usdc fails usd-core validation: {'; '.join(info['compliance_errors'])}")
    return info


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
