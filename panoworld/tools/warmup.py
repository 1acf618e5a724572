"""`runner.py warmup`: compile every numba kernel of a pipeline run once per install, so that a first run pays no
compilation (the runner also starts this in the background when it finds numba's cache cold)."""

from __future__ import annotations

import argparse
import sys
import time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python runner.py warmup", description=__doc__)
    ap.parse_args(argv)
    from panoworld.framework.kernels import cache_dir, compile_and_stamp, row_line

    print(f"warmup: compiling the numba kernels into {cache_dir()} (once per install)", file=sys.stderr, flush=True)
    t0, c0 = time.perf_counter(), time.process_time()

    rows = compile_and_stamp(lambda r: print(f"  {row_line(r)}", file=sys.stderr, flush=True))
    failed = [r["kernel"] for r in rows if r["error"]]
    print(f"warmup: {len(rows)} kernels, {sum(not r['cached'] for r in rows)} compiled, in "
          f"{time.perf_counter() - t0:.1f} s ({time.process_time() - c0:.1f} s CPU)", file=sys.stderr)
    if failed:
        print(f"error: warmup: {', '.join(failed)} did not compile (the stages compile them when they call them)",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
