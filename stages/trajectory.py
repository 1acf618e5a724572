"""Collision-free SE(3) camera trajectory on the NavMesh (explore, sector or ring; or a user file): trajectory.json + .tum."""

from __future__ import annotations

import enum
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.core.conventions import invert_pose
from panoworld.core.errors import PanoWorldError
from panoworld.core.params import param
from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.geometry.erp_mesh import load_erp_mesh
from panoworld.geometry.navmesh import HOME_SNAP_M, load_navmesh
from panoworld.io.home import capture_poses
from panoworld.io.trajectory import TrajectoryFileError, path_indices, read_trajectory_file, write_trajectory
from panoworld.trajectory import (
    MIN_SECTOR_DIST_M,
    PathKind,
    TrajectoryParams,
    YawMode,
    clearance_cap,
    format_issues,
    mesh_clearance,
    path_yaw,
    plan_path,
    planning_hub,
    poses_from_positions,
    sector_coverage,
    sector_reachability,
    step_lengths,
    validate_poses,
)
from panoworld.trajectory.stationary import stationary_plan

NAME = "trajectory"
VERSION = "4"
ARTIFACT = "trajectory"
INPUTS = {
    "navmesh": Input("navmesh", help="navmesh artifact (navmesh.json)"),
    "mesh": Input("mesh", help="mesh artifact (mesh.ply): poses are checked for clearance against it"),
    "user_trajectory": Input(
        "file", optional=True,
        help="user poses instead of planning: JSON {\"poses\": [4x4 world_from_cam, ...]} or a list, or TUM text "
        "'t tx ty tz qx qy qz qw'; canonical frame (pose 0 = identity = the panorama camera)",
    ),
    "register": Input("register", optional=True, help="register artifact: a home's trajectory visits every capture point"),
}


class OnInvalid(enum.StrEnum):
    ERROR = "error"
    """Fail (exit code 2) naming every pose that collides or leaves the walkable area."""
    REPORT = "report"
    """Write the trajectory anyway and list the invalid poses under info.invalid_poses."""


@dataclass(kw_only=True)
class Params(TrajectoryParams):
    on_invalid: OnInvalid = OnInvalid.ERROR
    """What to do with poses closer than the agent radius to the mesh or outside the NavMesh (pose 0 is exempt)."""
    fps: float = param(16.0, gt=0)
    """Frame rate for the TUM timestamps (t = i / fps)."""
    reanchor: bool = False
    """Re-express a user trajectory whose pose 0 is not the identity relative to pose 0 (else that is an error)."""
    home_frames: int = param(41, ge=2)
    """A home (several capture points): frames per capture point; its explore paths and the walk to the next capture
    point share them (panoworld/trajectory/home.py)."""


def _user_poses(path: Path, params: Params) -> np.ndarray:
    try:
        poses = read_trajectory_file(path)
    except TrajectoryFileError as e:
        raise StageInputError(f"{e}; see docs for the JSON/TUM trajectory formats") from None
    dt = float(np.linalg.norm(poses[0, :3, 3]))
    dr = float(np.abs(poses[0, :3, :3] - np.eye(3)).max())
    if dt > 1e-3 or dr > 1e-3:
        if not params.reanchor:
            raise StageInputError(
                f"{path}: pose 0 is not the identity (|t| = {dt:.4f} m, max |R - I| = {dr:.4f}) but poses must be in the "
                "canonical frame of the panorama camera; pass --reanchor true to express them relative to pose 0"
            )
        poses = invert_pose(poses[0]) @ poses
    poses[0] = np.eye(4)
    return poses


def _plan_or_stay(nav, params: Params, where: Path):
    """plan_path, or a stationary rotation-only path when the NavMesh records no room to move."""
    no_room = nav.info.get("no_room")
    if no_room and no_room.get("decision") == "stationary":
        return stationary_plan(params, no_room["reason"])
    try:
        return plan_path(nav, params)
    except ValueError as e:
        if no_room:
            return stationary_plan(params, f"{no_room['reason']}; with a smaller agent still: {e}")
        raise PanoWorldError(f"no path planned on the NavMesh of {where.parent} ({e}); the planner failed (exit 1), "
                             "not an input") from None


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    try:
        nav = load_navmesh(inputs["navmesh"])
    except ValueError as e:
        raise StageInputError(f"{e}; rerun the navmesh stage") from None
    mesh_path = Path(inputs["mesh"]) / "mesh.ply"
    try:
        mesh = load_erp_mesh(inputs["mesh"])
    except Exception as e:  # plyfile raises many types on corrupt files
        raise StageInputError(f"{mesh_path}: unreadable mesh ({type(e).__name__}: {e}); rerun the mesh stage") from None
    radius = float(nav.agent["agent_radius_m"])
    t0 = time.perf_counter()
    user = inputs.get("user_trajectory")
    meta: dict = {}
    skip: tuple[int, ...] = (0,)
    if user is not None:
        poses = _user_poses(Path(user), params)
        source = f"user: {Path(user).name}"
        kind, stride, step_m = "user", None, float(np.median(step_lengths(poses))) if len(poses) > 1 else 0.0
    elif len(captures := capture_poses(inputs.get("register"))) >= 2:
        from panoworld.trajectory.home import plan_home

        plan = plan_home(nav, captures, params, params.home_frames * len(captures))
        yaw = None if params.yaw == YawMode.FIXED else path_yaw(plan.positions, plan.info["paths"], closed=False)
        poses = poses_from_positions(plan.positions, yaw)
        poses[:, 1, 3] = plan.info.pop("camera_y")
        source, kind, stride, step_m = "planned", "home", None, plan.step_m
        meta = plan.info
        if meta["cuts"]:
            print(f"no walk joins these capture points (floors that do not connect on the NavMesh): "
                  f"{', '.join(' -> '.join(c) for c in meta['cuts'])}; each starts new paths", flush=True)
        if meta["unreached_captures"]:
            print(f"capture points with no NavMesh floor within {HOME_SNAP_M} m (their capture frame only): "
                  f"{meta['unreached_captures']}", flush=True)
        skip = tuple(plan.exempt)
    else:
        plan = _plan_or_stay(nav, params, Path(inputs["navmesh"]) / "navmesh.json")
        paths = plan.info.get("paths") or [{"start": 0, "stop": len(plan.positions)}]
        yaw = None if params.yaw == YawMode.FIXED else path_yaw(plan.positions, paths, closed=params.kind == PathKind.RING)
        if plan.info.get("rotation_only"):
            yaw = np.asarray(plan.info.pop("yaw_rad"))
        poses = poses_from_positions(plan.positions, yaw)
        source = "planned"
        kind, stride, step_m = str(params.kind), params.stride, plan.step_m
        meta = plan.info
        skip = tuple(plan.exempt)
    plan_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    cap = clearance_cap(radius)
    clearance = mesh_clearance(mesh.vertices, mesh.faces[mesh.face_valid], poses[:, :3, 3], cap)
    issues = validate_poses(poses, nav, clearance, agent_radius=radius, skip=skip)
    check_s = time.perf_counter() - t1
    where = Path(user) if user is not None else Path(inputs["navmesh"]) / "navmesh.json"
    if issues and params.on_invalid == OnInvalid.ERROR:
        hint = "move those poses" if user is not None else "the NavMesh disagrees with the mesh; rebuild the navmesh"
        raise StageInputError(f"{where}: {format_issues(issues, len(poses))}; {hint} or pass --on-invalid report")
    paths = meta.get("paths")
    steps = np.concatenate([step_lengths(poses[path_indices(p)]) for p in paths]) if paths else step_lengths(poses)
    xz = poses[:, [0, 2], 3]
    if "sectors_reachable" in meta:
        reachable = int(meta["sectors_reachable"])
    else:  # ring and user paths: the same measure with their own length as the budget
        hub, _ = planning_hub(nav, np.zeros(2))
        reachable = int(sector_reachability(nav, np.zeros(2), hub, params.sectors, float(steps.sum()))["reachable"].sum())
    info = {
        "source": source,
        "kind": kind,
        "frames": len(poses),
        "stride": stride,
        "step_m": step_m,
        "length_m": float(steps.sum()),
        "paths": len(paths) if paths else 1,
        "max_reach_m": float(np.linalg.norm(xz, axis=1).max()),
        "step_cv": float(steps.std() / steps.mean()) if len(steps) and steps.mean() > 0 else 0.0,
        "closure_m": float(np.linalg.norm(xz[-1] - xz[0])),
        "sectors": params.sectors,
        "sectors_covered": int(sector_coverage(xz, np.zeros(2), params.sectors, MIN_SECTOR_DIST_M).sum()),
        "sectors_reachable": reachable,
        "start_off_navmesh_m": float(meta.get("start_off_navmesh_m", 0.0)),
        "no_room": (nav.info.get("no_room") or {}).get("reason"),
        "rotation_only": bool(meta.get("rotation_only", False)),
        "min_clearance_m": float(clearance.min()),
        "clearance_cap_m": cap,
        "agent_radius_m": radius,
        "invalid_poses": [{"index": it.index, "reasons": it.reasons} for it in issues],
        "exempt_poses": list(skip),
        "exempt_min_clearance_m": float(clearance[list(skip[1:])].min()) if len(skip) > 1 else None,
        "plan": meta,
        "plan_s": plan_s,
        "check_s": check_s,
    }
    write_trajectory(
        out_dir, poses, clearance, fps=params.fps, kind=kind, stride=stride, step_m=step_m, source=source,
        yaw=str(params.yaw) if user is None else None, agent_radius_m=radius, clearance_cap_m=cap,
        floor_y=nav.floor_y, camera_height_m=nav.floor_y, invalid_poses=info["invalid_poses"],
        **({"paths": paths} if paths else {}),
    )
    return info


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
