"""Prints end-to-end quality of the weight-free pipeline on synthetic scenes: `runner.py eval` after a full run."""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from panoworld import pipeline as pl
from panoworld.evaluate import EvalParams, evaluate, is_unavailable

REPO = Path(__file__).resolve().parent.parent
# Paper-like chain at a CPU-friendly size: 256x512 frames, no upscaling, the planned poses (COLMAP has its own bench).
SETS = ["conditions.height=256", "conditions.width=512", "video.upscale=none", "video.mcap=false",
        "poses.backend=planned", "gaussians.height=256"]
SHOW = {
    "conditions": ["psnr_valid", "mask_iou"],
    "video": ["psnr", "ssim", "ws_psnr", "psnr_disoccluded"],
    "trajectory": ["min_clearance_m", "path_collisions", "step_cv"],
    "gaussians": ["context_psnr", "novel_psnr", "context_ssim", "novel_ssim"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--preset", default="default", help="synth preset of the scenes (the pipeline runs at SETS sizes)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in a.seeds:
            scene = Path(tmp) / f"scene_{seed}"
            subprocess.run([sys.executable, "runner.py", "synth", str(scene), "--seed", str(seed), "--preset", a.preset],
                           cwd=REPO, check=True, capture_output=True)
            t0 = time.perf_counter()
            report = pl.run(scene, sets=SETS)
            assert report.ok, report.table()
            secs = time.perf_counter() - t0
            result, errors = evaluate(scene, EvalParams(), stages=list(SHOW))
            print(f"seed {seed}: pipeline {secs:.0f} s" + (f"  (eval errors: {errors})" if errors else ""))
            for stage, keys in SHOW.items():
                vals = result["stages"].get(stage, {})
                shown = []
                for k in keys:
                    v = vals.get(k)
                    shown.append(f"{k}={'n/a' if v is None or is_unavailable(v) else f'{v:.3f}' if isinstance(v, float) else v}")
                print(f"  {stage:<11} " + "  ".join(shown))


if __name__ == "__main__":
    main()
