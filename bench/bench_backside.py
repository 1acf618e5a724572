"""Prints, per roam bucket of synthetic scenes already run to `gaussians`, the share of pixels where a view sees the
source's surfaces from behind (a thin wall's other side) and the PSNR of the Gaussians there and elsewhere.

A pixel sees a surface from behind when its ray's first hit on the scene's mesh artifact (the source depth's mesh
without its stretched faces, which the Gaussians do not have either) is a face whose side facing the view is not the side facing the capture point (faces seen
under 6 degrees or less from the capture point are left out). Each `--ply NAME=PATH` is scored on the same pixels
(`artifact`: the scene's own gaussians.ply); roam poses as bench_gs_variants (seed 0). Tune on VALIDATION seeds only.

  python bench/bench_backside.py /work/runs/s9/val/seed_4 --buckets d0 d1 d2 far --ply back=/tmp/g/gaussians.ply
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

ARTIFACTS = "artifacts"
EDGE_ON = 0.1
"""Faces whose normal is within this cosine of perpendicular to the capture point's ray are neither side."""


def behind_mask(mesh, caster, pose: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) bool: the view at pose (canonical world_from_cam) sees a mesh face from the side away from the capture
    point (the canonical origin)."""
    hits = caster.render_erp(pose, height, width)
    face = hits.face
    ok = face >= 0
    f = mesh.faces[np.where(ok, face, 0)]
    v = mesh.vertices
    p = v[f].mean(-2)
    n = np.cross(v[f[..., 1]] - v[f[..., 0]], v[f[..., 2]] - v[f[..., 0]])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    to_src = -p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
    to_view = pose[:3, 3] - p
    s_src = (to_src * n).sum(-1)
    s_view = (to_view * n).sum(-1)
    return ok & mesh.face_valid[np.where(ok, face, 0)] & (np.abs(s_src) > EDGE_ON) & (s_src * s_view < 0)


def measure(scene: Path, plys: dict[str, Path], buckets: list[str], views: int, height: int,
            behind_views_only: bool = False) -> dict:
    from panoworld.geometry.erp_mesh import load_erp_mesh
    from panoworld.geometry.navmesh import load_navmesh
    from panoworld.geometry.raycast import Raycaster
    from panoworld.io.splat_ply import read_gaussians_ply
    from panoworld.render.erp import render_erp
    from panoworld.tools.eval.groundtruth import open_ground_truth
    from panoworld.tools.eval.roam import sample_roam_poses

    mesh = load_erp_mesh(scene / ARTIFACTS / "mesh")
    mesh.faces = mesh.faces[mesh.face_valid]
    mesh.face_valid = mesh.face_valid[mesh.face_valid]
    caster = Raycaster(mesh.vertices, mesh.faces)
    gt = open_ground_truth(scene)
    roam = sample_roam_poses(load_navmesh(scene / ARTIFACTS / "navmesh"), views, seed=0)
    W = 2 * height
    refs = {}
    for key in buckets:
        for k, pose in enumerate(roam.poses.get(key, [])):
            refs[key, k] = gt.render(pose, height, W)[0].astype(np.float64), behind_mask(mesh, caster, pose, height, W)
    out: dict = {}
    for name, ply in plys.items():
        g = read_gaussians_ply(ply)
        row: dict = {"gaussians": len(g.means), "ply_mb": ply.stat().st_size / 2**20}
        for key in buckets:
            acc = {"all": [0.0, 0], "behind": [0.0, 0], "rest": [0.0, 0]}
            per_view = []
            for k, pose in enumerate(roam.poses.get(key, [])):
                ref, back = refs[key, k]
                per_view.append(float(back.mean()))
                if behind_views_only and not back.any():
                    continue
                img = (render_erp(g, pose, height, W).rgb.clamp(0, 1).numpy() * 255.0).round()
                err = ((img - ref) ** 2).mean(-1)
                for part, m in (("all", np.ones_like(back)), ("behind", back), ("rest", ~back)):
                    acc[part][0] += float(err[m].sum())
                    acc[part][1] += int(m.sum())
            row[key] = {"behind_share": float(np.mean(per_view)) if per_view else 0.0, "behind_share_views": per_view,
                        **{f"psnr_{part}": (10 * np.log10(255.0**2 / (se / n)) if n and se > 0 else None)
                           for part, (se, n) in acc.items()}}
        out[name] = row
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--ply", action="append", default=[], help="NAME=PATH of another gaussians.ply (repeatable; "
                    "with one scene)")
    ap.add_argument("--behind-views-only", action="store_true", help="render only the views that see something "
                    "from behind (PSNR all / rest then cover those views only)")
    ap.add_argument("--no-artifact", action="store_true", help="score only the --ply files")
    ap.add_argument("--buckets", nargs="*", default=["d0", "d1", "d2", "far"])
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    if a.ply and len(a.scenes) > 1:
        raise SystemExit("--ply: give one scene")
    res = {}
    print("| scene | variant | N | MB | bucket | seen from behind % (per view) | PSNR all | behind | rest |\n"
          "|---|---|---|---|---|---|---|---|---|")
    for scene in a.scenes:
        plys = {} if a.no_artifact else {"artifact": scene / ARTIFACTS / "gaussians" / "gaussians.ply"}
        plys.update({kv.split("=", 1)[0]: Path(kv.split("=", 1)[1]) for kv in a.ply})
        res[str(scene)] = rows = measure(scene, plys, a.buckets, a.views, a.height, a.behind_views_only)

        def f(v):
            return "n/a" if v is None else f"{v:.2f}"

        for name, row in rows.items():
            for key in a.buckets:
                r = row[key]
                print(f"| {scene.name} | {name} | {row['gaussians']} | {row['ply_mb']:.1f} | {key} | "
                      f"{100 * r['behind_share']:.2f} ({', '.join(f'{100 * s:.1f}' for s in r['behind_share_views'])}) | "
                      f"{f(r['psnr_all'])} | {f(r['psnr_behind'])} | {f(r['psnr_rest'])} |", flush=True)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
