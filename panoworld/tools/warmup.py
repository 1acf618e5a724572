"""`runner.py warmup`: compile every numba kernel once per install, so that a first run pays no compilation."""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path


def warmup(preset: str = "ci-tiny") -> tuple[float, list[str]]:
    """Run the whole pipeline on a tiny synthetic scene in a temporary directory: every stage's kernels are compiled
    into numba's on-disk cache (NUMBA_CACHE_DIR, else each package's __pycache__). Returns (seconds, failed stages)."""
    from panoworld.framework import pipeline as pl
    from panoworld.tools.synth.cli import main as synth_main

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="panoworld-warmup-") as tmp:
        scene = Path(tmp) / "scene"
        if synth_main([str(scene), "--seed", "0", "--preset", "ci-tiny"]):
            return time.perf_counter() - t0, ["synth"]
        report = pl.run(scene, preset=preset, echo=False)
    return time.perf_counter() - t0, [r.stage for r in report.results if r.action == "failed"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python runner.py warmup", description=__doc__)
    ap.add_argument("--preset", default="ci-tiny", help="pipeline preset of the tiny run (default ci-tiny)")
    a = ap.parse_args(argv)
    print("warmup: compiling the numba kernels (a tiny pipeline run; once per install)", file=sys.stderr, flush=True)
    seconds, failed = warmup(a.preset)
    if failed:
        print(f"error: warmup: stages {', '.join(failed)} failed on the tiny scene", file=sys.stderr)
        return 1
    print(f"warmup: done in {seconds:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
