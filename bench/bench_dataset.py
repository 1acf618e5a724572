"""Prints dataset-run throughput (scenes/hour) with 1 and 2 local workers and with Ray, and the paper-layout tables
of those scenes at strides r = 1, 2, 4 (`runner.py run/eval DATASET --all`)."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from panoworld.tools.batch.run import cost_table, run_dataset
from panoworld.tools.eval.common import EvalParams
from panoworld.tools.eval.dataset import evaluate_dataset


def cpu_seconds() -> float:
    """user + sys CPU of this process and its finished children (the stages run as children)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--preset", default="ci-tiny")
    ap.add_argument("--until", default="poses", help="last stage of the timed runs (gaussians dominates on a CPU)")
    ap.add_argument("--strides", default="1,2,4")
    ap.add_argument("--no-ray", action="store_true")
    ap.add_argument("--no-sweep", action="store_true", help="skip the r = 1, 2, 4 tables")
    ap.add_argument("--keep", type=Path, help="keep the dataset here instead of a temporary directory")
    a = ap.parse_args()
    tmp = tempfile.mkdtemp()
    try:
        data = Path(tmp) / "data"
        subprocess.run([sys.executable, "runner.py", "synth", str(data), "--seed", "7", "--scenes", str(a.scenes),
                        "--preset", a.preset], cwd=REPO, check=True, capture_output=True)
        print(f"dataset: {a.scenes} {a.preset} scenes; timed runs: depth..{a.until}, stride 1; machine: "
              f"{os.cpu_count()} cores (shared: wall numbers are inflated when others load it)")
        rate = {}
        runs = [("local", 1), ("local", 2)] + ([] if a.no_ray else [("ray", 2)])
        for executor, workers in runs:
            work = Path(tmp) / f"run_{executor}_{workers}"
            shutil.copytree(data, work)
            c0, t0 = cpu_seconds(), time.perf_counter()
            s = run_dataset(work, executor=executor, workers=workers, preset=a.preset, until=a.until,
                            progress=False, echo_stages=False)
            wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
            if s["scenes_failed"]:
                print(f"{executor} workers={workers}: FAILED scenes {s['scenes_failed']}; first failure: "
                      f"{(work / 'batch_failures.jsonl').read_text().splitlines()[0]}")
            rate[(executor, workers)] = s["scenes_per_hour"]
            print(f"{executor:<5} workers={workers}: {a.scenes} scenes in {wall:.0f} s = {s['scenes_per_hour']:.0f} "
                  f"scenes/hour (CPU user+sys of stage processes {cpu:.0f} s" + (", Ray workers' CPU not counted)" if executor == "ray" else ")"))
            if (executor, workers) == ("local", 1):
                print(cost_table(s))
            if executor == "ray":
                import ray

                ray.shutdown()
            else:
                shutil.rmtree(work)
        print(f"speed-up 2 vs 1 local workers: {rate[('local', 2)] / rate[('local', 1)]:.2f}x (target >= 1.7x)")
        if ("ray", 2) in rate:
            print(f"ray vs local at 2 workers: {rate[('ray', 2)] / rate[('local', 2)]:.2f} (target within 20%)")
        if a.no_sweep:
            return
        # The paper's tables at r = 1, 2, 4: one sweep over the tail, depth/mesh/navmesh computed once per scene.
        sweep = Path(tmp) / "sweep"
        shutil.copytree(data, sweep)
        t0 = time.perf_counter()
        s = run_dataset(sweep, workers=2, preset=a.preset, sweeps=[f"trajectory.stride={a.strides}"], progress=False,
                        echo_stages=False)
        print(f"\nsweep trajectory.stride={a.strides} (all stages): {s['runs_ok']}/{s['runs']} runs in "
              f"{time.perf_counter() - t0:.0f} s; stages {s['stages']}")
        result = evaluate_dataset(sweep, EvalParams(max_frames=4, gs_height=64), workers=2, progress=False)
        print("\n\n".join(t.text() for t in result["_tables"]))
        if a.keep:
            shutil.copytree(sweep, a.keep, dirs_exist_ok=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
