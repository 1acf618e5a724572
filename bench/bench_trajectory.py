"""Benchmark of NavMesh + trajectory planning against synthetic ground truth: clearance, containment, steps, closure, coverage, timings."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.core.conventions import invert_pose, transform_points
from panoworld.core.errors import NoFloorError
from panoworld.geometry.erp_mesh import erp_mesh_from_depth
from panoworld.navmesh import NavMeshParams, build_navmesh
from panoworld.tools.synth import generate_scene
from panoworld.trajectory import (
    PathKind,
    TrajectoryParams,
    clearance_cap,
    mesh_clearance,
    plan_path,
    poses_from_positions,
    sector_coverage,
    sector_reach,
    step_lengths,
)


def synth_case(seed: int, preset: str, height: int):
    """(ERP mesh of the GT depth at the panorama pose, GT vertices and faces in the canonical frame)."""
    scene = generate_scene(seed, preset)
    world_from_canonical = scene.world_from_canonical
    depth = scene.raycaster.render_erp(world_from_canonical, height, 2 * height).distance.astype(np.float32)
    mesh = erp_mesh_from_depth(depth, np.zeros(depth.shape + (3,), np.uint8))
    gt_vertices = transform_points(invert_pose(world_from_canonical), scene.vertices.astype(np.float64))
    return mesh, gt_vertices, scene.faces


def evaluate(nav, gt_vertices, gt_faces, params: TrajectoryParams, min_dist: float) -> dict:
    """Plan one path and measure it against the ground-truth mesh."""
    t = time.perf_counter()
    plan = plan_path(nav, params)
    plan_s = time.perf_counter() - t
    poses = poses_from_positions(plan.positions)
    steps = step_lengths(poses)
    clearance = mesh_clearance(gt_vertices, gt_faces, poses[:, :3, 3])
    _, reach = sector_reach(nav, np.zeros(2), 8)
    return {
        "plan_s": plan_s,
        "min_clearance": float(clearance.min()),
        "inside": bool(nav.contains(plan.positions).all()),
        "step_cv": float(steps.std() / steps.mean()),
        "step_m": plan.step_m,
        "closure_m": float(np.linalg.norm(plan.positions[-1] - plan.positions[0])),
        "closure_ok": bool(np.linalg.norm(plan.positions[-1] - plan.positions[0]) <= steps.max() + 1e-9),
        "covered": int(sector_coverage(plan.positions, np.zeros(2), 8, min_dist).sum()),
        "reachable": int((reach >= min_dist).sum()),
        "adapted": bool(plan.info.get("step_adapted")),
        "laps": int(plan.info.get("ring_laps", 0)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--preset", default="default", help="synth preset (default | ci-tiny)")
    ap.add_argument("--height", type=int, default=256, help="ERP height of the GT depth the NavMesh is built from")
    ap.add_argument("--strides", default="1,2,4")
    ap.add_argument("--min-dist", type=float, default=0.1, help="a sector counts as covered beyond this distance")
    ap.add_argument("--timing-height", type=int, default=720, help="ERP height of the full-size timing runs (0 = skip)")
    ap.add_argument("--timing-seeds", type=int, default=3)
    args = ap.parse_args(argv)
    strides = [int(s) for s in args.strides.split(",")]
    radius = NavMeshParams().agent_radius_m
    rows, nav_times, failures = [], [], []
    print(f"{'seed':>4} {'kind':>6} {'r':>2} {'min_clear':>9} {'inside':>6} {'step_cv':>7} {'step_m':>6} "
          f"{'close':>6} {'cov':>5} {'adapt':>5} {'laps':>4} {'plan_s':>6}")
    for seed in range(args.seeds):
        mesh, gt_v, gt_f = synth_case(seed, args.preset, args.height)
        t = time.perf_counter()
        try:
            nav = build_navmesh(mesh.vertices, mesh.faces, mesh.face_valid)
        except NoFloorError as e:
            failures.append(f"seed {seed}: {e}")
            continue
        nav_times.append(time.perf_counter() - t)
        for kind in PathKind:
            for stride in strides:
                try:
                    r = evaluate(nav, gt_v, gt_f, TrajectoryParams(kind=kind, stride=stride), args.min_dist)
                except ValueError as e:
                    failures.append(f"seed {seed} {kind} stride {stride}: {e}")
                    continue
                r.update(seed=seed, kind=str(kind), stride=stride)
                rows.append(r)
                print(f"{seed:>4} {kind:>6} {stride:>2} {r['min_clearance']:9.3f} {r['inside']!s:>6} {r['step_cv']:7.4f} "
                      f"{r['step_m']:6.3f} {r['closure_m']:6.3f} {r['covered']:>2}/{r['reachable']:<2} "
                      f"{r['adapted']!s:>5} {r['laps']:>4} {r['plan_s']:6.3f}", flush=True)
    print()
    print(f"NavMesh build (ERP {args.height}x{2 * args.height}, {len(nav_times)} scenes): "
          f"median {np.median(nav_times):.3f} s, max {np.max(nav_times):.3f} s")
    for kind in PathKind:
        rs = [r for r in rows if r["kind"] == kind]
        ok_clear = sum(r["min_clearance"] >= radius for r in rs)
        ok_in = sum(r["inside"] for r in rs)
        ok_cv = sum(r["step_cv"] <= 0.1 for r in rs)
        line = (f"{kind}: {len(rs)} paths; clearance >= {radius} m: {ok_clear}/{len(rs)} (worst {min(r['min_clearance'] for r in rs):.3f} m); "
                f"inside NavMesh: {ok_in}/{len(rs)}; step CV <= 0.1: {ok_cv}/{len(rs)} (worst {max(r['step_cv'] for r in rs):.4f}); "
                f"step adapted (room too small): {sum(r['adapted'] for r in rs)}")
        if kind == PathKind.RING:
            line += f"; closed within one step: {sum(r['closure_ok'] for r in rs)}/{len(rs)}"
            line += f"; laps 1/2/3/4: {'/'.join(str(sum(r['laps'] == k for r in rs)) for k in (1, 2, 3, 4))}"
        else:
            ok_cov = sum(r["covered"] >= min(6, r["reachable"]) for r in rs)
            line += f"; >= min(6, reachable) of 8 sectors: {ok_cov}/{len(rs)}"
        line += f"; plan median {np.median([r['plan_s'] for r in rs]):.3f} s"
        print(line)
    if args.timing_height:
        timing(args.preset, args.timing_height, args.timing_seeds, radius)
    for f in failures:
        print("FAILED", f)
    return 1 if failures else 0


def timing(preset: str, height: int, n_seeds: int, radius: float) -> None:
    """NavMesh build from a full-size ERP mesh and the trajectory stage's clearance check against it."""
    print(f"\nFull size: ERP {height}x{2 * height} mesh (stage defaults: re-meshed to <= 192 rows for the NavMesh)")
    for seed in range(n_seeds):
        mesh, _, _ = synth_case(seed, preset, height)
        t = time.perf_counter()
        nav = build_navmesh(mesh.vertices, mesh.faces, mesh.face_valid)
        total = time.perf_counter() - t
        steps = {k: round(v, 3) for k, v in nav.info["timings_s"].items() if k != "total_s"}
        poses = poses_from_positions(plan_path(nav, TrajectoryParams(stride=4)).positions)
        t = time.perf_counter()
        mesh_clearance(mesh.vertices, mesh.faces[mesh.face_valid], poses[:, :3, 3], clearance_cap(radius))
        check = time.perf_counter() - t
        print(f"seed {seed}: {len(mesh.faces)} faces, downsample {nav.info['erp_downsample']}: NavMesh {total:.3f} s {steps}; "
              f"clearance of 81 poses vs full mesh {check:.3f} s")


if __name__ == "__main__":
    sys.exit(main())
