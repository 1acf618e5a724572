"""Prints per-stage wall/CPU seconds and peak MB of the whole pipeline at a preset (default: `default`) on synthetic
scenes and the real Realsee3D samples, with fidelity (poses ATE vs the plan / ground truth, Gaussian context and novel
PSNR), and optionally the same scene at full size (features and fusion at the stored frame size) for comparison."""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.framework import pipeline as pl
from panoworld.io.manifest import read_manifest
from panoworld.tools.eval.cli import EvalParams, evaluate, is_unavailable

REPO = Path(__file__).resolve().parent.parent
REAL = REPO.parent / "shared" / "data" / "real" / "realsee3d_assets"
REAL_SCENES = {"realsee-real": ("panoImage_real.jpg", "depth_real_raw_units_float32.npy"),
               "realsee-synthetic": ("panoImage_synthesis.jpg", "depth_synthetic_raw_units_float32.npy")}
# Full size: COLMAP's defaults (SIFT on the frames as stored, upsampled first octave, 8192 features, incremental
# mapper) and Gaussians fused from the frames as stored.
FULL_SETS = ["poses.colmap.max_image_size=0", "poses.colmap.max_features=8192", "poses.colmap.upsample_features=true", "poses.colmap.mapper=incremental",
             "gaussians.max_height=0"]


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_scene(scene: Path, preset: str, sets: list[str] = (), from_: str | None = None) -> tuple[list[dict], float]:
    """Run the pipeline; rows of (stage, action, wall s, CPU s, peak MB) and the total wall seconds."""
    rows, last = [], [_cpu()]

    def on_result(r: pl.StageResult) -> None:
        now = _cpu()
        rows.append({"stage": r.stage, "action": r.action, "wall_s": r.seconds, "cpu_s": now - last[0],
                     "peak_mb": r.peak_rss_mb, "reason": r.reason})
        last[0] = now
        print(f"    [{r.stage}] {r.action} {r.seconds:.1f} s", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    report = pl.run(scene, preset=preset, sets=list(sets), from_=from_, on_result=on_result)
    total = time.perf_counter() - t0
    if report.compile_process is not None:  # numba's cache was cold: the runner compiled the kernels beside the stages
        _, status, usage = os.wait4(report.compile_process.pid, 0)
        report.compile_process.returncode = os.waitstatus_to_exitcode(status)
        cpu = usage.ru_utime + usage.ru_stime
        print(f"  background kernel compilation (beside the stages, not in their CPU): {cpu:.1f} s CPU, waited "
              f"{time.perf_counter() - t0 - total:.1f} s for it after the run")
    if not report.ok:
        failed = [r for r in report.results if r.action == "failed"]
        print(f"  FAILED: {failed[0].stage}: {failed[0].reason}")
    return rows, total


def fidelity(scene: Path) -> dict:
    """ATE vs the plan (poses.json), ATE vs ground truth and Gaussian PSNRs (runner.py eval) when the scene has gt/."""
    out: dict = {}
    art = scene / pl.ARTIFACTS_DIRNAME
    try:
        info = read_manifest(art / "poses")["info"]
        m = info.get("metrics_vs_planned") or {}
        out.update(registered=f"{info['num_registered']}/{info['num_frames']}", ate_plan_mm=1000 * m["ate"]
                   if m.get("ate") is not None else None)
    except (OSError, KeyError, ValueError):
        pass
    try:
        info = read_manifest(art / "gaussians")["info"]
        out.update(num_gaussians=info["num_gaussians"], self_psnr=info.get("context_psnr"))
    except (OSError, KeyError, ValueError):
        pass
    if (scene / "gt" / "gt.json").is_file():
        res, _ = evaluate(scene, EvalParams(), stages=["poses", "gaussians"])
        p, g = res["stages"]["poses"], res["stages"]["gaussians"]
        val = lambda d, k: None if d.get(k) is None or is_unavailable(d.get(k)) else d[k]
        out.update(ate_gt_mm=None if val(p, "ate") is None else 1000 * p["ate"], context_psnr=val(g, "context_psnr"),
                   novel_psnr=val(g, "novel_psnr"), gs_setting=g.get("setting"))
    return out


def print_rows(name: str, rows: list[dict], total: float) -> None:
    ran = [r for r in rows if r["action"] == "ran"]
    print(f"  {'stage':<11} {'action':<8} {'wall s':>8} {'CPU s':>8} {'peak MB':>8}")
    for r in rows:
        mb = f"{r['peak_mb']:.0f}" if r["peak_mb"] is not None else "-"
        print(f"  {r['stage']:<11} {r['action']:<8} {r['wall_s']:8.1f} {r['cpu_s']:8.1f} {mb:>8}")
    peak = max((r["peak_mb"] or 0) for r in ran) if ran else 0
    print(f"  {name}: pipeline {total:.1f} s wall, {sum(r['cpu_s'] for r in ran):.1f} s CPU, peak {peak:.0f} MB "
          f"(stages ran: {len(ran)})")


def print_fidelity(f: dict) -> None:
    fmt = lambda v, p=2: "n/a" if v is None else f"{v:.{p}f}" if isinstance(v, float) else str(v)
    print(f"  fidelity: registered {fmt(f.get('registered'))}, ATE vs plan {fmt(f.get('ate_plan_mm'), 3)} mm, "
          f"ATE vs GT {fmt(f.get('ate_gt_mm'), 3)} mm, Gaussians {fmt(f.get('num_gaussians'))}, context PSNR "
          f"{fmt(f.get('context_psnr'))} dB, novel PSNR {fmt(f.get('novel_psnr'))} dB ({fmt(f.get('gs_setting'))}), "
          f"self-render PSNR {fmt(f.get('self_psnr'))} dB")


def reference_loop_s() -> float:
    """Seconds of a pure-Python 20M-step sum in a function: this machine's single-core speed, to compare timings
    across machines (the same loop at module level runs about 2.5x slower)."""
    t = time.perf_counter()
    s = 0
    for i in range(20_000_000):
        s += i
    return time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2], help="synthetic scenes (synth preset default)")
    ap.add_argument("--preset", default="default", help="pipeline preset")
    ap.add_argument("--real", choices=["auto", "none"], default="auto",
                    help=f"auto: also the Realsee3D samples under {REAL} when present")
    ap.add_argument("--full", type=int, default=None, metavar="SEED",
                    help="also rerun poses and gaussians of this seed's scene at full size (" + " ".join(FULL_SETS) + ")")
    ap.add_argument("--out", type=Path, help="keep the scenes here (default: a temporary directory)")
    ap.add_argument("--cold", action="store_true",
                    help="a new user's first run: numba's on-disk caches empty (NUMBA_CACHE_DIR a fresh directory), so "
                         "every kernel is compiled in the stage that first calls it")
    ap.add_argument("--warmup", action="store_true",
                    help="with --cold: `runner.py warmup` first (the once-per-install compilation), timed apart")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-pipeline-") as tmp:
        if a.cold:
            os.environ["NUMBA_CACHE_DIR"] = str(Path(tmp) / "numba-cache")  # the stages' subprocesses inherit it
        if a.warmup:
            c0 = _cpu()
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "runner.py", "warmup"], cwd=REPO, check=True)
            print(f"warmup: {time.perf_counter() - t0:.1f} s wall, {_cpu() - c0:.1f} s CPU (once per install)")
        root = a.out or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        scenes: list[tuple[str, Path]] = []
        for seed in a.seeds:
            scene = root / f"synth_{seed}"
            if not (scene / "panorama.png").is_file():
                subprocess.run([sys.executable, "runner.py", "synth", str(scene), "--seed", str(seed)], cwd=REPO,
                               check=True, capture_output=True)
            scenes.append((f"synth seed {seed}", scene))
        if a.real == "auto" and REAL.is_dir():
            for name, (pano, depth) in REAL_SCENES.items():
                scene = root / name
                if (REAL / pano).is_file() and (REAL / depth).is_file():
                    scene.mkdir(exist_ok=True)
                    shutil.copyfile(REAL / pano, scene / "panorama.jpg")
                    shutil.copyfile(REAL / depth, scene / "depth.npy")
                    scenes.append((name, scene))
        print(f"preset {a.preset}; machine: {subprocess.run(['nproc'], capture_output=True, text=True).stdout.strip()} "
              f"cores, load average {open('/proc/loadavg').read().split()[0]} at start (shared: wall times inflate, "
              f"CPU times much less); reference loop {reference_loop_s():.2f} s (see reference_loop_s); numba caches "
              f"{('cold (--cold)' + (', then runner.py warmup' if a.warmup else '')) if a.cold else 'as found (warm after a first run)'}")
        for name, scene in scenes:
            print(f"\n{name}: {scene}")
            rows, total = run_scene(scene, a.preset)
            print_rows(name, rows, total)
            print_fidelity(fidelity(scene))
        if a.full is not None:
            src = root / f"synth_{a.full}"
            full = root / f"synth_{a.full}_full"
            if not full.exists():
                shutil.copytree(src, full, ignore=shutil.ignore_patterns(".tmp-*", ".lock"))
            print(f"\nsynth seed {a.full} at full size ({' '.join(FULL_SETS)}): poses and gaussians rerun")
            rows, total = run_scene(full, a.preset, FULL_SETS, from_="poses")
            print_rows("full size", rows, total)
            print_fidelity(fidelity(full))
    return 0


if __name__ == "__main__":
    sys.exit(main())
