"""Benchmark of the video stage on synthetic scenes: warp-inpaint vs frame-inpaint fidelity, temporal consistency, CPU time."""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.framework import pipeline as pl
from panoworld.geometry.erp_mesh import load_erp_mesh
from panoworld.io.conditions import load_conditions
from panoworld.io.manifest import read_manifest
from panoworld.io.trajectory import load_trajectory
from panoworld.render.metrics import reprojection_error, ssim_map, video_psnr
from panoworld.tools.synth import generate_scene
from panoworld.video import background_layer, inpaint


def make_scene_dir(scene, root: Path, height: int) -> Path:
    """A pipeline scene directory (panorama.png + GT depth.npy at the panorama pose) rendered at height x 2 height."""
    root.mkdir(parents=True, exist_ok=True)
    rgb, depth = scene.render(scene.world_from_canonical, height, 2 * height)
    cv2.imwrite(str(root / "panorama.png"), rgb[..., ::-1])
    np.save(root / "depth.npy", np.where(np.isfinite(depth), depth, 0).astype(np.float32))
    return root


def run_upstream(scene_dir: Path, height: int, stride: int, frames: int) -> None:
    sets = [f"trajectory.stride={stride}", f"trajectory.frames={frames}", f"conditions.height={height}",
            f"conditions.width={2 * height}"]
    report = pl.run(scene_dir, preset="default", until="conditions", sets=sets)
    if any(r.action == "failed" for r in report.results):
        raise RuntimeError(report.table())


def fill_all(cond, poses, mesh, backend: str):
    """-> (list of FilledFrame, seconds of CPU time, wall seconds); conditions are decoded before the clock starts."""
    rgb, mask, depth = np.asarray(cond.rgb), np.asarray(cond.mask), np.asarray(cond.depth)
    c0, w0 = time.process_time(), time.perf_counter()
    if backend == "warp-inpaint":
        frames, _ = inpaint.warp_inpaint_video(rgb, mask, depth, poses, mesh, progress=False)
    else:
        frames = [inpaint.frame_inpaint(rgb[t], mask[t], depth[t]) for t in range(len(rgb))]
    return frames, time.process_time() - c0, time.perf_counter() - w0


def temporal_rmse(frames, masks, gt_depth, poses) -> tuple[float, int]:
    """RMS colour error between frame t+1 and frame t reprojected with GT depth, on pixels filled in both frames."""
    errs = []
    for t in range(len(frames) - 1):
        err, ok = reprojection_error(frames[t], frames[t + 1], gt_depth[t], gt_depth[t + 1], poses[t], poses[t + 1],
                                     mask_t=~masks[t])
        errs.append(err[ok & ~masks[t + 1]])
    e = np.concatenate(errs)
    return (float(np.sqrt((e**2).mean())) if len(e) else float("nan")), len(e)


def video_metrics(outs: np.ndarray, gts: np.ndarray, holes: np.ndarray) -> dict[str, float]:
    """PSNR / WS-PSNR of the error pooled over frames (T, H, W, 3) and SSIM averaged over pixels, on all pixels and on
    the disoccluded ones (holes (T, H, W))."""
    smaps = np.stack([ssim_map(o, g) for o, g in zip(outs, gts)])
    return {
        "psnr": video_psnr(outs, gts), "ssim": float(smaps.mean()), "ws_psnr": video_psnr(outs, gts, spherical=True),
        "psnr_hole": video_psnr(outs, gts, holes), "ssim_hole": float(smaps[holes].mean()) if holes.any() else np.nan,
        "ws_psnr_hole": video_psnr(outs, gts, holes, spherical=True),
    }


def evaluate_stride(scene, scene_dir: Path, height: int, stride: int, frames: int) -> None:
    run_upstream(scene_dir, height, stride, frames)
    art = scene_dir / "artifacts"
    poses = load_trajectory(art / "trajectory")
    cond = load_conditions(art / "conditions")
    mesh = load_erp_mesh(art / "mesh")
    masks = np.asarray(cond.mask)
    gt = [scene.render(scene.world_from_canonical @ T, height, 2 * height) for T in poses]
    gt_depth = [np.where(np.isfinite(d), d, 0).astype(np.float32) for _, d in gt]
    gt_rgb = np.stack([g[0] for g in gt])
    length = float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())
    print(f"\nstride r={stride}: {len(poses)} frames, path {length:.2f} m, {height}x{2 * height}, "
          f"hole fraction {1 - masks.mean():.4f} (metrics over frames 1..{len(poses) - 1}, error pooled over frames)")
    rows = []
    for backend in ("warp-inpaint", "frame-inpaint"):
        filled, cpu_s, wall_s = fill_all(cond, poses, mesh, backend)
        outs = np.stack([f.rgb for f in filled])
        mean = video_metrics(outs[1:], gt_rgb[1:], ~masks[1:])  # frame 0 is the input panorama
        tc, n = temporal_rmse(outs, masks, gt_depth, poses)
        f2d = sum(int(f.filled_2d.sum()) for f in filled) / max(int((~masks).sum()), 1)
        rows.append((backend, mean, tc, n, f2d, cpu_s))
    gt_tc, _ = temporal_rmse(gt_rgb, masks, gt_depth, poses)
    print(f"  {'backend':14s} {'PSNR':>6s} {'SSIM':>6s} {'WS-PSNR':>7s} | {'PSNR':>6s} {'SSIM':>6s} {'WS-PSNR':>7s} (holes)"
          f" | {'temporal RMSE':>13s} {'2D fill':>7s} {'CPU s':>6s}")
    for backend, m, tc, _n, f2d, cpu_s in rows:
        print(f"  {backend:14s} {m['psnr']:6.2f} {m['ssim']:6.4f} {m['ws_psnr']:7.2f} | {m['psnr_hole']:6.2f} "
              f"{m['ssim_hole']:6.4f} {m['ws_psnr_hole']:7.2f}         | {tc:13.2f} "
              f"{f2d:7.3f} {cpu_s:6.2f}")
    print(f"  temporal RMSE of the GT frames themselves on the same pixels (resampling floor): {gt_tc:.2f} "
          f"({rows[0][3]} pixel pairs; 8-bit RGB units)")


def time_full_size(scene, scene_dir: Path, height: int, frames: int) -> None:
    run_upstream(scene_dir, height, 1, frames)
    art = scene_dir / "artifacts"
    poses = load_trajectory(art / "trajectory")
    cond = load_conditions(art / "conditions")
    mesh = load_erp_mesh(art / "mesh")
    rgb, mask, depth = np.asarray(cond.rgb), np.asarray(cond.mask), np.asarray(cond.depth)
    c0, w0 = time.process_time(), time.perf_counter()
    layer = background_layer.build_background_layer(mesh, inpaint.max_translation(poses))
    c1, w1 = time.process_time(), time.perf_counter()
    filler = inpaint.WarpInpainter(layer)
    filled = [filler.fill(rgb[t], mask[t], depth[t], poses[t]) for t in range(len(rgb))]
    c2, w2 = time.process_time(), time.perf_counter()
    f2d = sum(int(f.filled_2d.sum()) for f in filled) / max(int((~mask).sum()), 1)
    print(f"\nwarp-inpaint at {height}x{2 * height}, {len(poses)} frames ({len(mesh.faces)} mesh faces, "
          f"{layer.layer_faces} layer faces, hole fraction {1 - mask.mean():.4f}, 2D fallback {f2d:.4f} of holes):")
    print(f"  layer {c1 - c0:.2f} s CPU ({w1 - w0:.2f} s wall), fill {c2 - c1:.2f} s CPU ({w2 - w1:.2f} s wall, "
          f"{1000 * (w2 - w1) / len(poses):.0f} ms/frame); total {c2 - c0:.2f} s CPU, {w2 - w0:.2f} s wall "
          "(excludes reading conditions and writing the artifact)")
    for upscale in ("none", "lanczos"):
        t0 = time.perf_counter()
        report = pl.run(scene_dir, preset="default", only=["video"], sets=[f"video.upscale={upscale}"], force=True)
        result = next(r for r in report.results if r.stage == "video")
        info = read_manifest(art / "video")["info"]
        print(f"  whole video stage, upscale={upscale} (PNG frames + depth, preview.mp4, video.mcap"
              f"{', upscaled/ x2 output' if upscale != 'none' else ''}): {time.perf_counter() - t0:.1f} s wall "
              f"({result.action}); fill {info['fill_s']:.1f} s, upscale {info['upscale_s']:.1f} s, "
              f"write {info['write_s']:.1f} s")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", default="3", help="synthetic scene seeds, comma separated (one table set per scene)")
    ap.add_argument("--height", type=int, default=256, help="ERP height of the quality runs (width = 2x)")
    ap.add_argument("--frames", type=int, default=81)
    ap.add_argument("--strides", default="1,2,4")
    ap.add_argument("--time-height", type=int, default=720, help="ERP height of the timing run; 0 skips it")
    ap.add_argument("--keep", type=Path, help="keep the scene directories here instead of a temporary directory")
    args = ap.parse_args(argv)
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_video_"))
    try:
        for seed in (int(s) for s in args.seeds.split(",") if s):
            scene = generate_scene(seed, "default")
            print(f"\n=== synthetic scene seed {seed} (default preset) ===")
            scene_dir = make_scene_dir(scene, root / f"scene{seed}_{args.height}", args.height)
            for r in (int(s) for s in args.strides.split(",") if s):
                evaluate_stride(scene, scene_dir, args.height, r, args.frames)
            if args.time_height:
                big = make_scene_dir(scene, root / f"scene{seed}_{args.time_height}", args.time_height)
                time_full_size(scene, big, args.time_height, args.frames)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
