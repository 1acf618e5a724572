"""Prints how far the explore paths reach in each sector (eval's trajectory_reach) and their step, per trajectory setting.

    python bench/bench_reach.py SCENE [SCENE ...] [--variant reach_m=3] [--variant max_step_m=0.25] [--json FILE]

SCENE: a scene directory run to `navmesh` at least (runner.py run SCENE --until navmesh). Each variant plans the
trajectory with those TrajectoryParams overrides (comma-separated KEY=VALUE; "" = the defaults) and scores the
planned poses with `panoworld.tools.eval.roam.trajectory_reach`: per sector the farthest pose against the distance walkable
from the capture point straight along the sector's centre (target: min fraction >= 0.7).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.geometry.navmesh import load_navmesh
from panoworld.tools.eval.roam import trajectory_reach
from panoworld.trajectory import TrajectoryParams, plan_path, poses_from_positions


def parse_variant(text: str) -> TrajectoryParams:
    fields = {f.name: f for f in dataclasses.fields(TrajectoryParams)}
    kw = {}
    for item in filter(None, text.split(",")):
        key, value = item.split("=", 1)
        kw[key] = None if value.lower() == "none" else type(getattr(TrajectoryParams(), key) or 0.0)(value)
        if key not in fields:
            raise SystemExit(f"--variant {text}: unknown trajectory param {key}")
    return TrajectoryParams(**kw)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--variant", action="append", help='TrajectoryParams overrides, e.g. "reach_m=3" ("" = defaults)')
    ap.add_argument("--json", type=Path, help="also write the rows as JSON")
    a = ap.parse_args()
    variants = a.variant or ["", "reach_m=3"]
    rows = []
    print("| scene | variant | min sector reach | reached / reachable m (worst sector) | farthest pose m | mean step m |")
    print("|---|---|---|---|---|---|")
    for scene in a.scenes:
        nav = load_navmesh(scene / "artifacts" / "navmesh")
        for v in variants:
            plan = plan_path(nav, parse_variant(v))
            r = trajectory_reach(nav, poses_from_positions(plan.positions))
            frac = [min(x / y, 1.0) if y >= 0.1 else None for x, y in zip(r["sector_reached_m"], r["sector_reachable_m"])]
            k = min((i for i, f in enumerate(frac) if f is not None), key=lambda i: frac[i])
            rows.append({"scene": scene.name, "variant": v or "defaults", "step_m": plan.step_m, **r})
            print(f"| {scene.name} | {v or 'defaults'} | {r['sector_reach_fraction_min']:.2f} | "
                  f"{r['sector_reached_m'][k]:.2f} / {r['sector_reachable_m'][k]:.2f} | {r['reach_max_m']:.2f} | "
                  f"{plan.step_m:.3f} |")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
