"""Layout depth from a camera beside its own room's outline: random room outlines (rectangles, L-shapes, bay-window
corners, rectangles at an angle), the camera inside or outside the polygon near one of its walls, each annotation
rendered as a ZInD tour's layout depth renders it (`tools.synth.annotation.polygon_layout_depth`: from outside, the
floor and ceiling recede for hundreds of metres) and run through `runner.py run DIR --until navmesh` at default
settings, no flags.

    python bench/bench_layout_outside.py [--cases 40] [--seed 1] [--rows 512] [--keep DIR] [--json F]

Per case: the outline's kind and area, the camera's signed distance from the outline (negative inside), the NavMesh
area over the room's floor area (done when <= 1.5), whether the camera stands on the NavMesh or how far from it (the
NavMesh keeps the agent's radius, 0.25 m, and a cell from the walls, so a camera nearer a wall than about 0.33 m stands
beside it), the nearest mesh vertex to the camera (done when >= 0.10 m) and the share of the panorama the depth stage
masked as implausible; then the worst of each over the cases, inside and outside apart."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2
import numpy as np
from real_home_scores import nearest_vertex_m  # bench/, beside this script

from panoworld.geometry.polygons import ring_area
from panoworld.io.jsonio import read_json
from panoworld.tools.synth.annotation import polygon_layout_depth

CAMERA_HEIGHT_M = 1.435
"""The shared ZInD tour's camera height."""
KINDS = ("rectangle", "L", "bay", "turned")


def outline(kind: str, rng: np.random.Generator) -> np.ndarray:
    """A room outline (K, 2) in metres, centred near the origin."""
    w, h = rng.uniform(1.2, 6.0), rng.uniform(1.2, 6.0)
    if kind == "L":
        a, b = rng.uniform(0.3, 0.8) * w, rng.uniform(0.3, 0.8) * h
        p = np.array([(0, 0), (w, 0), (w, b), (a, b), (a, h), (0, h)], float)
    elif kind == "bay":  # one corner cut at 45 degrees
        c = rng.uniform(0.2, 0.45) * min(w, h)
        p = np.array([(0, 0), (w - c, 0), (w, c), (w, h), (0, h)], float)
    else:
        p = np.array([(0, 0), (w, 0), (w, h), (0, h)], float)
    p -= p.mean(0)
    if kind == "turned":
        t = rng.uniform(0.0, np.pi / 2)
        p = p @ np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])
    return p


def camera_beside_a_wall(p: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """A camera position (2,) within 0.8 m of a random wall of p, inside or outside, and its signed distance from the
    polygon's outline (negative inside)."""
    j = rng.integers(len(p))
    a, b = p[j], p[(j + 1) % len(p)]
    e = b - a
    normal = np.array([e[1], -e[0]]) / np.linalg.norm(e)
    cam = a + rng.uniform(0.1, 0.9) * e + rng.uniform(-0.8, 0.8) * normal
    d = cv2.pointPolygonTest(p.astype(np.float32).reshape(-1, 1, 2), (float(cam[0]), float(cam[1])), True)
    return cam, -float(d)


def run_case(k: int, rng: np.random.Generator, rows: int, root: Path) -> dict:
    kind = KINDS[k % len(KINDS)]
    p = outline(kind, rng)
    cam, signed = camera_beside_a_wall(p, rng)
    ceiling = rng.uniform(0.85, 1.2)
    scene = root / f"case_{k:03d}"
    scene.mkdir(parents=True, exist_ok=True)  # --keep DIR again: the runner reruns what the new inputs change
    np.save(scene / "depth.npy", polygon_layout_depth(p, cam, CAMERA_HEIGHT_M, ceiling, rows, 2 * rows))
    texture = np.random.default_rng(k).uniform(90, 170, (rows // 8, rows // 4, 3)).astype(np.float32)
    cv2.imwrite(str(scene / "panorama.png"), cv2.resize(texture, (2 * rows, rows)).astype(np.uint8))
    t0 = time.time()
    r = subprocess.run([sys.executable, str(REPO / "runner.py"), "run", str(scene), "--until", "navmesh"],
                       capture_output=True, text=True)
    row = {"case": k, "kind": kind, "room_m2": round(abs(ring_area(p)), 2), "camera_from_outline_m": round(signed, 3),
           "inside": signed < 0, "exit": r.returncode, "s": round(time.time() - t0, 1)}
    if r.returncode:
        return {**row, "error": (r.stderr.strip().splitlines() or [""])[-1]}
    nav = read_json(scene / "artifacts" / "navmesh" / "manifest.json")["info"]
    plaus = read_json(scene / "artifacts" / "depth" / "manifest.json")["info"].get("plausibility", {})
    return {**row, "navmesh_m2": round(nav["area_m2"], 2), "navmesh_over_room": round(nav["area_m2"] / row["room_m2"], 3),
            "camera_on_navmesh": bool(nav["camera_on_navmesh"]),
            "camera_to_navmesh_m": round(float(nav["camera_distance_to_navmesh_m"]), 3),
            "nearest_vertex_m": round(nearest_vertex_m(scene, {"camera": np.eye(4)})["camera"], 3),
            "masked_implausible": round(float(plaus.get("masked_fraction", 0.0)), 3)}


def summary(rows: list[dict]) -> dict:
    out = {}
    for side, pick in (("inside", True), ("outside", False)):
        ok = [r for r in rows if r["inside"] == pick and not r["exit"]]
        out[side] = {"cases": sum(r["inside"] == pick for r in rows), "failed_runs": sum(r["inside"] == pick and
                     bool(r["exit"]) for r in rows),
                     "max_navmesh_over_room": max((r["navmesh_over_room"] for r in ok), default=None),
                     "min_nearest_vertex_m": min((r["nearest_vertex_m"] for r in ok), default=None),
                     "over_1_5": sum(r["navmesh_over_room"] > 1.5 for r in ok),
                     "vertex_within_0_10": sum(r["nearest_vertex_m"] < 0.10 for r in ok),
                     "camera_on_navmesh": sum(r["camera_on_navmesh"] for r in ok)}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rows", type=int, default=512, help="the layout depth's and the panorama's rows")
    ap.add_argument("--keep", type=Path, help="write the cases' scenes here (default: a temporary folder, removed)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        print("| case | outline | room m² | camera from outline m | NavMesh m² | NavMesh / room | camera on it | "
              "nearest vertex m | masked implausible | s |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for k in range(args.cases):
            r = run_case(k, rng, args.rows, root)
            rows.append(r)
            if r["exit"]:
                print(f"| {k} | {r['kind']} | {r['room_m2']} | {r['camera_from_outline_m']:+.2f} | exit {r['exit']}: "
                      f"{r['error']} | | | | | {r['s']} |", flush=True)
                continue
            on = "yes" if r["camera_on_navmesh"] else f"{r['camera_to_navmesh_m']:.2f} m off"
            print(f"| {k} | {r['kind']} | {r['room_m2']} | {r['camera_from_outline_m']:+.2f} | {r['navmesh_m2']} | "
                  f"{r['navmesh_over_room']:.2f} | {on} | "
                  f"{r['nearest_vertex_m']:.3f} | {r['masked_implausible']:.1%} | {r['s']} |", flush=True)
    s = summary(rows)
    print("\n| camera | cases | runs failed | max NavMesh / room | NavMesh > 1.5 x room | min nearest vertex m | "
          "vertex within 0.10 m | camera on NavMesh |")
    print("|---|---|---|---|---|---|---|---|")
    for side, v in s.items():
        fmt = lambda x, f: "-" if x is None else format(x, f)
        print(f"| {side} its outline | {v['cases']} | {v['failed_runs']} | {fmt(v['max_navmesh_over_room'], '.2f')} | "
              f"{v['over_1_5']} | {fmt(v['min_nearest_vertex_m'], '.3f')} | {v['vertex_within_0_10']} | "
              f"{v['camera_on_navmesh']} |")
    if args.json:
        args.json.write_text(json.dumps({"seed": args.seed, "rows": args.rows, "cases": rows, "summary": s}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
