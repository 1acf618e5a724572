"""Prints how long a no-op `runner.py run` of an up-to-date scene takes, wall and CPU (target: 0.3 s on the demo):
a ci-tiny scene made and run here, or `--scene DIR`, an up-to-date scene of yours (e.g. demo_out/scene). `--decide`:
each run after a file made and removed in the scene folder, so that it decides every stage again instead of replaying
the last no-op (what the first no-op after an edit costs)."""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def noop_times(scene: Path, runs: int, extra: list[str], decide: bool = False) -> tuple[list[float], list[float]]:
    """(wall s, CPU s) of `runs` no-op `runner.py run` processes (decide: each after a change of the scene folder's
    stat); AssertionError when one runs a stage."""
    walls, cpus = [], []
    for _ in range(runs):
        if decide:
            (scene / ".bench_runner").touch()
            (scene / ".bench_runner").unlink()
        c0, t0 = _cpu(), time.perf_counter()
        out = subprocess.run([sys.executable, "runner.py", "run", str(scene), *extra, "--json"], cwd=REPO, check=True,
                             capture_output=True, text=True)
        walls.append(time.perf_counter() - t0)
        cpus.append(_cpu() - c0)
        assert '"ran"' not in out.stdout, "expected a no-op run"
    return walls, cpus


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", type=Path, help="an up-to-date scene (default: a ci-tiny scene made and run here)")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--decide", action="store_true", help="make each run decide every stage (no replay)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        extra: list[str] = []
        scene = a.scene
        if scene is None:
            scene, extra = Path(tmp) / "scene", ["--preset", "ci-tiny"]
            subprocess.run([sys.executable, "runner.py", "synth", str(scene), "--seed", "0", "--preset", "ci-tiny"],
                           cwd=REPO, check=True, capture_output=True)
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "runner.py", "run", str(scene), *extra], cwd=REPO, check=True,
                           capture_output=True)
            print(f"full ci-tiny pipeline run: {time.perf_counter() - t0:.1f} s")
        walls, cpus = noop_times(scene, a.runs, extra, a.decide)
        print(f"no-op run of {scene} (whole CLI process, {a.runs} runs{', each deciding' if a.decide else ''}): wall median {statistics.median(walls):.3f} s, "
              f"min {min(walls):.3f} s; CPU median {statistics.median(cpus):.3f} s, min {min(cpus):.3f} s; load average "
              f"{open('/proc/loadavg').read().split()[0]} (target 0.3 s wall on an idle machine)")


if __name__ == "__main__":
    main()
