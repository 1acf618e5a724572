"""Prints what the code digest in the cache key covers and costs: per stage, the modules it follows (count and lines:
an edit to any of them reruns the stage) and seconds in a fresh process, cold (no digest cache) and warm (the cache a
previous run left), what each stage process and `status` pay."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
STAGES = ["depth", "register", "mesh", "navmesh", "trajectory", "conditions", "video", "poses", "gaussians", "asset"]
PROBE = """
import json, sys, time
t = time.perf_counter()
from panoworld.framework import code_digest
t_import = time.perf_counter() - t
from panoworld.framework.stage import load_stage, unused_backends
skips = {s: unused_backends(spec, spec.params_cls()) for s in sys.argv[1:] for spec in [load_stage(s)]}
out = {}
for s in sys.argv[1:]:
    t = time.perf_counter()
    files = code_digest.code_digests("stages." + s, skip=skips[s])  # the default backend's code, as a run digests it
    seconds = time.perf_counter() - t
    lines = sum(len((code_digest.REPO_ROOT / f).read_text().splitlines()) for f in files)
    out[s] = {"files": len(files), "lines": lines, "seconds": seconds}
print(json.dumps({"import_s": t_import, "stages": out}))
"""


def probe(cache_home: str, stages: list[str]) -> dict:
    env = dict(os.environ, XDG_CACHE_HOME=cache_home, PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", PROBE, *stages], env=env, cwd=REPO, capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as cache:
        for s in STAGES:  # one process per stage, as the runner starts them
            cold_cache = tempfile.mkdtemp(dir=cache)
            cold = probe(cold_cache, [s])["stages"][s]
            warm = probe(cold_cache, [s])["stages"][s]
            rows[s] = {"modules": cold["files"], "lines": cold["lines"], "cold_s": cold["seconds"],
                       "warm_s": warm["seconds"]}
        shared = tempfile.mkdtemp(dir=cache)  # the runner: every stage's digest in one process
        cold_all = probe(shared, STAGES)
        warm_all = probe(shared, STAGES)
    result = {"stages": rows,
              "all_stages_one_process_cold_s": sum(r["seconds"] for r in cold_all["stages"].values()),
              "all_stages_one_process_warm_s": sum(r["seconds"] for r in warm_all["stages"].values())}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print("| stage | modules | lines | cold s | warm s |\n| --- | ---: | ---: | ---: | ---: |")
    for s, r in rows.items():
        print(f"| {s} | {r['modules']} | {r['lines']} | {r['cold_s']:.3f} | {r['warm_s']:.3f} |")
    print(f"\nall {len(STAGES)} stages in one process (what `status` / a no-op run pays): cold "
          f"{result['all_stages_one_process_cold_s']:.3f} s (once per machine, and per edited file), warm "
          f"{result['all_stages_one_process_warm_s']:.3f} s")


if __name__ == "__main__":
    main()
