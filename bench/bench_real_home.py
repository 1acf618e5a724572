"""A real home captured as several panoramas, run as a user would (no flags), measured against its survey.

    python bench/bench_real_home.py SCENE --survey survey.json [--json F] [--work DIR] [--survey-poses | --split]
                                    [--loo | --loo-only NAME ...] [--loo-build captures|full] [--height 256]

SCENE is a home (docs/multi.md: panoramas/, depths/); it is copied to --work (default
../scratch/bench_real_home/NAME) and `runner.py run` runs on the copy at the default preset with no flags and no
poses.json. Reported: registered count and each unregistered panorama's reason; pairwise capture-point distance
error and relative yaw error against the survey (compare_to_survey); the NavMesh (area, which capture points stand
on it, its connected components and the capture points of each; the trajectory's cuts between them), the nearest mesh vertex to
each capture point; the Gaussian scene rendered at each capture pose against that panorama as the pipeline cleaned it
(PSNR, SSIM, coverage = share of pixels with alpha > 0.5, at --height rows), and the PSNR against the input panorama,
whole and outside the removed rig (its mask grown by 2 px); per-stage wall seconds and peak memory from the runner's report.

--split (the user mode): where registration leaves groups unplaced, `runner.py split` makes each a home of its own
(into --work/user/split), each is built with no flags and measured as the home is (its registration against the survey
within the group, its capture poses), so every panorama is in some scene.

--survey-poses [--set STAGE.PARAM=VALUE ...] writes a poses.json built from the survey into the copy (survey_poses), so the stages after
registration can be measured while registration cannot join the rooms: its rows are labelled "survey poses", and
its registration numbers only check the poses went through. --set (that mode only, labelled) passes a runner
override, e.g. trajectory.on_invalid=report where rooms whose floors do not connect stop the trajectory.

--loo (every panorama) or --loo-only NAME...: leave-one-out novel views. The home is built again without that
panorama (its panorama, depth and pose removed) and rendered at the panorama's pose as registered with all of them
(the full run's, mapped into the reduced run's world frame through the common capture point nearest to it), against
the real panorama: PSNR, SSIM and coverage over the sphere and split into the pixels another panorama sees (seen:
the others' cleaned depth explains the left-out panorama's surface) and the rest (unseen).

--loo-build picks what "built without that panorama" means (the table header says which):
  captures (default, seconds each): the Gaussians of the other panoramas alone (gaussians.home.home_anchored_fusion
    with no frames, the stage's default settings), from the full run's depth artifact (each panorama's depth is
    cleaned on its own, so it does not depend on the left-out one) with the doorway lines through the other capture
    points dropped (drop_near_captures without the left-out one), at the full run's poses (no alignment needed). No
    generated frames: they come from walks through every capture point, so the full run's would show the left-out
    panorama; without them the unseen split's coverage is what the other captures cover.
  full (one whole home build each, ~8 min of CPU on east): `runner.py run` on a copy without the panorama, rendered
    at its pose mapped into that run's world frame through the common capture point nearest to it.

The survey (ZInD, zind_home/SOURCE.md) is read here only: never by the pipeline.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np
from real_home_scores import (  # bench/, beside this script
    home_sources,
    input_as_built,
    nearest_vertex_m,
    outside_rig,
    render_scores,
    seen_by_others,
    surface_masks,
)
from real_home_survey import compare_to_survey

from panoworld.io.manifest import read_manifest

# ---------------------------------------------------------------- survey


def survey_poses(survey: dict) -> dict[str, np.ndarray]:
    """{NAME: world_from_cam (4, 4)} from a ZInD survey (2D position m, yaw deg, camera height), in the frame of the
    first panorama (by name) as the pipeline's register stage puts it: up = -Y, metres.

    ZInD's pixel azimuth theta = atan2(-x, y) grows to the image's right, so its local floor-plan axes are a mirror
    image of the camera's (camera x right, z forward: local x = -x_cam, y = z_cam); the floor plan is mirrored back
    (gy -> -gy) to give proper rotations. Distances are unchanged by that mirror."""
    panos = survey["panos"]
    world = {}
    for n, p in panos.items():
        r = math.radians(p["yaw_deg"])
        c, s = math.cos(r), math.sin(r)
        x_cam = np.array([-c, s, 0.0])  # mirrored floor plan (gx, -gy), z up
        z_cam = np.array([-s, -c, 0.0])
        y_cam = np.array([0.0, 0.0, -1.0])
        T = np.eye(4)
        T[:3, :3] = np.stack([x_cam, y_cam, z_cam], axis=1)
        gx, gy = p["position_m_xy"]
        T[:3, 3] = [gx, -gy, p["camera_height_m"]]
        world[n] = T
    first = np.linalg.inv(world[sorted(world)[0]])
    return {n: first @ T for n, T in sorted(world.items())}


# ---------------------------------------------------------------- runs


def copy_home(src: Path, dst: Path, *, leave_out: str | None = None, poses: dict[str, np.ndarray] | None = None
              ) -> Path:
    """The home's panoramas/, depths/ and rig_masks/ copied to dst (without leave_out), plus poses.json when given."""
    if dst.exists():
        shutil.rmtree(dst)
    for sub in ("panoramas", "depths", "rig_masks"):
        if (src / sub).is_dir():
            (dst / sub).mkdir(parents=True)
            for f in sorted((src / sub).iterdir()):
                if f.stem != leave_out:
                    shutil.copy(f, dst / sub / f.name)
    if poses is not None:
        (dst / "poses.json").write_text(json.dumps({n: T.tolist() for n, T in poses.items() if n != leave_out}))
    return dst


def run_home(scene: Path, sets: list[str] = ()) -> dict:
    """`runner.py run SCENE --json` (default preset; no flags unless sets, --set STAGE.PARAM=VALUE each): wall
    seconds, the report's stages, the exit code."""
    t0 = time.perf_counter()
    cmd = [sys.executable, "runner.py", "run", str(scene), "--json"] + [a for v in sets for a in ("--set", v)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    try:
        stages = json.loads(proc.stdout)["stages"]
    except (ValueError, KeyError):
        stages = []
    return {"rc": proc.returncode, "wall_s": wall, "stages": stages, "stderr_tail": proc.stderr[-1500:]}


def manifest_info(scene: Path, stage: str) -> dict:
    try:
        return read_manifest(scene / "artifacts" / stage)["info"]
    except Exception:  # a stage that did not run
        return {}


def measure_home(scene: Path, survey: dict, height: int, sets: list[str] = ()) -> dict:
    from panoworld.io.home import RIG_MASK_PNG, capture_poses, home_depth_dirs
    from panoworld.io.splat_ply import read_gaussians_ply

    run = run_home(scene, sets)
    arts = scene / "artifacts"
    row: dict = {"scene": str(scene), "rc": run["rc"], "wall_s": run["wall_s"],
                 "stages": {s["stage"]: {"action": s.get("action"), "seconds": s.get("seconds"),
                                         "peak_rss_mb": s.get("peak_rss_mb"), "reason": (s.get("reason") or "")[:200]}
                            for s in run["stages"]}}
    for st in row["stages"]:
        row["stages"][st]["cpu_s"] = read_manifest(arts / st).get("cpu_s") if (arts / st / "manifest.json").is_file() \
            else None
    if run["rc"] != 0:
        row["stderr_tail"] = run["stderr_tail"]
    panos = sorted(p.stem for p in (scene / "panoramas").iterdir())
    poses = capture_poses(arts / "register") if (arts / "register" / "panoramas.json").is_file() else {}
    reg = manifest_info(scene, "register")
    regdoc = json.loads((arts / "register" / "registration.json").read_text()) \
        if (arts / "register" / "registration.json").is_file() else {}
    row["registered"] = sorted(poses)
    row["unregistered"] = {n: (regdoc.get("panoramas", {}).get(n, {}) or {}).get("reason", "?")
                           for n in panos if n not in poses}
    row["register_info"] = {k: v for k, v in reg.items() if not isinstance(v, (dict, list))}
    row["survey"] = compare_to_survey(poses, survey)
    nav = manifest_info(scene, "navmesh")
    row["navmesh"] = {"area_m2": nav.get("area_m2"), "on": nav.get("capture_points_on_navmesh"),
                      "components": nav.get("components")}
    if len(poses) == 1 and "camera_on_navmesh" in nav:  # one registered panorama: built as a single-panorama scene
        (only,) = poses
        row["navmesh"].update(on={only: bool(nav["camera_on_navmesh"])},
                              components=[{"area_m2": nav.get("area_m2"), "capture_points": [only]}])
    off = [n for n, ok in (row["navmesh"]["on"] or {}).items() if not ok and n in poses]
    if off and (arts / "navmesh").is_dir():  # how far beside it: within the agent's radius of a wall, or elsewhere
        from panoworld.geometry.navmesh import load_navmesh

        clearance = load_navmesh(arts / "navmesh").clearance(np.array([poses[n][[0, 2], 3] for n in off]))
        row["navmesh"]["off_by_m"] = {n: round(float(-c), 3) for n, c in zip(off, clearance)}
    traj = manifest_info(scene, "trajectory")
    plan = traj.get("plan") or {}
    row["trajectory"] = {"frames": traj.get("frames"), "invalid_poses": len(traj.get("invalid_poses") or []),
                         "cuts": plan.get("cuts"), "unreached": plan.get("unreached_captures")}
    depth = manifest_info(scene, "depth")
    row["plausibility"] = {n: (i.get("plausibility") or {}) for n, i in
                           (depth.get("home", {}).get("panoramas", {}) or {}).items()}
    if (arts / "mesh" / "mesh.ply").is_file() and poses:
        row["nearest_vertex_m"] = nearest_vertex_m(scene, poses)
    if (arts / "gaussians" / "gaussians.ply").is_file() and poses:
        g = read_gaussians_ply(arts / "gaussians" / "gaussians.ply")
        rgbs, _ = home_sources(scene, poses)

        row["capture"] = {}
        dirs = home_depth_dirs(arts / "depth")
        for n in poses:
            raw = input_as_built(scene, n)
            row["capture"][n] = {"cleaned": render_scores(g, poses[n], rgbs[n], height),
                                 "input": render_scores(g, poses[n], raw, height)}
            rig = outside_rig(dirs[n] / RIG_MASK_PNG, height)
            if rig is not None:
                row["capture"][n]["input_outside_rig"] = render_scores(g, poses[n], raw, height, seen=rig)["seen"]
        row["num_gaussians"] = manifest_info(scene, "gaussians").get("num_gaussians")
    return row


def loo_skip(full_poses: dict, name: str) -> str:
    """Why `name` gets no leave-one-out view ('' when it does): not registered in the full run, or registered alone."""
    if name not in full_poses:
        return "not registered in the full run"
    return "the only registered panorama: no other to build the home from" if len(full_poses) < 2 else ""


def leave_one_out_captures(full: Path, name: str, height: int) -> dict:
    """The other panoramas' Gaussians (--loo-build captures), rendered at `name`'s pose registered with all of them."""
    from panoworld.gaussians.backends.voxel_fusion import VoxelFusionOptions
    from panoworld.gaussians.home import home_anchored_fusion
    from panoworld.io.home import capture_poses

    full_poses = capture_poses(full / "artifacts" / "register")
    if (why := loo_skip(full_poses, name)):
        return {"name": name, "skipped": why}
    t0, c0 = time.perf_counter(), time.process_time()
    others = {n: T for n, T in full_poses.items() if n != name}
    _, depths = home_sources(full, others)
    rgbs, full_depths = home_sources(full, full_poses)
    g = home_anchored_fusion(None, {n: (rgbs[n], depths[n], others[n]) for n in depths}, VoxelFusionOptions()).gaussians
    seen = seen_by_others(name, full_poses, full_depths, height)
    out = {"name": name, "build": "captures", "registered": len(others), "num_gaussians": len(g)}
    out.update(render_scores(g, full_poses[name], rgbs[name], height, seen, surface_masks(full_depths[name], height)))
    out.update(wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0)
    return out


def leave_one_out(src: Path, work: Path, full: Path, name: str, survey_mode: dict | None, height: int,
                  sets: list[str] = ()) -> dict:
    """The home built without `name` (--loo-build full), rendered at its pose registered with all of them (the full
    run's)."""
    from panoworld.io.home import capture_poses
    from panoworld.io.splat_ply import read_gaussians_ply

    full_poses = capture_poses(full / "artifacts" / "register")
    if (why := loo_skip(full_poses, name)):
        return {"name": name, "skipped": why}
    scene = copy_home(src, work / f"loo_{name}", leave_out=name, poses=survey_mode)
    run = run_home(scene, sets)
    out: dict = {"name": name, "build": "full", "rc": run["rc"], "wall_s": run["wall_s"]}
    if run["rc"] != 0 or not (scene / "artifacts" / "gaussians" / "gaussians.ply").is_file():
        out["stderr_tail"] = run["stderr_tail"]
        return out
    loo_poses = capture_poses(scene / "artifacts" / "register")
    common = [n for n in loo_poses if n in full_poses]
    if not common:
        out["skipped"] = "no capture point in common with the full run"
        return out
    ref = min(common, key=lambda n: np.linalg.norm(full_poses[n][:3, 3] - full_poses[name][:3, 3]))
    loo_from_full = loo_poses[ref] @ np.linalg.inv(full_poses[ref])
    pose = loo_from_full @ full_poses[name]
    _, depths = home_sources(full, full_poses)
    seen = seen_by_others(name, full_poses, depths, height)
    g = read_gaussians_ply(scene / "artifacts" / "gaussians" / "gaussians.ply")
    raw = input_as_built(full, name)
    out.update(aligned_through=ref, registered=len(loo_poses),
               **render_scores(g, pose, raw, height, seen, surface_masks(depths[name], height)))
    return out


# ---------------------------------------------------------------- report


def _off(name: str, nav: dict) -> str:
    """A capture point off the NavMesh, with how far beside it it stands where measured."""
    d = (nav.get("off_by_m") or {}).get(name)
    return name if d is None else f"{name} {d:.2f} m beside it"


def fmt(v, spec=".2f"):
    return "-" if v is None else format(v, spec)


def measure_groups(full: Path, work: Path, survey: dict, height: int) -> list[dict]:
    """`runner.py split` on the full run's home (into work/split, made afresh), then each group built and measured: a
    home as measure_home does (registration against the survey, capture poses, stages); one panorama's scene run
    alone (exit code, wall seconds) and scored at its capture point."""
    out = work / "split"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    proc = subprocess.run([sys.executable, "runner.py", "split", str(full), "--out", str(out)], cwd=REPO,
                          capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"runner.py split failed: {proc.stderr.strip()}")
    listed = dict(re.split(r"\s{2,}", line.strip())[2:0:-1] for line in proc.stdout.splitlines()[1:] if line.strip())
    rows = []
    for d in sorted(out.iterdir()):
        if (d / "panoramas").is_dir():
            rows.append({"group": d.name, **measure_home(d, survey, height)})
        else:  # one panorama's scene (its name from split's table), scored at its capture point (the identity)
            run = run_home(d)
            name = listed.get(str(d), "?")
            rows.append({"group": d.name, "scene": str(d), "rc": run["rc"], "wall_s": run["wall_s"],
                         "registered": [name], "unregistered": {}})
            ply = d / "artifacts" / "gaussians" / "gaussians.ply"
            if ply.is_file():
                from panoworld.io.depth import load_depth_artifact
                from panoworld.io.splat_ply import read_gaussians_ply

                rgb = load_depth_artifact(d / "artifacts" / "depth")[2]
                rows[-1]["capture"] = {name: {"cleaned": render_scores(read_gaussians_ply(ply), np.eye(4), rgb, height)}}
        print(f"split: {d.name} built (rc {rows[-1]['rc']}, {rows[-1]['wall_s']:.0f} s)", file=sys.stderr, flush=True)
    return rows


def print_groups(groups: list[dict]) -> None:
    print("\nthe unplaced groups as homes of their own (`runner.py split`), each built with no flags:\n")
    print("| home | panoramas | registered | distance error m median / max | yaw error deg median / max | "
          "capture poses PSNR dB / SSIM | runner rc | wall s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for g in groups:
        sv = g.get("survey") or {}
        names = sorted(set(g["registered"]) | set(g["unregistered"]))
        err = (f"{sv['dist_err_m_median']:.3f} / {sv['dist_err_m_max']:.3f} | {sv['yaw_err_deg_median']:.2f} / "
               f"{sv['yaw_err_deg_max']:.2f}") if sv.get("pairs") else "- | -"
        cap = ", ".join(f"{n[-2:]} {c['cleaned']['psnr']:.2f} / {c['cleaned']['ssim']:.3f}"
                        for n, c in sorted((g.get("capture") or {}).items())) or "-"
        print(f"| {g['group']} | {', '.join(names)} | {len(g['registered'])} of {len(names)} | {err} | {cap} | "
              f"{g['rc']} | {g['wall_s']:.0f} |")


def print_report(res: dict) -> None:
    r = res["home"]
    label = "SURVEY POSES (poses.json from survey.json: downstream only)" if res["survey_poses"] else \
        "as a user runs it (no poses.json, no flags)"
    if res.get("sets"):
        label += ", with " + " ".join(f"--set {v}" for v in res["sets"])
    print(f"\n## {res['scene']}: {label}\n")
    sv = r["survey"]
    print(f"registered {len(r['registered'])} of {len(r['registered']) + len(r['unregistered'])}; runner rc "
          f"{r['rc']}, wall {r['wall_s']:.0f} s")
    for n, why in r["unregistered"].items():
        print(f"  unregistered {n}: {why}")
    if sv.get("pairs"):
        print(f"pairwise distance error median / max {sv['dist_err_m_median']:.3f} / {sv['dist_err_m_max']:.3f} m; "
              f"yaw error median / max {sv['yaw_err_deg_median']:.2f} / {sv['yaw_err_deg_max']:.2f} deg "
              f"({len(sv['pairs'])} pairs)")
    nav = r["navmesh"]
    on = nav.get("on") or {}
    comps = nav.get("components") or []
    print(f"NavMesh {fmt(nav.get('area_m2'), '.1f')} m^2 in {len(comps)} component(s); capture points on it: "
          f"{sum(bool(v) for v in on.values())} of {len(on)}"
          + (f" (off: {', '.join(_off(n, nav) for n, v in on.items() if not v)})" if on and not all(on.values()) else ""))
    for k, c in enumerate(comps):
        print(f"  component {k}: {fmt(c.get('area_m2'), '.1f')} m^2, capture points {', '.join(c['capture_points']) or '-'}")
    tr = r.get("trajectory") or {}
    if tr.get("frames") is not None:
        print(f"trajectory {tr['frames']} frames, {tr['invalid_poses']} invalid poses; cuts between floors: "
              f"{', '.join(' -> '.join(c) for c in tr.get('cuts') or []) or 'none'}")
    print("\n| panorama | PSNR dB (cleaned) | SSIM | coverage | PSNR dB (input) | PSNR dB (input, outside the removed "
          "rig) | nearest mesh vertex m | masked implausible | room floor m^2 (walls) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for n in sorted(set(r.get("capture", {})) | set(r.get("plausibility", {}))):
        c = r.get("capture", {}).get(n, {})
        p = r.get("plausibility", {}).get(n, {})
        cl, ip = c.get("cleaned", {}), c.get("input", {})
        print(f"| {n} | {fmt(cl.get('psnr'))} | {fmt(cl.get('ssim'), '.3f')} | {fmt(cl.get('coverage'), '.3f')} | "
              f"{fmt(ip.get('psnr'))} | {fmt(c.get('input_outside_rig', {}).get('psnr'))} | "
              f"{fmt((r.get('nearest_vertex_m') or {}).get(n), '.3f')} | "
              f"{fmt(p.get('masked_fraction'), '.1%')} | {fmt(p.get('room_floor_area_m2'), '.1f')} |")
    print("\n| stage | action | wall s | CPU s | peak MB |")
    print("| --- | --- | --- | --- | --- |")
    for st, s in r["stages"].items():
        print(f"| {st} | {s['action']} | {fmt(s['seconds'], '.1f')} | {fmt(s.get('cpu_s'), '.1f')} | "
              f"{fmt(s['peak_rss_mb'], '.0f')} |")
    if res.get("groups"):
        print_groups(res["groups"])
    if res.get("loo"):
        how = {"captures": "the other panoramas' Gaussians alone, no generated frames (--loo-build captures)",
               "full": "the whole home built again without it (--loo-build full)"}[res["loo_build"]]
        print(f"\nleave-one-out novel views, rendered at the left-out panorama's pose against it: {how}\n")
        print("| panorama | PSNR dB | SSIM | coverage | seen share | seen PSNR / SSIM / cov | unseen PSNR / SSIM / cov "
              "| build s |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
        for o in res["loo"]:
            if "psnr" not in o:
                why = f"skipped: {o['skipped']}" if "skipped" in o else f"failed: {o.get('stderr_tail', '')[-120:]!r}"
                print(f"| {o['name']} | {why} |")
                continue
            s, u = o.get("seen", {}), o.get("unseen", {})
            print(f"| {o['name']} | {o['psnr']:.2f} | {o['ssim']:.3f} | {o['coverage']:.3f} | "
                  f"{fmt(s.get('share'), '.2f')} | {fmt(s.get('psnr'))} / {fmt(s.get('ssim'), '.3f')} / "
                  f"{fmt(s.get('coverage'), '.3f')} | {fmt(u.get('psnr'))} / {fmt(u.get('ssim'), '.3f')} / "
                  f"{fmt(u.get('coverage'), '.3f')} | {o['wall_s']:.0f} |")
        print("\nthe seen pixels by the surface the left-out panorama's depth puts them on, and with one gain per "
              "channel fitted (the captures' exposures differ):\n")
        print("| panorama | seen PSNR dB | gain-matched PSNR dB (gain R, G, B) | floor share / PSNR | walls share / PSNR "
              "| ceiling share / PSNR |")
        print("| --- | --- | --- | --- | --- | --- |")
        for o in res["loo"]:
            s = o.get("seen") or {}
            if "psnr" not in s:
                continue
            cells = [f"{fmt((s.get(k) or {}).get('share'), '.2f')} / {fmt((s.get(k) or {}).get('psnr'))}"
                     for k in ("floor", "walls", "ceiling")]
            print(f"| {o['name']} | {s['psnr']:.2f} | {fmt(s.get('psnr_gain_matched'))} "
                  f"({', '.join(f'{x:.2f}' for x in s.get('gain', []))}) | " + " | ".join(cells) + " |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--survey", type=Path, required=True, help="survey.json (ZInD convention; measuring only)")
    ap.add_argument("--json", type=Path, help="write every figure here")
    ap.add_argument("--work", type=Path, help="where the copies run (default ../scratch/bench_real_home/NAME)")
    ap.add_argument("--survey-poses", action="store_true", help="give the copy a poses.json from the survey "
                    "(development of the stages after registration; labelled in the output)")
    ap.add_argument("--loo", action="store_true", help="leave-one-out novel views for every panorama")
    ap.add_argument("--loo-only", nargs="+", metavar="NAME", help="leave-one-out for these panoramas only")
    ap.add_argument("--loo-build", choices=("captures", "full"), default="captures",
                    help="captures: the other panoramas' Gaussians alone (seconds); full: a whole home build each")
    ap.add_argument("--split", action="store_true", help="after the run as a user runs it, each group registration "
                    "left unplaced made a home of its own (`runner.py split`), built and measured")
    ap.add_argument("--skip-full", action="store_true", help="reuse the full run already in --work (no rerun)")
    ap.add_argument("--height", type=int, default=256, help="ERP rows of the renders and references")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                    help="with --survey-poses only: a runner override (labelled in the output)")
    args = ap.parse_args(argv)
    if args.sets and not args.survey_poses:
        ap.error("--set is for the --survey-poses development mode; the user mode runs with no flags")
    if args.split and args.survey_poses:
        ap.error("--split is for the user mode: with --survey-poses every panorama is placed")
    survey = json.loads(args.survey.read_text())
    src = args.scene.resolve()
    mode = "survey" if args.survey_poses else "user"
    work = (args.work or REPO.parent / "scratch" / "bench_real_home" / src.name).resolve() / mode
    work.mkdir(parents=True, exist_ok=True)
    poses = survey_poses(survey) if args.survey_poses else None
    full = work / "full"
    if not args.skip_full:
        copy_home(src, full, poses=poses)
    home = measure_home(full, survey, args.height, args.sets)
    res = {"scene": src.name, "survey_poses": bool(args.survey_poses), "sets": args.sets, "home": home, "loo": [],
           "loo_build": args.loo_build}
    if args.split and home["unregistered"]:
        res["groups"] = measure_groups(full, work, survey, args.height)
    names = sorted(home["registered"]) if args.loo else (args.loo_only or [])
    for n in names:
        res["loo"].append(leave_one_out_captures(full, n, args.height) if args.loo_build == "captures" else
                          leave_one_out(src, work, full, n, poses, args.height, args.sets))
        print(json.dumps(res["loo"][-1])[:400], file=sys.stderr)
    print_report(res)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
