"""Prints how long a no-op `runner.py run` of an up-to-date ci-tiny scene takes (target: under 1 s)."""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene"
        subprocess.run([sys.executable, "runner.py", "synth", str(scene), "--seed", "0", "--preset", "ci-tiny"], cwd=REPO, check=True,
                       capture_output=True)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "runner.py", "run", str(scene), "--preset", "ci-tiny"], cwd=REPO, check=True, capture_output=True)
        full = time.perf_counter() - t0
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "runner.py", "run", str(scene), "--preset", "ci-tiny", "--json"], cwd=REPO,
                                 check=True, capture_output=True, text=True)
            times.append(time.perf_counter() - t0)
            assert '"ran"' not in out.stdout, "expected a no-op run"
        print(f"full ci-tiny pipeline run: {full:.1f} s")
        print(f"no-op run (whole CLI process, median of 5): {statistics.median(times):.3f} s  (target < 1 s)")


if __name__ == "__main__":
    main()
