"""Real panoramas and their synthetic failure classes through the whole pipeline at default settings, no flags.

    python bench/bench_real.py [SCENE_DIR ...] [--until STAGE] [--work DIR] [--no-synthetic] [--no-huge] [--rgb-only PANO ...]

A SCENE_DIR is a scene directory (panorama.png|jpg [+ depth.npy|exr|png]) or a folder holding an RGB-D pair the
way the Realsee3D README assets come (panoImage_*.jpg + depth_image*.png: each pair becomes a scene under
--work). Default: the Realsee pair under ../shared/data/real/realsee3d_assets (real LiDAR and synthesis), the
synthetic failure classes of panoworld.tools.synth.failure_cases at 256x512, and an 8192x4096 panorama (the synthetic
scene upsampled: checks the depth stage's resolution policy keeps every stage under 8 GiB). Prints per scene:
stages ok, seconds, peak MB (largest stage), NavMesh area, start-off-NavMesh distance, exempt poses, min
clearance (against the scene mesh), sectors covered/reachable, the Gaussians' context PSNR; then what was decided
for no room to move, depth outliers and a start off the NavMesh; then the nadir table:
capture rig found and removed (kind, cap, sphere share), the nadir-cap vs floor-ring luminance gap before/after
and the share of pixels completed from floor/ceiling planes, for these scenes, ../shared/data/real/zind_garage
and (rig detection on colour alone) the RGB-only panoramas of ../shared/data/real/rgb_only.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np

from panoworld.core.errors import ArtifactError
from panoworld.framework import pipeline as pl
from panoworld.io.manifest import read_manifest

REAL = REPO.parent / "shared" / "data" / "real" / "realsee3d_assets"
ZIND = REPO.parent / "shared" / "data" / "real" / "zind_garage"
RGB_ONLY = REPO.parent / "shared" / "data" / "real" / "rgb_only"
PAIRS = {"realsee_real": ("panoImage_real.jpg", "depth_image.png"),
         "realsee_synthesis": ("panoImage_synthesis.jpg", "depth_image_synthesis.png")}


def scenes_from(path: Path, work: Path) -> list[Path]:
    """A scene directory as it is, or the Realsee-style pairs of an asset folder copied into scene directories
    (a ZInD-style folder, panorama.jpg + layout_depth_m.npy, becomes a scene with that depth as depth.npy)."""
    if (path / "layout_depth_m.npy").is_file() and not (path / "depth.npy").is_file():
        d = work / path.name
        d.mkdir(parents=True, exist_ok=True)
        pano = next(p for p in path.glob("panorama.*"))
        shutil.copy(pano, d / pano.name)
        shutil.copy(path / "layout_depth_m.npy", d / "depth.npy")
        return [d]
    if any((path / n).is_file() for n in ("panorama.png", "panorama.jpg", "panorama.jpeg")):
        return [path]
    out = []
    for name, (pano, depth) in PAIRS.items():
        if (path / pano).is_file():
            d = work / name
            d.mkdir(parents=True, exist_ok=True)
            shutil.copy(path / pano, d / "panorama.jpg")
            if (path / depth).is_file():
                shutil.copy(path / depth, d / "depth.png")
            out.append(d)
    if not out:
        raise SystemExit(f"{path}: neither a scene directory nor a folder of Realsee-style RGB-D pairs")
    return out


def huge_scene(work: Path) -> Path:
    """An 8192x4096 panorama with depth: the synthetic scene rendered at 1024 rows and upsampled (nearest depth)."""
    import cv2
    import numpy as np

    from panoworld.tools.synth.failure_cases import failure_scene

    d = work / "huge-8192x4096"
    if (d / "depth.npy").is_file():
        return d
    d.mkdir(parents=True, exist_ok=True)
    scene = failure_scene(0)
    rgb, depth = scene.render(scene.world_from_canonical, 1024, 2048)
    cv2.imwrite(str(d / "panorama.jpg"), cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), (8192, 4096), interpolation=cv2.INTER_CUBIC))
    np.save(d / "depth.npy", cv2.resize(np.where(np.isfinite(depth), depth, 0).astype(np.float32), (8192, 4096),
                                        interpolation=cv2.INTER_NEAREST))
    return d


def stage_info(scene: Path, stage: str) -> dict:
    """A stage's manifest `info` ({} when it has not run)."""
    try:
        return read_manifest(scene / "artifacts" / stage)["info"]
    except (OSError, KeyError, ValueError, ArtifactError):  # --until stopped before the stage
        return {}


def measure(scene: Path, until: str) -> dict:
    t0 = time.perf_counter()
    try:
        report = pl.run(scene, until=until)
    except pl.PipelineError as e:  # bad input or a broken pipeline file: a failed row, the other scenes still run
        report = pl.Report(scene)
        report.results.append(pl.StageResult("-", "failed", str(e)))
    wall = time.perf_counter() - t0
    ran = [r for r in report.results if r.action in ("ran", "cached")]
    failed = [r for r in report.results if r.action == "failed"]
    selected = [r for r in report.results if r.reason != "not selected"]
    row = {"scene": scene.name, "ok": f"{len(ran)}/{len(selected)}",
           "seconds": wall, "peak_mb": max([r.peak_rss_mb or 0 for r in ran] + [0]),
           "failed": f"{failed[0].stage}: {failed[0].reason[:160]}" if failed else ""}

    def info(stage):
        return stage_info(scene, stage)

    nav, traj, gs = info("navmesh"), info("trajectory"), info("gaussians")
    row.update(nadir_row(scene, info("depth")))
    min_clear = None
    if traj:  # over the poses held to the NavMesh (pose 0 and the way onto the NavMesh are exempt)
        clear = json.loads((scene / "artifacts" / "trajectory" / "trajectory.json").read_text())["clearance_m"]
        held = [c for i, c in enumerate(clear) if i not in set(traj["exempt_poses"])]
        min_clear = min(held) if held else None
    row.update(area=nav.get("area_m2"), off=traj.get("start_off_navmesh_m"),
               exempt=len(traj.get("exempt_poses", [])) - 1 if traj else None,
               min_clear=min_clear, radius=traj.get("agent_radius_m"),
               sectors=f"{traj['sectors_covered']}/{traj['sectors_reachable']}" if "sectors_reachable" in traj else "-",
               psnr=gs.get("context_psnr"), assumed=(nav.get("assumed_walkable") or {}).get("assumed_m2"),
               decisions="; ".join(info("depth").get("decisions", [])))
    return row


def hostile_decisions(scene: Path) -> dict:
    """What the pipeline decided for the hostile-input classes (closet, depth outliers, a start off the NavMesh)."""
    dep, nav, traj = (stage_info(scene, s) for s in ("depth", "navmesh", "trajectory"))
    out = dep.get("outliers") or {}
    nr = nav.get("no_room") or {}
    return {
        "scene": scene.name,
        "no_room": f"{nr['decision']} (r {nr['requested_agent_radius_m']} -> {nr['agent_radius_m']} m)" if nr else "-",
        "rotation_only": traj.get("rotation_only"),
        "outliers": f"{out.get('far_px', 0)} far + {out.get('spike_px', 0)} spikes" if out else "-",
        "max_depth": f"{out['max_depth_before']:.4g} -> {out['max_depth_after']:.4g}" if out.get("max_depth_after") else "-",
        "area": nav.get("area_m2"),
        "off": traj.get("start_off_navmesh_m"),
        "approach": (traj.get("plan") or {}).get("approach_steps"),
        "frames": traj.get("frames"),
    }


def print_hostile_table(scenes: list[Path]) -> None:
    """The hostile-input table: per scene, what was decided for no room to move, depth outliers and the approach."""
    head = ("scene", "no room to move: decision", "rotation only", "depth outliers masked", "max depth before -> after",
            "NavMesh m2", "start off m", "approach steps / frames")
    print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for s in scenes:
        r = hostile_decisions(s)
        print("| " + " | ".join([r["scene"], r["no_room"], fmt(r["rotation_only"]), r["outliers"], r["max_depth"],
                                 fmt(r["area"]), fmt(r["off"]), f"{fmt(r['approach'])} / {fmt(r['frames'])}"]) + " |")


def nadir_row(scene: Path, depth_info: dict) -> dict:
    """Rig found/removed, its area, the nadir-cap vs floor-ring luminance gap of the input and of the cleaned
    panorama (artifacts/depth/panorama.png), and the share of pixels completed from floor/ceiling planes."""
    import cv2

    from panoworld.depth.depth_map import resize_panorama
    from panoworld.depth.rig.remove import nadir_luminance_gap
    from panoworld.io.depth import read_panorama

    rig = depth_info.get("rig") or {}
    out = {"rig": rig.get("kind") if rig.get("found") else ("none" if rig else "-"),
           "rig_reason": rig.get("reason", ""), "rig_cap": (rig.get("mask") or {}).get("cap_deg"),
           "rig_area": (rig.get("mask") or {}).get("sphere_fraction"),
           "completed": (depth_info.get("pole_completion") or {}).get("completed_fraction"),
           "gap_before": None, "gap_after": None}
    cleaned = scene / "artifacts" / "depth" / "panorama.png"
    pano = next((p for p in sorted(scene.glob("panorama.*"))), None)
    if cleaned.is_file() and pano is not None:
        after = cv2.cvtColor(cv2.imread(str(cleaned), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        before = resize_panorama(read_panorama(pano), after.shape[0])
        out.update(gap_before=nadir_luminance_gap(before), gap_after=nadir_luminance_gap(after),
                   unchanged=bool(np.array_equal(before, after)))
    return out


def nadir_only(paths: list[Path]) -> list[dict]:
    """RGB-only panoramas (no depth, so no pipeline without weights): rig detection and removal on the colour alone."""
    from panoworld.depth.depth_map import resize_panorama
    from panoworld.depth.rig.detect import detect_rig
    from panoworld.depth.rig.remove import area_stats, nadir_luminance_gap, remove_rig
    from panoworld.io.depth import read_panorama

    rows = []
    for p in paths:
        rgb = read_panorama(p)
        rgb = resize_panorama(rgb, min(rgb.shape[0], 1024))
        det = detect_rig(rgb)
        out = remove_rig(rgb, det) if det.found else rgb
        a = area_stats(det.mask) if det.found else {}
        rows.append({"scene": p.name, "rig": det.kind or "none", "rig_reason": det.reason, "rig_cap": a.get("cap_deg"),
                     "rig_area": a.get("sphere_fraction"), "gap_before": nadir_luminance_gap(rgb),
                     "gap_after": nadir_luminance_gap(out), "unchanged": bool(np.array_equal(out, rgb)),
                     "completed": None})
    return rows


def print_nadir_table(rows: list[dict]) -> None:
    head = ("scene", "rig", "cap deg", "sphere %", "lum gap before", "lum gap after", "unchanged", "completed %")
    print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in rows:
        pct = (lambda v: "-" if v is None else f"{v:+.1%}")
        cells = (r["scene"], r["rig"], fmt(r["rig_cap"], ".1f"), fmt(None if r["rig_area"] is None else 100 * r["rig_area"]),
                 pct(r["gap_before"]), pct(r["gap_after"]), str(r.get("unchanged", "-")),
                 fmt(None if r["completed"] is None else 100 * r["completed"], ".1f"))
        print("| " + " | ".join(cells) + " |")
    for r in rows:
        print(f"  {r['scene']}: {r['rig_reason']}")


def fmt(v, spec=".2f"):
    return "-" if v is None else format(v, spec) if isinstance(v, float) else str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="*", type=Path)
    ap.add_argument("--until", default="gaussians", help="last stage to run (default: gaussians)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/panoworld_bench_real"), help="where generated scenes go")
    ap.add_argument("--no-synthetic", action="store_true", help="skip the synthetic failure-class scenes")
    ap.add_argument("--no-huge", action="store_true", help="skip the 8192x4096 panorama")
    ap.add_argument("--height", type=int, default=256, help="panorama height of the synthetic failure-class scenes")
    ap.add_argument("--rgb-only", nargs="*", type=Path, default=None,
                    help="RGB-only panoramas (default: ../shared/data/real/rgb_only/*) for the nadir table alone")
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    scenes: list[Path] = []
    for s in args.scenes or [p for p in (REAL, ZIND) if p.is_dir()]:
        scenes += scenes_from(s, args.work)
    if not args.scenes and not args.no_synthetic:
        from panoworld.tools.synth.failure_cases import FailureCase, write_failure_scene

        for case in FailureCase:
            if case in (FailureCase.HUGE,):
                continue
            d = args.work / f"synth-{case}"
            if not (d / "gt_scene.json").is_file():
                write_failure_scene(case, d, height=args.height)
            scenes.append(d)
    if not args.scenes and not args.no_huge:
        scenes.append(huge_scene(args.work))
    print(f"{len(scenes)} scenes, default settings, no flags, through {args.until} "
          "(times and memory on a shared machine: measured under load)", flush=True)
    head = ("scene", "stages ok", "s", "peak MB", "NavMesh m2", "assumed m2", "start off m", "exempt", "min clear m (held)",
            "sectors", "ctx PSNR")
    rows = []
    for s in scenes:
        r = measure(s, args.until)
        rows.append(r)
        print(f"{r['scene']}: {r['ok']} stages ok, {r['seconds']:.0f} s, peak {r['peak_mb']:.0f} MB "
              f"{'FAILED ' + r['failed'] if r['failed'] else ''}\n  depth decisions: {r['decisions']}", flush=True)
    print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in rows:
        cells = (r["scene"], r["ok"], fmt(r["seconds"], ".0f"), fmt(r["peak_mb"], ".0f"), fmt(r["area"]),
                 fmt(r["assumed"]), fmt(r["off"]), fmt(r["exempt"]), fmt(r["min_clear"]), r["sectors"], fmt(r["psnr"]))
        print("| " + " | ".join(cells) + " |")
    print_hostile_table(scenes)
    nadir = rows + (nadir_only(sorted(p for p in RGB_ONLY.glob("*") if p.suffix in (".png", ".jpg")))
                    if args.rgb_only is None and not args.scenes and RGB_ONLY.is_dir() else nadir_only(args.rgb_only or []))
    print("\nNadir: capture rig found/removed (depth.rig auto) and floor/ceiling completion (depth.complete_poles);"
          " lum gap = mean luminance of the 15 deg nadir cap vs the 30-42 deg floor ring (target |after| <= 15 % where"
          " a rig was found; captures without one unchanged)")
    print_nadir_table(nadir)
    bad = [r for r in rows if r["failed"] or (r["min_clear"] is not None and r["min_clear"] < r["radius"] - 1e-9)]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
