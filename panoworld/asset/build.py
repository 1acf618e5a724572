"""Assemble the simulation asset from the stage artifacts: scene.usdc, collider.obj, asset.json in the asset frame."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from panoworld.asset.collider import Collider, collision_mesh, write_obj
from panoworld.core.conventions import asset_from_canonical, transform_points
from panoworld.core.errors import ArtifactError
from panoworld.geometry.erp_mesh import ErpMesh
from panoworld.geometry.navmesh import HOME_SNAP_M, NavMesh
from panoworld.io.gaussian_set import Gaussians
from panoworld.io.jsonio import read_json, write_json
from panoworld.io.trajectory import load_trajectory, path_indices, read_trajectory_doc

SCENE_USD = "scene.usdc"
COLLIDER_OBJ = "collider.obj"
ASSET_JSON = "asset.json"
FLOOR_PATCH_BELOW_M = 0.01
"""The NavMesh floor joins the collider this far below the floor height: coplanar duplicates of the seen floor would
make resting contacts jitter."""


def write_asset_doc(out_dir: Path, doc: dict) -> Path:
    """asset.json of an asset artifact (frame, spawn, collider, agent, counts; artifacts_schema/asset.schema.json)."""
    return write_json(Path(out_dir) / ASSET_JSON, doc)


def read_asset_doc(asset_dir: Path) -> dict:
    """asset.json of an asset artifact directory; ArtifactError naming the file when it is missing or unreadable."""
    path = Path(asset_dir) / ASSET_JSON
    try:
        doc = read_json(path)
    except (OSError, ValueError) as e:
        raise ArtifactError(f"{path}: unreadable ({e}); rerun the asset stage") from None
    if not isinstance(doc, dict) or "asset_from_canonical" not in doc:
        raise ArtifactError(f"{path}: not an asset document (no asset_from_canonical); rerun the asset stage")
    return doc


def trajectory_paths(trajectory_dir: Path) -> tuple[list[np.ndarray], float]:
    """The planned camera paths (world_from_cam, canonical) and their frame rate: the artifact's `poses`, or each of
    its `paths` (pose ranges [start, stop) with their predecessor `from`, see trajectory.path_indices) when it holds
    several."""
    path = Path(trajectory_dir)
    doc = read_trajectory_doc(path)
    fps = float(doc.get("fps", 16.0))
    poses = load_trajectory(path)
    if isinstance(doc.get("paths"), list) and doc["paths"]:
        return [poses[path_indices(p)] for p in doc["paths"]], fps
    return [poses], fps


def with_walkable_floor(col: Collider, nav: NavMesh) -> Collider:
    """The collider plus the NavMesh's triangles at floor height: where the NavMesh lets the agent walk, the floor is
    solid, also where the mesh has no floor (the capture rig's blind spot under the camera, small depth dropouts)."""
    nav_v, nav_f = nav.mesh3d()
    nav_v[:, 1] += FLOOR_PATCH_BELOW_M  # y is down: just below the seen floor, so it only catches what falls through
    v = np.concatenate([col.vertices, nav_v])
    f = np.concatenate([col.faces, nav_f + len(col.vertices)])  # both face up (-Y), towards the camera
    info = {**col.info, "faces_decimated": col.info["faces_out"], "walkable_floor_triangles": int(len(nav_f)),
            "faces_out": int(len(f))}
    return Collider(v, f, info)


def spawn_point(collider_canonical: Collider, nav: NavMesh) -> tuple[np.ndarray, str, float]:
    """The agent's spawn for the capture point at the origin (canonical frame): agent_spawns of the camera centre."""
    return agent_spawns(collider_canonical, nav, np.zeros((1, 3)))[0]


def agent_spawns(collider_canonical: Collider, nav: NavMesh, cameras: np.ndarray,
                 below: list[tuple[np.ndarray, str]] | None = None) -> list[tuple[np.ndarray, str, float]]:
    """Where an agent of the NavMesh's radius stands for each camera centre (K, 3) (canonical frame): the floor below
    the camera (floors_below; below: those already at hand) where the camera stands over the NavMesh, else the floor
    below the NavMesh's nearest point within HOME_SNAP_M (a camera nearer a wall than the agent's radius: an agent
    below it would stand in the wall); farther than that, the floor below the camera. Each as (point (3,), its floor's
    source, how far it lies from the floor below the camera, m)."""
    cameras = np.asarray(cameras, np.float64).reshape(-1, 3)
    xz = cameras[:, [0, 2]]
    near = nav.closest_point(xz) if len(nav.triangles) else xz
    moved = np.linalg.norm(near - xz, axis=1)
    onto = (moved > 0) & (moved <= HOME_SNAP_M)
    out = [(p, source, 0.0) for p, source in (below or floors_below(collider_canonical, nav.floor_y, cameras))]
    if onto.any():
        at = cameras[onto].copy()
        at[:, 0], at[:, 2] = near[onto, 0], near[onto, 1]
        for k, (p, source) in zip(np.flatnonzero(onto), floors_below(collider_canonical, nav.floor_y, at)):
            out[k] = (p, source, float(moved[k]))
    return out


def floors_below(collider_canonical: Collider, floor_y: float, cameras: np.ndarray) -> list[tuple[np.ndarray, str]]:
    """The floor below each camera centre (K, 3) (canonical frame): the collider straight below it, or the NavMesh
    floor height (y = floor_y) where the collider is not within 1 m of it there; with its source."""
    from panoworld.geometry.raycast import Raycaster

    cameras = np.asarray(cameras, np.float64).reshape(-1, 3)
    hits = Raycaster(collider_canonical.vertices, collider_canonical.faces).cast(
        cameras.astype(np.float32), np.tile(np.array([[0.0, 1.0, 0.0]], np.float32), (len(cameras), 1)))
    out = []
    for c, d in zip(cameras, np.asarray(hits.distance, np.float64)):
        if np.isfinite(d) and abs(c[1] + d - floor_y) < 1.0:
            out.append((np.array([c[0], c[1] + d, c[2]]), "collider"))
        else:
            out.append((np.array([c[0], float(floor_y), c[2]]), "navmesh floor"))
    return out


def capture_spawns(col: Collider, nav: NavMesh, captures: dict[str, np.ndarray], a_from_c: np.ndarray) -> dict:
    """A home's capture points in the asset frame: {NAME: {"floor": the floor below the camera, "spawn": where the agent
    stands (agent_spawns: that floor, or the nearest NavMesh floor where the camera stood nearer a wall than the
    agent's radius), "spawn_from_floor_m": how far apart they are, "camera": the camera centre, "yaw_deg": where the
    panorama's centre looks (about +z, from +x), "floor_source": collider | navmesh floor}} (captures: {NAME:
    world_from_cam (4, 4) canonical})."""
    names = list(captures)
    cams = np.array([np.asarray(captures[n], np.float64)[:3, 3] for n in names]).reshape(-1, 3)

    def asset(p):
        return [round(float(x), 6) for x in transform_points(a_from_c, np.asarray(p)[None])[0]]

    below = floors_below(col, nav.floor_y, cams)
    out = {}
    for n, c, (floor, source), (spawn, _, moved) in zip(names, cams, below, agent_spawns(col, nav, cams, below)):
        fwd = a_from_c[:3, :3] @ np.asarray(captures[n], np.float64)[:3, 2]
        out[n] = {"floor": asset(floor), "spawn": asset(spawn), "spawn_from_floor_m": round(moved, 4),
                  "camera": asset(c), "yaw_deg": round(float(np.degrees(np.arctan2(fwd[1], fwd[0]))), 4),
                  "floor_source": source}
    return out


def build_asset(out_dir: Path, *, mesh: ErpMesh, nav: NavMesh, trajectory_dir: Path, gaussians: Gaussians,
                max_triangles: int, max_error_m: float = 0.0, captures: dict[str, np.ndarray] | None = None) -> dict:
    """Write scene.usdc, collider.obj and asset.json into out_dir; returns the manifest facts. The collider:
    collision_mesh(mesh, max_triangles, max_error_m) and the NavMesh's floor. captures: a home's capture points
    {NAME: world_from_cam (4, 4) canonical}, each given a spawn on the floor below it (two or more)."""
    from panoworld.asset.usd import UP_AXIS, SceneParts, compliance_errors, write_scene_usd

    out_dir = Path(out_dir)
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    col = with_walkable_floor(collision_mesh(mesh, max_triangles, max_error_m), nav)
    timings["collider"] = time.perf_counter() - t0
    t = time.perf_counter()
    spawn_c, spawn_source, spawn_moved = spawn_point(col, nav)
    a_from_c = asset_from_canonical(nav.floor_y)
    spawn = transform_points(a_from_c, spawn_c[None])[0]
    points = capture_spawns(col, nav, captures, a_from_c) if captures and len(captures) >= 2 else {}
    col_v = transform_points(a_from_c, col.vertices)
    write_obj(out_dir / COLLIDER_OBJ, col_v, col.faces,
              "PanoWorld collider: asset frame (z up, x forward, y left, floor below the capture at z = 0), metres")
    nav_v, nav_f = nav.mesh3d()
    paths, fps = trajectory_paths(trajectory_dir)
    timings["collider_io"] = time.perf_counter() - t
    t = time.perf_counter()
    parts = SceneParts(asset_from_canonical=a_from_c, gaussians=gaussians, collider=(col_v, col.faces),
                       navmesh=(transform_points(a_from_c, nav_v), nav_f), spawn=spawn, camera_paths=paths, fps=fps,
                       capture_points=points)
    counts = write_scene_usd(out_dir / SCENE_USD, parts)
    timings["write_usd"] = time.perf_counter() - t
    t = time.perf_counter()
    problems = compliance_errors(out_dir / SCENE_USD)
    timings["compliance"] = time.perf_counter() - t
    doc = {
        "up_axis": UP_AXIS,
        "meters_per_unit": 1.0,
        "asset_from_canonical": a_from_c.tolist(),
        "spawn": [float(x) for x in spawn],
        "spawn_from_capture_m": round(spawn_moved, 4),
        "collider": COLLIDER_OBJ,
        "scene": SCENE_USD,
        "frame": "x forward (the panorama's centre column), y left, z up (REP 103); origin on the floor below the "
                 "capture point; gravity -9.81 m/s^2 along -z",
        "agent": dict(nav.agent),
        **({"capture_points": points} if points else {}),
        "counts": {"particles": counts["particles"], "collider_triangles": counts["collider_triangles"],
                   "collider_vertices": int(len(col_v)), "navmesh_triangles": counts["navmesh_triangles"],
                   "cameras": counts["cameras"], "frames": counts["frames"]},
    }
    write_asset_doc(out_dir, doc)
    sizes = {n: (out_dir / n).stat().st_size for n in (SCENE_USD, COLLIDER_OBJ, ASSET_JSON)}
    return {
        **doc["counts"],
        "sh_degree": counts["sh_degree"],
        "spawn": doc["spawn"],
        "spawn_source": spawn_source,
        "spawn_from_capture_m": doc["spawn_from_capture_m"],
        "capture_points": len(points),
        "up_axis": UP_AXIS,
        "collider": col.info,
        "compliance_errors": problems,
        "sizes_mb": {n: s / 1e6 for n, s in sizes.items()},
        "timings_s": timings,
        "export_s": time.perf_counter() - t0,
    }
