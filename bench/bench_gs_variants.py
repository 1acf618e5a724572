"""Prints roam PSNR/coverage per distance bucket, Gaussian count, .ply size and times for Gaussian-stage variants and
ERP supersampling factors on scenes already run to `poses` (e.g. kept by `bench_roam.py --out DIR`).

Each variant is a list of gaussians-stage params (KEY=VALUE, as `--set gaussians.KEY=VALUE`), fused from the scene's
video and poses artifacts into a temporary directory; `artifact` is the scene's own gaussians.ply. The pseudo-param
`pole_scale=S` (e.g. `artifact,pole_scale=2`) sets erp_render.ERP_POLE_SCALE, the pole faces of the stage's colour fit
and of the renders, for that variant only. Tune on the VALIDATION seeds of bench_roam.py (1 2 3), never on its test
seeds.

  python bench/bench_gs_variants.py /tmp/roam/seed_1 --variant artifact --supersample 1 2 3
  python bench/bench_gs_variants.py /tmp/roam/seed_1 --variant source_height=256 --variant source_height=512
  python bench/bench_gs_variants.py /tmp/roam/seed_1 --variant pole_scale=2,source_scale=2.1,fit_height=512
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from panoworld.tools.eval.groundtruth import open_ground_truth
from panoworld.tools.eval.roam import BUCKETS, sample_roam_poses, source_seen, split_scores

ARTIFACTS = "artifacts"


def split_variant(variant: str) -> tuple[str, float | None]:
    """'KEY=VALUE,...' -> (the gaussians params, the pole_scale pseudo-param or None)."""
    items = [item for item in variant.split(",") if item]
    pole = [float(item.split("=", 1)[1]) for item in items if item.startswith("pole_scale=")]
    return ",".join(item for item in items if not item.startswith("pole_scale=")), (pole[-1] if pole else None)


def build(scene: Path, variant: str, out: Path) -> tuple[Path, float, float]:
    """The variant's gaussians.ply (fused into `out` unless 'artifact') and its fusion wall and CPU seconds (0 for
    'artifact')."""
    if variant == "artifact":
        return scene / ARTIFACTS / "gaussians" / "gaussians.ply", 0.0, 0.0
    import yaml

    from panoworld.framework.stage_params import params_from_dict
    from stages.gaussians import Params, run

    kv = dict(item.split("=", 1) for item in variant.split(",") if item)
    try:  # flat (source_height) or nested (voxel_fusion.source_height) names, as --set takes them
        params = params_from_dict(Params, {**{k: yaml.safe_load(v) for k, v in kv.items()}, "eval_views": 0}, "gaussians")
    except ValueError as e:
        raise SystemExit(str(e)) from None
    out.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    nav = scene / ARTIFACTS / "navmesh"
    run({"video": scene / ARTIFACTS / "video", "poses": scene / ARTIFACTS / "poses",
         "navmesh": nav if nav.is_dir() else None}, params, out)
    return out / "gaussians.ply", time.perf_counter() - t0, time.process_time() - c0


def render_by_weights(g, pose, height: int, supersample: int):
    """render_erp's colour and alpha from the colour fit's operator (the numba weights kernel; equal to 2e-5,
    tests/test_render_gs.py), several times faster on CPU: (rgb (H, W, 3), alpha (H, W)) tensors."""
    import torch

    from panoworld.render.erp_operator import ErpColorOperator
    from panoworld.render.splats import _prepare

    op = ErpColorOperator(g, pose, height, 2 * height, supersample=supersample)
    return op(_prepare(g, np.asarray(pose, np.float64)[:3, 3]).color), op(torch.ones(len(g), 3))[..., 0]


def measure(scene: Path, ply: Path, supersample: int, views: int, height: int, refs: dict,
            buckets: list[str] | None = None, fast: bool = False) -> dict:
    import cv2

    from panoworld.geometry.navmesh import load_navmesh
    from panoworld.io.splat_ply import read_gaussians_ply
    from panoworld.io.video import load_frames
    from panoworld.render.erp import render_erp
    from panoworld.render.metrics import psnr

    g = read_gaussians_ply(ply)
    nav = load_navmesh(scene / ARTIFACTS / "navmesh")
    gt = open_ground_truth(scene)
    roam = sample_roam_poses(nav, views, seed=0)
    row: dict = {"gaussians": len(g.means), "ply_mb": ply.stat().st_size / 2**20}
    times = []
    for b in BUCKETS:
        if b.key not in roam.poses or (buckets and b.key not in buckets):
            continue
        ps, cov, split = [], [], {}
        for k, pose in enumerate(roam.poses[b.key]):
            t0 = time.perf_counter()
            if fast:
                rgb, alpha = render_by_weights(g, pose, height, supersample)
            else:
                r = render_erp(g, pose, height, 2 * height, supersample=supersample)
                rgb, alpha = r.rgb, r.alpha
            times.append(time.perf_counter() - t0)
            img = (rgb.clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
            cov.append(float((alpha > 0.5).float().mean()))
            if gt.kind == "synthetic":
                key = (b.key, k)
                if key not in refs:
                    refs[key] = gt.render(pose, height, 2 * height)[0], source_seen(gt, pose, height, 2 * height)
                ps.append(psnr(img, refs[key][0]))
                for name, v in split_scores(img, refs[key][0], refs[key][1], alpha.numpy()).items():
                    split.setdefault(name, []).append(v)
            if b.key == "d0" and k == 0:
                pano = next(p for p in (scene / f"panorama.{e}" for e in ("png", "jpg", "jpeg")) if p.is_file())
                ref = cv2.resize(load_frames([pano])[0], (2 * height, height), interpolation=cv2.INTER_AREA)
                row["d0_vs_input"] = psnr(img, ref)
        row[f"{b.key}_psnr"] = float(np.mean(ps)) if ps else None
        row[f"{b.key}_cov"] = float(np.mean(cov))
        for name, vals in split.items():
            row[f"{b.key}_{name.removeprefix('erp_')}"] = float(np.mean(vals))
    row["render_s"] = float(np.median(times))
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--variant", action="append", help="comma-separated KEY=VALUE gaussians params, or 'artifact' "
                    "(default: artifact)")
    ap.add_argument("--supersample", type=int, nargs="+", default=[2])
    ap.add_argument("--views", type=int, default=2, help="roam views per bucket")
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--buckets", nargs="*", help="only these roam buckets (e.g. d0 d1 d2)")
    ap.add_argument("--fast", action="store_true", help="render through the colour fit's operator (numba weights; "
                    "the same images to 2e-5, faster on CPU)")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    import torch

    from panoworld.render import erp as erp_render

    torch.set_num_threads(1)
    variants = a.variant or ["artifact"]
    rows = []
    keys = [b.key for b in BUCKETS if not a.buckets or b.key in a.buckets]
    default_pole = erp_render.ERP_POLE_SCALE
    print(f"{'scene':<10} {'variant':<34} {'ss':>2} {'N':>8} {'MB':>6} {'fuse s':>6} {'cpu s':>6} {'rend s':>6} "
          + " ".join(f"{k + ' dB':>8} {'cov':>6}" for k in keys) + f" {'vs in':>6}")
    with tempfile.TemporaryDirectory(prefix="gs-variants-") as tmp:
        for scene in a.scenes:
            refs: dict = {}
            for vi, variant in enumerate(variants):
                params, pole = split_variant(variant)
                erp_render.ERP_POLE_SCALE = default_pole if pole is None else pole
                ply, fuse_s, fuse_cpu_s = build(scene, params, Path(tmp) / scene.name / str(vi))
                for s in a.supersample:
                    r = measure(scene, ply, s, a.views, a.height, refs, a.buckets, a.fast)
                    r.update(scene=scene.name, variant=variant, supersample=s, fuse_s=fuse_s, fuse_cpu_s=fuse_cpu_s,
                             pole_scale=erp_render.ERP_POLE_SCALE)
                    rows.append(r)

                    def f(v, p=2):
                        return "n/a" if v is None else f"{v:.{p}f}"

                    print(f"{scene.name:<10} {variant:<34} {s:>2} {r['gaussians']:>8} {r['ply_mb']:6.1f} "
                          f"{fuse_s:6.1f} {fuse_cpu_s:6.1f} {r['render_s']:6.2f} "
                          + " ".join(f"{f(r.get(k + '_psnr')):>8} {f(r.get(k + '_cov'), 4):>6}" for k in keys)
                          + f" {f(r.get('d0_vs_input')):>6}", flush=True)
                    print(f"{'':<10} {'seen / unseen dB, unseen px, err share':<34} "
                          + " ".join(f"{f(r.get(k + '_psnr_seen'))}/{f(r.get(k + '_psnr_unseen'))} "
                                     f"{f(r.get(k + '_unseen_fraction'), 3)} {f(r.get(k + '_unseen_error_share'), 3)}"
                                     for k in keys), flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
