"""Prints how well warp-inpaint fills the disoccluded pixels of a synthetic scene's video, against the ground truth.

    python bench/bench_warp_fill.py SCENE [--paths 0 2 4 6] [--height 180] [--side-depth 0 0.5] [--reuse]
        [--variant layout_planes=1,color_sigma_px=2 ...]

SCENE: a synthetic scene (runner.py synth; tune on validation seeds only) run to `conditions` at least. Every frame
of the chosen paths is filled in path order (as the video stage does) with the default fill, each
`video.warp.side_depth_m` asked for and each `video.warp.edge_depth_ratio`, (--reuse) `video.warp.reuse`, and its hole pixels (conditions mask 0) are
scored against the anti-aliased ground truth at the same pose: PSNR over the holes and per true surface (floor /
walls / ceiling / object side / top / underside: roam.unseen_parts), the share of hole pixels given depth (those
become Gaussians), the share whose depth is within 10 % of the truth, and the fill time; below each row, per source
(background layer / 2D fill) and per true surface: share of the hole pixels, depth within 10 %, PSNR.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.geometry.erp_mesh import load_erp_mesh
from panoworld.io.conditions import load_conditions
from panoworld.io.trajectory import load_clips, load_trajectory
from panoworld.tools.eval.groundtruth import GroundTruth
from panoworld.tools.eval.roam import UNSEEN_PARTS, unseen_parts
from panoworld.video import background_layer, inpaint


def psnr(se: float, n: int) -> str:
    return f"{10 * np.log10(255.0**2 / max(se / n, 1e-12)):.2f}" if n else "-"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--paths", type=int, nargs="*", default=[0, 2, 4, 6], help="which paths (clips) to fill")
    ap.add_argument("--height", type=int, default=180, help="rows the frames are scored at (area-downsampled)")
    ap.add_argument("--side-depth", type=float, nargs="*", default=[0.0], help="video.warp.side_depth_m values")
    ap.add_argument("--edge-ratio", type=float, nargs="*", default=[0.95],
                    help="video.warp.edge_depth_ratio values (each with the first side depth)")
    ap.add_argument("--reuse", action="store_true", help="also video.warp.reuse (default side depth)")
    ap.add_argument("--variant", action="append", default=[],
                    help="KEY=VAL[,KEY=VAL]: keyword arguments of build_background_layer / WarpInpainter (repeatable), "
                         "e.g. layout_planes=1,color_sigma_px=2; each after the flags' variants")
    ap.add_argument("--variants-only", action="store_true", help="only the --variant rows (no flag variants)")
    ap.add_argument("--stride", type=int, default=1, help="score every n-th frame (all are filled)")
    ap.add_argument("--max-dist", type=float, default=float("inf"),
                    help="score only frames at most this far (m) from the capture point (e.g. 1.5: the ~1 m bucket)")
    a = ap.parse_args()
    art = a.scene / "artifacts"
    cond = load_conditions(art / "conditions")
    poses = load_trajectory(art / "trajectory")
    clips = load_clips(art / "trajectory", len(poses))
    mesh = load_erp_mesh(art / "mesh")
    gt = GroundTruth(a.scene / "gt", supersample=2)
    h, w = a.height, 2 * a.height
    frames = [i for k in a.paths if k < len(clips) for i in clips[k][1:]]
    near = [i for i in frames if np.linalg.norm(poses[i][:3, 3]) <= a.max_dist]
    scored = set(near[a.stride - 1::a.stride])
    print(f"{a.scene}: paths {a.paths} of {len(clips)} ({len(frames)} frames, {len(scored)} scored), scored at {h}x{w}")
    print("| fill | hole PSNR | " + " | ".join(UNSEEN_PARTS) + " | with depth | depth within 10 % | fill s |\n|---|"
          + "---|" * (len(UNSEEN_PARTS) + 4))
    variants = [dict(side_depth_m=s, edge_depth_ratio=a.edge_ratio[0]) for s in a.side_depth]
    variants += [dict(side_depth_m=a.side_depth[0], edge_depth_ratio=r) for r in a.edge_ratio[1:]]
    variants += [dict(side_depth_m=a.side_depth[0], edge_depth_ratio=a.edge_ratio[0], reuse=True)] if a.reuse else []
    variants += [{"side_depth_m": a.side_depth[0], "edge_depth_ratio": a.edge_ratio[0]}
                 | {k: float(v) for k, v in (kv.split("=") for kv in spec.split(","))} for spec in a.variant]
    variants = variants[len(variants) - len(a.variant):] if a.variants_only else variants
    filler_keys = set(inspect.signature(inpaint.WarpInpainter).parameters)
    truth = {}
    for var in variants:
        layer = background_layer.build_background_layer(mesh, inpaint.max_translation(poses),
                                               **{k: v for k, v in var.items() if k not in filler_keys})
        filler = inpaint.WarpInpainter(layer, **{k: bool(v) if k in ("reuse", "depth_fill") else v
                                                 for k, v in var.items() if k in filler_keys})
        se, n = np.zeros(len(UNSEEN_PARTS) + 1), np.zeros(len(UNSEEN_PARTS) + 1, np.int64)
        with_depth = right = holes = 0
        split = np.zeros((2 + len(UNSEEN_PARTS), 3))  # rows: layer, 2D fill, per part; cols: pixels, depth right, se
        seconds = 0.0
        for i in frames:
            t0 = time.perf_counter()
            f = filler.fill(cond.rgb[i], cond.mask[i], cond.depth[i], poses[i])
            seconds += time.perf_counter() - t0
            hole = ~cond.mask[i]
            if i not in scored:
                continue
            if i not in truth:
                H, W = hole.shape
                truth[i] = (gt.render(poses[i], h, w)[0], gt.depth(poses[i], H, W), unseen_parts(gt, poses[i], h, w))
            ref, ref_d, part = truth[i]
            holes += int(hole.sum())
            with_depth += int((f.depth[hole] > 0).sum())
            right += int((np.abs(f.depth - ref_d) <= 0.1 * ref_d)[hole].sum())
            small = cv2.resize(f.rgb, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)
            hs = cv2.resize(hole.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
            err = ((small - ref) ** 2).mean(-1)
            se[0] += err[hs].sum()
            n[0] += hs.sum()
            ok = cv2.resize((np.abs(f.depth - ref_d) <= 0.1 * ref_d).astype(np.uint8), (w, h),
                            interpolation=cv2.INTER_NEAREST) > 0
            by = [cv2.resize(x.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
                  for x in (f.filled_3d, f.filled_2d)]
            for k in range(len(UNSEEN_PARTS)):
                m = hs & (part == k)
                se[k + 1] += err[m].sum()
                n[k + 1] += m.sum()
                by.append(m)
            for r, m in enumerate(by):
                m = m & hs
                split[r] += (m.sum(), (m & ok).sum(), err[m].sum())
        name = " ".join(f"{k}={v:g}" for k, v in var.items())
        parts = " | ".join(f"{psnr(se[k + 1], n[k + 1])} ({100 * n[k + 1] / max(n[0], 1):.0f} %)"
                           for k in range(len(UNSEEN_PARTS)))
        print(f"| {name} | {psnr(se[0], n[0])} | {parts} | {with_depth / max(holes, 1):.3f} | "
              f"{right / max(holes, 1):.3f} | {seconds:.0f} |", flush=True)
        names = ["layer", "2D fill", *UNSEEN_PARTS]
        print("    by source / surface (share of hole pixels, depth within 10 %, PSNR): " + "; ".join(
            f"{nm} {100 * c / max(n[0], 1):.0f} % / {r / max(c, 1):.2f} / {psnr(e, int(c))}"
            for nm, (c, r, e) in zip(names, split)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
