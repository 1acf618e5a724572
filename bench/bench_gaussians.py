"""Novel-view and context-view quality of voxel-fusion Gaussians on synthetic ground truth (the paper's N@N protocol).

For each scene seed: 2N frames uniformly spaced along GT track 0 are rendered (RGB + exact depth + poses); the even
ones are the N context views fused into Gaussians, the odd ones are the N held-out novel views. Gaussians are rendered
as ERP at every view and compared with the ground truth (PSNR, WS-PSNR, SSIM over the full panorama, holes included).

    python bench/bench_gaussians.py [--seeds 0 1 2] [--height 256] [--views 4] [--supersample 1 2] [--set voxel_size=0.02]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.framework.stage_params import params_from_dict
from panoworld.gaussians.fusion import FusionParams, uniform_subset, voxel_fusion
from panoworld.render.erp import render_erp
from panoworld.render.metrics import psnr, ssim, ws_psnr
from panoworld.tools.synth import generate_scene


def evaluate(gaussians, poses, frames, H):
    rows = []
    for pose, gt in zip(poses, frames):
        out = render_erp(gaussians, pose, H, 2 * H)
        img = (out.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        rows.append((psnr(img, gt), ws_psnr(img, gt), ssim(img, gt), float(out.alpha.mean())))
    return np.array(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--height", type=int, default=256, help="ERP height of frames and renders (width = 2x)")
    ap.add_argument("--views", type=int, default=4, help="N of N@N: context views = novel views = N")
    ap.add_argument("--supersample", type=int, nargs="+", default=[2, 1],
                    help="GT RGB supersampling per axis (2 = area-sampled pixels like a camera; 1 = aliased point samples)")
    ap.add_argument("--set", action="append", default=[], help="FusionParams override NAME=VALUE (repeatable)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    params = params_from_dict(FusionParams, dict(kv.split("=", 1) for kv in args.set), where="--set")
    print(f"voxel-fusion {dataclasses.asdict(params)}")
    print(f"{args.views}@{args.views}, ERP {2 * args.height}x{args.height}, torch threads {args.threads} "
          "(timings on a shared CPU are inflated)")
    H = args.height
    summary = {ss: {"ctx": [], "nov": []} for ss in args.supersample}
    for seed in args.seeds:
        scene = generate_scene(seed)
        track = scene.tracks[0].world_from_cam
        idx = uniform_subset(range(len(track)), 2 * args.views)
        ctx, nov = idx[0::2], idx[1::2]
        for ss in args.supersample:
            t0 = time.perf_counter()
            frames = {i: scene.render(track[i], H, 2 * H, supersample=ss) for i in idx}
            t_gt = time.perf_counter() - t0
            t0 = time.perf_counter()
            res = voxel_fusion([(*frames[i], track[i]) for i in ctx], params)
            t_fuse = time.perf_counter() - t0
            t0 = time.perf_counter()
            c = evaluate(res.gaussians, track[ctx], [frames[i][0] for i in ctx], H)
            n = evaluate(res.gaussians, track[nov], [frames[i][0] for i in nov], H)
            t_render = (time.perf_counter() - t0) / len(idx)
            summary[ss]["ctx"].append(c)
            summary[ss]["nov"].append(n)
            span = np.linalg.norm(track[idx[-1]][:3, 3] - track[idx[0]][:3, 3])
            print(
                f"seed {seed} supersample {ss}: {len(res.gaussians)} Gaussians from {res.num_observations} pixels "
                f"(track span {span:.2f} m) | context PSNR {c[:, 0].mean():.2f} WS-PSNR {c[:, 1].mean():.2f} "
                f"SSIM {c[:, 2].mean():.3f} | novel PSNR {n[:, 0].mean():.2f} WS-PSNR {n[:, 1].mean():.2f} "
                f"SSIM {n[:, 2].mean():.3f} coverage {n[:, 3].mean():.3f} | GT {t_gt:.1f} s, fusion {t_fuse:.1f} s, "
                f"ERP render {t_render:.1f} s/view"
            )
    for ss, s in summary.items():
        c, n = np.concatenate(s["ctx"]), np.concatenate(s["nov"])
        print(
            f"MEAN supersample {ss}: context PSNR {c[:, 0].mean():.2f} (target >= 26) WS-PSNR {c[:, 1].mean():.2f} "
            f"SSIM {c[:, 2].mean():.3f} | novel PSNR {n[:, 0].mean():.2f} (target >= 22) WS-PSNR {n[:, 1].mean():.2f} "
            f"SSIM {n[:, 2].mean():.3f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
