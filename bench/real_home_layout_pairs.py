"""The layout pairs of a home's registration against its survey: per pair tried by layout (registration.json), the
best and best distinct score, their ratio, the layout pose's distance and yaw error against the ZInD survey, and
whether it became an edge or why not.

`python bench/real_home_layout_pairs.py REGISTER_ARTIFACT SURVEY_JSON [--json]`"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from bench_real_home import survey_poses  # bench/, beside this script


def layout_pairs(registration: dict, survey: dict) -> list[dict]:
    """One row per pair that registration.json says layout tried, with its error against the survey."""
    world = survey_poses(survey)
    rows = []
    for r in registration["pairs"]:
        if "layout_score" not in r:
            continue
        gt = np.linalg.inv(world[r["a"]]) @ world[r["b"]]
        gt_yaw = math.degrees(math.atan2(gt[0, 2] - gt[2, 0], gt[0, 0] + gt[2, 2]))
        rows.append({"a": r["a"], "b": r["b"], "score": r["layout_score"], "second": r["layout_second"],
                     "ratio": round(r["layout_score"] / max(r["layout_second"], 1e-9), 3),
                     "err_m": round(float(np.hypot(r["layout_xz_m"][0] - gt[0, 3], r["layout_xz_m"][1] - gt[2, 3])), 3),
                     "yaw_err_deg": round(abs((r["layout_yaw_deg"] - gt_yaw + 180) % 360 - 180), 2),
                     "edge": r.get("edge"), "refused": r.get("layout_refused", "")})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("register", type=Path, help="a register artifact (holds registration.json)")
    ap.add_argument("survey", type=Path, help="survey.json")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rows = layout_pairs(json.loads((args.register / "registration.json").read_text()),
                        json.loads(args.survey.read_text()))
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print("| pair | score | best distinct | ratio | error m | yaw error deg | edge | refused |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['a']}-{r['b']} | {r['score']:.0f} | {r['second']:.0f} | {r['ratio']:.2f} | {r['err_m']:.2f} | "
              f"{r['yaw_err_deg']:.1f} | {r['edge'] or '-'} | {r['refused']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
