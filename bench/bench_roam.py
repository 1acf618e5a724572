"""Prints the roam protocol on held-out synthetic scenes at the default preset: Gaussian renders at random NavMesh poses
per distance bucket (ERP 256x512 and a 90-degree pinhole) vs the anti-aliased ground truth, the planned trajectory's
reach, and the pipeline's wall time and peak memory (docs/evaluation.md, "Roam").

TEST seeds (report on these, never tune on them): 0 (the `runner.py demo` scene), 7, 19, 23.
VALIDATION seeds (tune on these): 1-6 (`--seeds 1 2 3 4 5 6`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
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
from panoworld.tools.eval.report import jsonable
from panoworld.tools.eval.roam import BUCKETS, FAR_KEY

REPO = Path(__file__).resolve().parent.parent
TEST_SEEDS = [0, 7, 19, 23]
VALIDATION_SEEDS = [1, 2, 3]
QUICK_SEEDS = [0, 7]
BUCKET_KEYS = [b.key for b in BUCKETS] + [FAR_KEY]
METRICS = ["erp_psnr", "erp_ssim", "erp_coverage", "pinhole_psnr", "pinhole_ssim", "pinhole_coverage"]
SPLIT = ["erp_psnr_seen", "erp_psnr_unseen", "erp_unseen_fraction", "erp_unseen_error_share", "erp_coverage_unseen"]
"""The ERP error split by what the capture point sees (roam.split_scores)."""
REALSEE = {"realsee-real": ("panoImage_real.jpg", "depth_real_raw_units_float32.npy")}


def make_scene(root: Path, seed: int, preset: str) -> Path:
    scene = root / f"seed_{seed}"
    if not (scene / "panorama.png").is_file():
        synth = "ci-tiny" if preset == "ci-tiny" else "default"
        subprocess.run([sys.executable, "runner.py", "synth", str(scene), "--seed", str(seed), "--preset", synth],
                       cwd=REPO, check=True, capture_output=True)
    (scene / pl.SCENE_CONFIG).write_text(f"preset: {preset}\n")
    return scene


def real_scenes(root: Path, real: Path) -> list[tuple[str, Path]]:
    """The Realsee3D sample (panorama + raw depth) and every subdirectory of `real` with a panorama and a depth file."""
    out = []
    for name, (pano, depth) in REALSEE.items():
        if (real / pano).is_file() and (real / depth).is_file():
            out.append((name, real / pano, real / depth))
    for d in sorted(p for p in real.iterdir() if p.is_dir()):
        for name, (pano, depth) in REALSEE.items():
            if (d / pano).is_file() and (d / depth).is_file():
                out.append((f"{d.name}/{name}", d / pano, d / depth))
        pano = next((p for p in d.glob("panorama.*")), None)
        depth = next((p for p in [*d.glob("depth*.npy"), *d.glob("*depth*_m.npy")]), None)
        if pano and depth:
            out.append((d.name, pano, depth))
    scenes = []
    for name, pano, depth in out:
        scene = root / name.replace("/", "_")
        scene.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(pano, scene / f"panorama{pano.suffix}")
        shutil.copyfile(depth, scene / "depth.npy")
        scenes.append((name, scene))
    return scenes


def run_pipeline(scene: Path, preset: str, sets: list[str] = ()) -> dict:
    """Run every stage; wall seconds and peak MB from the stage manifests (so a cached stage counts with the time it
    took when it ran: scenes kept with --out are reused, not rerun)."""
    report = pl.run(scene, preset=preset, sets=list(sets), on_result=lambda r: print(f"    [{r.stage}] {r.action} {r.seconds:.1f} s",
                                                                       file=sys.stderr, flush=True))
    if not report.ok:
        failed = next(r for r in report.results if r.action == "failed")
        raise RuntimeError(f"{scene}: stage {failed.stage} failed: {failed.reason}")
    manifests = [read_manifest(scene / pl.ARTIFACTS_DIRNAME / r.stage)
                 for r in report.results]
    return {"wall_s": sum(m.get("wall_s", 0.0) for m in manifests),
            "stages_ran": sum(r.action == "ran" for r in report.results),
            "peak_mb": max((m.get("peak_rss_mb") or 0.0 for m in manifests), default=None),
            "stage_wall_s": {r.stage: m.get("wall_s") for r, m in zip(report.results, manifests)}}


def _num(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def print_scene(name: str, res: dict) -> None:
    roam, traj = res["roam"], res["trajectory"]
    print(f"\n{name}  (reference: {roam.get('reference')}; ERP {roam.get('erp_size')}, pinhole {roam.get('pinhole')})")
    print(f"  {'bucket':<6} {'range m':>10} {'n':>2} {'dist m':>6}  {'ERP PSNR':>8} {'SSIM':>6} {'cov':>7}  "
          f"{'pin PSNR':>8} {'SSIM':>6} {'cov':>7}")
    for key in BUCKET_KEYS:
        if not roam.get(f"{key}_count"):
            why = roam.get(f"{key}_erp_psnr", {}).get("reason", "")
            print(f"  {key:<6} {roam.get(f'{key}_range_m', ''):>10}  0  not reached: {why}")
            continue
        vals = [_num(roam.get(f"{key}_{m}")) for m in METRICS]
        f = ["n/a" if v is None else f"{v:.2f}" if "psnr" in m else f"{v:.4f}" for v, m in zip(vals, METRICS)]
        print(f"  {key:<6} {roam[f'{key}_range_m']:>10} {roam[f'{key}_count']:>2} {roam[f'{key}_distance_m']:6.2f}  "
              f"{f[0]:>8} {f[1]:>6} {f[2]:>7}  {f[3]:>8} {f[4]:>6} {f[5]:>7}")
    print_split({key: {m: _num(roam.get(f"{key}_{m}")) for m in SPLIT} for key in BUCKET_KEYS})
    if _num(roam.get("d0_erp_psnr_vs_input")) is not None:
        print(f"  capture point vs the input panorama: {roam['d0_erp_psnr_vs_input']:.2f} dB")
    reach = traj.get("reach_max_m")
    if _num(reach) is not None:
        print(f"  trajectory reach: {reach:.2f} m max from the capture point; per sector reached / reachable: "
              + ", ".join(f"{a:.2f}/{b:.2f}" for a, b in zip(traj["sector_reached_m"], traj["sector_reachable_m"]))
              + f"; min fraction {traj['sector_reach_fraction_min']:.2f}")
    p = res["pipeline"]
    print(f"  pipeline: {p['wall_s']:.1f} s wall (sum of stages; {p['stages_ran']} ran now), peak "
          f"{p['peak_mb'] or 0:.0f} MB; eval {res['eval_s']:.1f} s")


def print_split(rows: dict[str, dict]) -> None:
    """Per bucket: PSNR where the capture point sees the surface / where it does not, the unseen pixels' fraction,
    their share of the squared error and their coverage."""
    if not any(v is not None for r in rows.values() for v in r.values()):
        return
    print(f"  {'bucket':<6} {'seen dB':>8} {'unseen dB':>9} {'unseen px':>9} {'err share':>9} {'unseen cov':>10}")
    for key, r in rows.items():
        f = ["n/a" if r.get(m) is None else f"{r[m]:.2f}" if "psnr" in m else f"{r[m]:.4f}" for m in SPLIT]
        print(f"  {key:<6} {f[0]:>8} {f[1]:>9} {f[2]:>9} {f[3]:>9} {f[4]:>10}")


def print_mean(results: dict[str, dict]) -> dict:
    """Mean over scenes per bucket and metric (scenes lacking a bucket are left out; their count is shown)."""
    print(f"\nmean over {len(results)} scene(s)")
    print(f"  {'bucket':<6} {'scenes':>6}  {'ERP PSNR':>8} {'SSIM':>6} {'cov':>7}  {'pin PSNR':>8} {'SSIM':>6} {'cov':>7}")
    summary = {}
    for key in BUCKET_KEYS:
        row = {}
        for m in METRICS + SPLIT:
            vals = [v for r in results.values() if (v := _num(r["roam"].get(f"{key}_{m}"))) is not None]
            row[m] = sum(vals) / len(vals) if vals else None
            row["scenes"] = max(row.get("scenes", 0), len(vals))
        summary[key] = row
        f = ["n/a" if row[m] is None else f"{row[m]:.2f}" if "psnr" in m else f"{row[m]:.4f}" for m in METRICS]
        print(f"  {key:<6} {row['scenes']:>6}  {f[0]:>8} {f[1]:>6} {f[2]:>7}  {f[3]:>8} {f[4]:>6} {f[5]:>7}")
    print_split(summary)
    walls = [r["pipeline"]["wall_s"] for r in results.values()]
    peaks = [r["pipeline"]["peak_mb"] or 0 for r in results.values()]
    fr = [v for r in results.values() if (v := _num(r["trajectory"].get("sector_reach_fraction_min"))) is not None]
    print(f"  pipeline wall {sum(walls) / len(walls):.1f} s mean (max {max(walls):.1f}), peak {max(peaks):.0f} MB; "
          f"min sector reach fraction {min(fr) if fr else float('nan'):.2f}")
    checks = [("capture point ERP PSNR >= 32 dB", summary["d0"]["erp_psnr"], 32.0),
              ("~1 m ERP PSNR >= 28 dB", summary["d1"]["erp_psnr"], 28.0),
              ("~2 m ERP PSNR >= 25 dB", summary["d2"]["erp_psnr"], 25.0),
              ("~2 m coverage >= 0.995", summary["d2"]["erp_coverage"], 0.995),
              ("every sector reached >= 70 %", min(fr) if fr else None, 0.7)]
    print("  targets (on the mean): " + "; ".join(
        f"{name}: {'n/a' if v is None else ('met' if v >= bound else 'NOT met')}" for name, v, bound in checks))
    return summary


def print_real(results: dict[str, dict]) -> None:
    """Real captures (no ground truth off the capture point): ERP coverage per bucket and the capture point against
    the input panorama, with the targets (Realsee: >= 0.99 coverage and >= 25 dB at the capture point; real
    captures in general: >= 0.99 coverage ~1 m and ~2 m away)."""
    print("\nreal captures: ERP coverage per bucket (alpha > 0.5), capture point vs the input panorama")
    keys = ["d0", "d0.5", "d1", "d2", FAR_KEY]
    print("| scene | " + " | ".join(f"cov {k}" for k in keys) + " | d0 vs input dB | targets |\n|---|"
          + "---|" * (len(keys) + 2))
    for name, res in results.items():
        roam = res["roam"]
        cov = {k: _num(roam.get(f"{k}_erp_coverage")) for k in keys}
        vs = _num(roam.get("d0_erp_psnr_vs_input"))
        checks = [("d0 cov", cov["d0"], 0.99), ("d1 cov", cov["d1"], 0.99), ("d2 cov", cov["d2"], 0.99)]
        if "realsee" in name:
            checks.append(("d0 vs input", vs, 25.0))
        met = ", ".join(f"{n} {'met' if v is not None and v >= b else 'NOT met' if v is not None else 'n/a'}"
                        for n, v, b in checks)
        print(f"| {name} | " + " | ".join("-" if cov[k] is None else f"{cov[k]:.4f}" for k in keys)
              + f" | {'-' if vs is None else f'{vs:.2f}'} | {met} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="*", help=f"synthetic scene seeds (default: the test set {TEST_SEEDS})")
    ap.add_argument("--scenes", type=int, help="only the first N of the seeds")
    ap.add_argument("--quick", action="store_true", help=f"ci-tiny preset and seeds {QUICK_SEEDS} (development, tests)")
    ap.add_argument("--views", type=int, default=0, help="roam views per bucket (default: 2; ci-tiny 1)")
    ap.add_argument("--real", type=Path, help="also the real captures under DIR (coverage only + capture-point PSNR vs "
                    "the input); e.g. /work/shared/data/real/realsee3d_assets")
    ap.add_argument("--out", type=Path, help="keep the scenes here (reused: cached stages are not rerun; their "
                    "manifests' wall times count)")
    ap.add_argument("--json", type=Path, help="also write everything as JSON to this file")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                    help="a param override for every scene (as runner.py run --set; for validation runs)")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)  # the evaluation's renders (stages run in their own processes, unaffected)
    preset = "ci-tiny" if a.quick else "default"
    seeds = a.seeds if a.seeds is not None else (QUICK_SEEDS if a.quick else TEST_SEEDS)
    seeds = seeds[: a.scenes] if a.scenes else seeds
    params = EvalParams(roam_views=a.views)
    load = Path("/proc/loadavg").read_text().split()[0]
    print(f"preset {preset}{' ' + ' '.join(a.sets) if a.sets else ''}; seeds {seeds} ({'TEST set' if seeds and set(seeds) <= set(TEST_SEEDS) else 'not the test set'}); "
          f"load average {load} at start on {os.cpu_count()} cores (shared machines inflate wall times)")
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bench-roam-") as tmp:
        root = a.out or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        scenes = [(f"synth seed {s}", make_scene(root, s, preset)) for s in seeds]
        if a.real:
            scenes += real_scenes(root, a.real)
        for name, scene in scenes:
            print(f"\n{name}: {scene}", file=sys.stderr, flush=True)
            pipe = run_pipeline(scene, preset, a.sets)
            t0 = time.perf_counter()
            report, errors = evaluate(scene, params, stages=["trajectory", "roam"])
            if errors:
                print(f"  {name}: eval errors: {[report['stages'][s]['reason'] for s in errors]}")
            st = report["stages"]
            results[name] = {"scene": str(scene), "reference": report["reference"], "pipeline": pipe,
                             "eval_s": time.perf_counter() - t0,
                             "roam": st["roam"] if not is_unavailable(st["roam"]) else {},
                             "trajectory": st["trajectory"] if not is_unavailable(st["trajectory"]) else {}}
            print_scene(name, results[name])
    synth = {k: v for k, v in results.items() if k.startswith("synth")}
    summary = print_mean(synth) if synth else {}
    real = {k: v for k, v in results.items() if not k.startswith("synth")}
    if real:
        print_real(real)
    if a.json:
        a.json.write_text(json.dumps(jsonable({"preset": preset, "seeds": seeds, "load_at_start": float(load),
                                               "scenes": results, "mean": summary}), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
