"""CPU speed of the pure-torch Gaussian renderer: 200k Gaussians at 512x256 perspective and as a 256x512 ERP.

The Gaussians are surfels (scales 1-4 cm, random rotations, opacity 0.5-1) on the walls, floor and ceiling of a
6 x 3 x 6 m room around the camera, the density of a voxel-fused indoor scene. Also checks the tile rasteriser
against the brute-force oracle on a crop of the same scene, and times the colour fit's compositing weights
(ErpColorOperator's cube faces at --weights-height ERP rows, 2x supersampled, 2x pole faces) from the torch tile
rasteriser and from its numba kernel (splat_weights), with how far their weights differ.

    python bench/bench_render_gs.py [--n 200000] [--threads 1] [--repeats 3] [--supersample 1 2] [--backend auto]
        [--weights-height 256]

With --device cuda (needs gsplat and a GPU) it instead times gsplat against the torch renderer on the CPU, perspective
512x256 and ERP 256x512 (cube faces through gsplat, resampled on the CPU), and prints how far their outputs differ.
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

from panoworld.core.conventions import invert_pose
from panoworld.io.gaussian_set import Gaussians
from panoworld.render.erp import erp_faces, face_cull, render_erp
from panoworld.render.splats import _prepare, face_weights, project, rasterize_tiles, render_perspective
from panoworld.tools.synth.surfels import room_surfels


def timed(fn, repeats: int) -> tuple[float, float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times[0], min(times), out


def fit_weights(g: Gaussians, height: int) -> None:
    """The colour fit's per-face compositing weights: torch tile rasteriser vs the numba kernel, wall and CPU s."""
    prep = _prepare(g, np.zeros(3))
    projs = [(project(prep, invert_pose(fc.world_from_face), fc.f, fc.f, fc.c, fc.c, fc.n, fc.n), fc.n)
             for fc in erp_faces(np.eye(4), height, 2 * height)]
    times, out = {}, {}
    for name in ("torch", "numba"):
        if name == "numba":
            face_weights(projs[0][0], projs[0][1], projs[0][1])  # compile (or load the cached kernel) first
        t0, c0 = time.perf_counter(), time.process_time()
        res = []
        for proj, n in projs:
            if name == "numba":
                res.append(face_weights(proj, n, n))
            else:
                parts: list = []
                rasterize_tiles(proj, n, n, torch.zeros(3), weights=parts)
                res.append(tuple(torch.cat(x).numpy() for x in zip(*parts)))
        times[name], out[name] = (time.perf_counter() - t0, time.process_time() - c0), res
    diff = max(float(np.abs(np.sort(a[2]) - np.sort(b[2])).max()) for a, b in zip(out["torch"], out["numba"]))
    count = sum(len(a[2]) for a in out["numba"])
    print(f"colour-fit weights, ERP {2 * height}x{height} (faces {', '.join(str(n) for _, n in projs)} px), "
          f"{count} weights: torch {times['torch'][0]:.2f} s wall / {times['torch'][1]:.2f} CPU s, numba "
          f"{times['numba'][0]:.2f} s / {times['numba'][1]:.2f} CPU s; same count "
          f"{count == sum(len(a[2]) for a in out['torch'])}, max |sorted weight diff| {diff:.1e}")


def cuda_timed(fn, repeats: int):
    """Best wall seconds of fn() after one warm-up call, synchronising CUDA around each, and its last output."""
    out = fn()
    torch.cuda.synchronize()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return best, out


def cuda_speed(g: Gaussians, repeats: int) -> None:
    """gsplat (CUDA) vs the torch tile rasteriser (CPU) on the same Gaussians: times and agreement."""
    gc = Gaussians(**{k: torch.as_tensor(getattr(g, k)).cuda() for k in ("means", "scales", "quats", "opacities", "sh_dc")})
    print(f"{torch.cuda.get_device_name()}, torch on {torch.get_num_threads()} CPU thread(s), {len(g)} Gaussians")
    args = (np.eye(4), 256.0, 256.0, 256.0, 128.0, 256, 512)
    t_cpu, a = cuda_timed(lambda: render_perspective(g, *args, backend="torch"), 1)
    t_gpu, b = cuda_timed(lambda: render_perspective(gc, *args, backend="gsplat"), repeats)
    diff = (b.rgb.cpu() - a.rgb).abs()
    print(f"perspective 512x256: torch CPU {t_cpu:.3f} s, gsplat {t_gpu * 1e3:.1f} ms; rgb |diff| mean "
          f"{float(diff.mean()):.1e}, max {float(diff.max()):.3f}")
    t_cpu, a = cuda_timed(lambda: render_erp(g, np.eye(4), 256, 512, backend="torch"), 1)
    t_gpu, b = cuda_timed(lambda: render_erp(gc, np.eye(4), 256, 512, backend="gsplat"), repeats)
    both = (a.alpha > 0.5) & (b.alpha > 0.5)
    depth = ((b.depth - a.depth).abs() / a.depth.clamp(min=1e-6))[both].median()
    print(f"ERP 256x512: torch CPU {t_cpu:.3f} s, gsplat {t_gpu:.3f} s; rgb |diff| mean {float((b.rgb - a.rgb).abs().mean()):.1e}, "
          f"alpha mean {float((b.alpha - a.alpha).abs().mean()):.1e}, depth median relative {float(depth):.2%}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--supersample", type=int, nargs="+", default=[1, 2], help="render_erp supersampling factors")
    ap.add_argument("--backend", default="auto", choices=("auto", "torch", "numba"),
                    help="render_erp's backend (auto: numba, as nothing needs a gradient)")
    ap.add_argument("--weights-height", type=int, default=256, help="ERP rows of the colour-fit weights timing (0 = skip)")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="cuda: gsplat vs the CPU renderer instead")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    g = room_surfels(args.n)
    if args.device == "cuda":
        if not torch.cuda.is_available():
            print("--device cuda: no CUDA GPU here", file=sys.stderr)
            return 2
        cuda_speed(g, args.repeats)
        return 0
    W, H = 512, 256
    f = W / 2  # 90 degree horizontal field of view
    pose = np.eye(4)
    first, best, out = timed(lambda: render_perspective(g, pose, f, f, W / 2, H / 2, H, W), args.repeats)
    print(f"perspective {W}x{H}, {args.n} Gaussians, {args.threads} thread(s): first {first:.2f} s, best {best:.2f} s "
          f"(target <= 2 s), coverage {float(out.alpha.mean()):.3f}")
    cull = face_cull(_prepare(g, pose[:3, 3]), g.scales, pose[:3, 3], 0.01)
    for s in args.supersample:
        first, best, out = timed(lambda s=s: render_erp(g, pose, 256, 512, supersample=s, backend=args.backend),
                                 args.repeats)
        projected = sum(len(cull(fc)[1]) for fc in erp_faces(pose, 256, 512, supersample=s)) / args.n
        print(f"ERP 512x256 {args.backend} supersample {s} (6 cube faces of {math.ceil(s * 512 / math.pi)} px + grid_sample + {s}x{s} "
              f"area): first {first:.2f} s, best {best:.2f} s (target <= 5 s), coverage {float(out.alpha.mean()):.3f}, "
              f"projected {projected:.2f} N (face cull)")
    sub = g.subset(np.linalg.norm(g.means - [0, 0, 3.0], axis=1) < 1.2)
    a = render_perspective(sub, pose, 60.0, 60.0, 40.0, 24.0, 48, 80)
    b = render_perspective(sub, pose, 60.0, 60.0, 40.0, 24.0, 48, 80, reference=True)
    print(f"tiles vs brute force on {len(sub)} Gaussians, 80x48: max |rgb diff| {float((a.rgb - b.rgb).abs().max()):.2e}, "
          f"max |alpha diff| {float((a.alpha - b.alpha).abs().max()):.2e}")
    if args.weights_height:
        fit_weights(g, args.weights_height)
    print("timings were taken on a shared CPU and are inflated by contention")
    return 0


if __name__ == "__main__":
    sys.exit(main())
