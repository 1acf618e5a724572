"""The simulation asset on the demo scene and the Realsee3D capture: sizes, export time and the consumer checks.

    python bench/bench_asset.py [--scene DIR ...] [--work DIR] [--real DIR] [--preset default] [--as-is] [--json]

Without --scene: the demo scene (`runner.py demo` into --work) and the Realsee3D real LiDAR pair under --real (the
panorama + depth_image.png copied into a scene directory under --work). Each scene runs the pipeline up to `asset`
(cached stages are reused), then the asset stage alone again, timed (wall and CPU of the stage process). Prints per
scene: particles, collider triangles and how far they stray from the mesh (asset.collider.surface_error, beside the
mesh's own), file sizes (MB), export wall/CPU seconds (target <= 15 s at the default preset), usd-core validation
errors, and the PyBullet checks: capsule drop at the spawn (rest height, speed; a home's at every capture point too),
walk along the plan (least clearance of the swept capsule), push into the nearest wall (stop gap, deepest penetration
on the way).
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from panoworld.asset import trajectory_paths
from panoworld.asset.physics import Agent, BulletScene, drop_ok, drop_test, walk_test, wall_ok, wall_test
from panoworld.asset.usd import compliance_errors
from panoworld.core.conventions import transform_points
from panoworld.framework import pipeline as pl
from panoworld.io.manifest import read_manifest

REAL = REPO.parent / "shared" / "data" / "real" / "realsee3d_assets"


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def scenes_default(work: Path, real: Path, preset: str) -> list[tuple[str, Path]]:
    out = []
    demo = work / "demo" / "scene"
    if not (demo / "panorama.png").is_file():
        subprocess.run([sys.executable, "runner.py", "demo", str(work / "demo"), "--preset", preset], cwd=REPO,
                       check=True)
    out.append(("demo", demo))
    if (real / "panoImage_real.jpg").is_file():
        d = work / "realsee_real"
        d.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(real / "panoImage_real.jpg", d / "panorama.jpg")
        shutil.copyfile(real / "depth_image.png", d / "depth.png")
        out.append(("realsee real", d))
    return out


def measure(name: str, scene: Path, preset: str | None, as_is: bool = False) -> dict:
    arts = scene / "artifacts"
    if as_is:  # the stage alone on the artifacts as they are (no cache check: upstream code may have changed since)
        cmd = [sys.executable, "-m", "stages.asset", "--out", str(arts / "asset")]
        cmd += [a for k in ("gaussians", "mesh", "navmesh", "trajectory", "register") if (arts / k).is_dir()
                for a in (f"--{k}", str(arts / k))]
    else:
        rep = pl.run(scene, preset=preset, until="asset", echo=False)
        if not rep.ok:
            raise SystemExit(f"{scene}: pipeline failed\n{rep.table()}")
        cmd = [sys.executable, "runner.py", "run", str(scene), "--only", "asset", "--force"]
        cmd += ["--preset", preset] if preset else []
    cpu0, t0 = _children_cpu(), time.perf_counter()
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=False)
    wall_s, cpu = time.perf_counter() - t0, _children_cpu() - cpu0
    if res.returncode != 0:
        raise SystemExit(f"{scene}: asset stage failed\n{res.stderr}")
    a = scene / "artifacts" / "asset"
    info = read_manifest(a)["info"]
    doc = json.loads((a / "asset.json").read_text())
    problems = compliance_errors(a / "scene.usdc")
    ag = doc["agent"]
    agent = Agent(radius=ag["agent_radius_m"], height=ag["agent_height_m"], step_height=ag["step_height_m"])
    spawn = np.array(doc["spawn"])
    paths, _ = trajectory_paths(scene / "artifacts" / "trajectory")
    with BulletScene(a / "collider.obj", agent) as sim:
        drop = drop_test(sim, spawn, drop_m=0.5)
        points = {n: drop_test(sim, np.array(cp["spawn"]), drop_m=0.5)
                  for n, cp in doc.get("capture_points", {}).items()}
        walks = [walk_test(sim, transform_points(np.array(doc["asset_from_canonical"]), p[:, :3, 3])[:, :2], 0.0)
                 for p in paths]
        try:
            wall = wall_test(sim, spawn)
        except ValueError as e:
            wall = {"error": str(e)}
    return {
        "scene": name, "particles": info["particles"], "sh_degree": info["sh_degree"],
        "collider_triangles": info["collider_triangles"], "mesh_faces_valid": info["collider"]["faces_valid"],
        "sizes_mb": info["sizes_mb"], "export_wall_s": wall_s, "export_cpu_s": cpu, "stage_export_s": info["export_s"],
        "collider": info["collider"], "timings_s": info["timings_s"], "compliance_errors": len(problems),
        "spawn_source": info["spawn_source"],
        "drop": drop, "drop_ok": drop_ok(drop), "capture_drops": points,
        "capture_drops_ok": sum(drop_ok(d) for d in points.values()),
        "walk": walks, "walk_ok": all(w["min_clearance_m"] > 0 for w in walks),
        "wall": wall, "wall_ok": "gap_m" in wall and wall_ok(wall),
    }


def print_rows(rows: list[dict]) -> None:
    head = ["scene", "particles", "collider tris", "scene.usdc MB", "collider.obj MB", "export wall s", "export CPU s",
            "validation errors", "drop", "walk", "wall"]
    print("| " + " | ".join(head) + " |\n|" + " --- |" * len(head))
    for r in rows:
        d, w = r["drop"], r["wall"]
        walk = min(x["min_clearance_m"] for x in r["walk"])
        wall = (f"stopped {w['gap_m'] * 100:+.1f} cm before the centre-line "
                f"{'wall' if w.get('flat') else 'obstacle (no flat wall around)'}, contact "
                f"{w['obstacle_contact_m'] * 100:.1f} cm, deepest {w['deepest_m'] * 100:.1f} cm" if "gap_m" in w
                else w.get("error", "?"))
        c = r["collider"]
        err = (f"; off the mesh {c['error_m'][-1] * 100:.1f} cm, its own {c['own_error_m'] * 100:.1f}"
               if c.get("error_m") else "")
        cells = [r["scene"], f"{r['particles']:,}", f"{r['collider_triangles']:,} (of {r['mesh_faces_valid']:,}{err})",
                 f"{r['sizes_mb']['scene.usdc']:.1f}", f"{r['sizes_mb']['collider.obj']:.1f}",
                 f"{r['export_wall_s']:.1f}", f"{r['export_cpu_s']:.1f}", str(r["compliance_errors"]),
                 f"{'pass' if r['drop_ok'] else 'FAIL'} (rest {d['rest_height_m'] * 100:+.1f} cm"
                 + (f"; rests at {r['capture_drops_ok']} of {len(r['capture_drops'])} capture points"
                    if r["capture_drops"] else "") + ")",
                 f"{'pass' if r['walk_ok'] else 'FAIL'} (min clearance {walk * 100:.1f} cm)",
                 f"{'pass' if r['wall_ok'] else 'FAIL'} ({wall})"]
        print("| " + " | ".join(cells) + " |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, action="append", help="an existing scene directory (repeatable)")
    ap.add_argument("--work", type=Path, default=REPO / "bench_out" / "asset", help="where the default scenes go")
    ap.add_argument("--real", type=Path, default=REAL, help="the Realsee3D asset folder")
    ap.add_argument("--preset", default=None, help="pipeline preset (default: the scene's own, else default)")
    ap.add_argument("--as-is", action="store_true",
                    help="run the asset stage alone on the scenes' artifacts as they are (no pipeline run)")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    a = ap.parse_args()
    scenes = ([(s.name, s) for s in a.scene] if a.scene
              else scenes_default(a.work, a.real, a.preset or "default"))
    load = open("/proc/loadavg").read().split()[0]
    rows = [measure(name, scene, a.preset, a.as_is) for name, scene in scenes]
    if a.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"load average {load} at start on {subprocess.run(['nproc'], capture_output=True, text=True).stdout.strip()} "
          "cores (a shared machine inflates wall times; CPU seconds are the stage process's user + system)")
    print_rows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
