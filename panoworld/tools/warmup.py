"""`runner.py warmup`: compile every numba kernel of a pipeline run once per install, so that a first run pays no
compilation (the runner also starts this in the background when it finds numba's cache cold)."""

from __future__ import annotations

import argparse
import sys
import time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python runner.py warmup", description=__doc__)
    ap.parse_args(argv)
    from panoworld.framework.kernels import cache_dir, compile_and_stamp

    print(f"warmup: compiling the numba kernels into {cache_dir()} (once per install)", file=sys.stderr, flush=True)
    t0, c0 = time.perf_counter(), time.process_time()

    def row(r: dict) -> None:
        print(f"  {r['stage']:<11} {r['kernel']:<34} {'cached' if r['cached'] else 'compiled':<9} {r['seconds']:6.2f} s CPU",
              file=sys.stderr, flush=True)

    rows = compile_and_stamp(row)
    print(f"warmup: {len(rows)} kernels, {sum(not r['cached'] for r in rows)} compiled, in "
          f"{time.perf_counter() - t0:.1f} s ({time.process_time() - c0:.1f} s CPU)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
