"""Walkable floor of the scene mesh as a NavMesh: navmesh.json (polygons, triangles, adjacency), navmesh.obj, navmesh.glb."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.geometry.erp_mesh import load_erp_mesh
from panoworld.geometry.navmesh import HOME_SNAP_M
from panoworld.io.home import capture_poses
from panoworld.navmesh import NavMeshParams
from panoworld.navmesh.home import home_navmesh
from panoworld.navmesh.no_room import build_navmesh_with_room

NAME = "navmesh"
VERSION = "4"
ARTIFACT = "navmesh"
INPUTS = {
    "mesh": Input("mesh", help="mesh artifact (mesh.ply, canonical frame, face property valid)"),
    "register": Input("register", optional=True, help="register artifact: a home's NavMesh spans every capture point"),
}


@dataclass(kw_only=True)
class Params(NavMeshParams):
    glb: bool = True
    """Also write navmesh.glb (glTF, Y up) for glTF viewers."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    path = Path(inputs["mesh"]) / "mesh.ply"
    try:
        mesh = load_erp_mesh(inputs["mesh"])
    except Exception as e:  # plyfile raises many types on corrupt files
        raise StageInputError(f"{path}: unreadable mesh ({type(e).__name__}: {e}); rerun the mesh stage") from None
    t0 = time.perf_counter()
    captures = capture_poses(inputs.get("register"))
    on_navmesh = home = None
    if len(captures) >= 2:  # a home: the floor component of every capture point, across rooms and doorways
        nav, on_navmesh = home_navmesh(mesh, captures, params)
        home = nav.info["home"]
        if len(home["components"]) > 1:
            groups = "; ".join(", ".join(c["capture_points"]) or "none" for c in home["components"])
            print(f"the home's floor is {len(home['components'])} NavMesh components that do not connect "
                  f"(capture points: {groups}); the trajectory cuts between them", flush=True)
        off = [n for n, ok in on_navmesh.items() if not ok]
        if off:
            print(f"capture points off the NavMesh (its nearest floor within {HOME_SNAP_M} m, or none): {off}", flush=True)
    else:
        nav = build_navmesh_with_room(mesh.vertices, mesh.faces, mesh.face_valid, params)  # no room: smaller agent / stationary
    no_room = nav.info.get("no_room")
    if no_room:
        print(f"no room to move: {no_room['reason']}; decided: {no_room['decision']} (agent radius "
              f"{no_room['agent_radius_m']} m)", flush=True)
    build_s = time.perf_counter() - t0
    files = nav.save(out_dir, glb=params.glb)
    return {
        "floor_y": nav.floor_y,
        "camera_height_m": nav.info["camera_height_m"],
        "area_m2": nav.area,
        "num_triangles": len(nav.triangles),
        "num_holes": sum(len(p["holes"]) for p in nav.polygons()),
        "assumed_walkable": nav.info["assumed_walkable"],
        "camera_on_navmesh": nav.info["camera_on_navmesh"],
        "agent_radius_m": nav.agent["agent_radius_m"],
        "no_room": no_room,
        "camera_distance_to_navmesh_m": nav.info["camera_distance_to_navmesh_m"],
        "erp_downsample": nav.info["erp_downsample"],
        "faces_used": nav.info["faces_used"],
        "build_s": build_s,
        "timings_s": nav.info["timings_s"],
        "files": files,
        **({"capture_points_on_navmesh": on_navmesh, "capture_components": home["capture_components"],
            "components": home["components"]} if home is not None else {}),
    }


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
