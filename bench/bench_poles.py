"""Prints the capture point's ERP PSNR per latitude band (|lat| 0-45 / 45-70 / 70-90 deg) against the anti-aliased
reference, for the input panorama, video frame 0 and source Gaussians built from it in several variants (footprint
scale, source rows, pole thinning, colour fit, render supersampling), on scenes already run to `poses` (e.g. kept by
`bench_roam.py --out DIR`). Tune on the VALIDATION seeds (1 2 3), never on the test seeds.

  python bench/bench_poles.py /tmp/roam/seed_1 --variant source_scale=1.9 --variant source_scale=1.9,fit_iters=10
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

BANDS = ((0.0, 45.0), (45.0, 70.0), (70.0, 90.0))
"""|latitude| bands in degrees."""
ARTIFACTS = "artifacts"


def band_masks(height: int) -> list[np.ndarray]:
    """(H, 2H) bool per BANDS entry."""
    lat = np.abs(90.0 - (np.arange(height) + 0.5) / height * 180.0)
    return [np.broadcast_to(((lat >= lo) & (lat < hi) | (hi == 90.0) & (lat >= lo))[:, None], (height, 2 * height))
            for lo, hi in BANDS]


def band_psnr(img: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    from panoworld.render.metrics import psnr

    out = {"all": psnr(img, ref)}
    for (lo, hi), m in zip(BANDS, band_masks(img.shape[0])):
        out[f"{lo:g}-{hi:g}"] = psnr(img, ref, m)
    return out


def parse_variant(text: str) -> dict:
    import yaml

    return {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in text.split(",") if item)}


def source_gaussians(scene: Path, v: dict):
    """The source view's per-pixel Gaussians of a variant (keys: source_height, source_scale, thin_poles, fit_iters,
    fit_height, fit_supersample, fit_pole_scale) and the frame-0 target and pose of its fit."""
    from panoworld.gaussians.backends.voxel_fusion import VoxelFusionOptions
    from panoworld.gaussians.fusion import context_source
    from panoworld.gaussians.pixel import SourceVisibility, fit_colors, pixel_gaussians, view_targets

    o = VoxelFusionOptions()
    frames = context_source(scene / ARTIFACTS / "video", scene / ARTIFACTS / "poses", max_height=512)
    h = int(v.get("source_height", o.source_height))
    src = replace(frames, height=min(h, frames.stored_height))
    rgb, depth, pose = src.frame(0)
    params = replace(o, scale_factor=float(v.get("source_scale", o.source_scale)),
                     opacity=float(v.get("opacity", o.opacity)))
    kw = {k: v[k] for k in ("thin_poles",) if k in v}
    g = pixel_gaussians(rgb, depth, pose, params, **kw)
    info: dict = {"gaussians": len(g.means)}
    iters = int(v.get("fit_iters", 0))
    if iters:
        fh = int(v.get("fit_height", 0)) or src.height
        target = replace(frames, height=min(fh, frames.stored_height)).frame(0)[0] if fh != src.height else rgb
        kw = {k.removeprefix("fit_"): v[k] for k in ("fit_supersample", "fit_pole_scale") if k in v}
        t0 = time.process_time()
        if int(v.get("fit_views", 0)):
            rest = replace(frames, rgb_paths=frames.rgb_paths[1:], depth_paths=frames.depth_paths[1:],
                           world_from_cam=frames.world_from_cam[1:], indices=frames.indices[1:])
            kw["extra"] = view_targets(rest, SourceVisibility(depth, pose, o.source_tol), int(v["fit_views"]),
                                       int(v.get("fit_view_height", o.fit_view_height)),
                                       float(v.get("fit_view_reach", 0.0)), float(v.get("fit_view_weight", 1.0)))
        g, fit = fit_colors(g, target, pose, iters=iters, **kw)
        fit.pop("render", None)
        info.update(fit_cpu_s=time.process_time() - t0, **fit)
    return g, pose, info


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--variant", action="append", default=[],
                    help="comma-separated KEY=VALUE (source_height, source_scale, opacity, thin_poles, "
                    "fit_iters, fit_height, fit_views, fit_view_height, fit_view_reach, fit_view_weight, "
                    "fit_supersample, fit_pole_scale; the render's supersample, pole_scale), or 'artifact' (the scene's gaussians.ply; 'artifact_source' / 'artifact_voxels': "
                    "its source / voxel part)")
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--yaw", type=float, default=0.0, help="camera yaw (deg) at the capture point")
    ap.add_argument("--save", type=Path, help="write each render and the reference as PNG here")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    import cv2
    import torch

    from panoworld.io.video import load_frames, read_video_doc
    from panoworld.render.erp import render_erp
    from panoworld.tools.eval.groundtruth import open_ground_truth
    from panoworld.trajectory import poses_from_positions

    torch.set_num_threads(1)
    H = a.height
    rows = []

    def report(scene, name, img, ref, **extra):
        r = {"scene": scene.name, "variant": name, **band_psnr(img, ref), **extra}
        rows.append(r)
        print(f"{scene.name:<8} {name:<44} " + " ".join(f"{r[k]:6.2f}" for k in ("all", *[f"{lo:g}-{hi:g}" for lo, hi in BANDS]))
              + "  " + " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in extra.items()),
              flush=True)
        if a.save:
            a.save.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(a.save / f"{scene.name}_{name.replace('=', '').replace(',', '_')}.png"), img[..., ::-1])

    print(f"{'scene':<8} {'image':<44} {'all':>6} " + " ".join(f"{lo:g}-{hi:g}".rjust(6) for lo, hi in BANDS))
    for scene in a.scenes:
        gt = open_ground_truth(scene)
        pose = poses_from_positions(np.zeros((1, 2)), np.array([np.radians(a.yaw)]), 0.0)[0]
        ref = gt.render(pose, H, 2 * H)[0]
        if a.save:
            a.save.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(a.save / f"{scene.name}_reference.png"), ref[..., ::-1])
        if a.yaw == 0.0:
            pano = next(p for p in (scene / f"panorama.{e}" for e in ("png", "jpg")) if p.is_file())
            report(scene, "input panorama", cv2.resize(load_frames([pano])[0], (2 * H, H), interpolation=cv2.INTER_AREA), ref)
            f0 = read_video_doc(scene / ARTIFACTS / "video").rgb[0]
            report(scene, "video frame 0", cv2.resize(load_frames([f0])[0], (2 * H, H), interpolation=cv2.INTER_AREA), ref)
        for name in a.variant:
            v = parse_variant(name) if "=" in name else {}
            ss = int(v.pop("supersample", 2))
            pole = float(v.pop("pole_scale", 1.0))
            if name.startswith("artifact"):
                from panoworld.io.manifest import read_manifest
                from panoworld.io.splat_ply import read_gaussians_ply

                art = scene / ARTIFACTS / "gaussians"
                g = read_gaussians_ply(art / "gaussians.ply")
                n_src = read_manifest(art)["info"]["num_source_gaussians"]
                part = {"artifact": slice(None), "artifact_source": slice(0, n_src), "artifact_voxels": slice(n_src, None)}
                g = g.subset(np.arange(len(g.means))[part[name]])
                info = {"gaussians": len(g.means)}
            else:
                g, _, info = source_gaussians(scene, v)
            t0 = time.process_time()
            r = render_erp(g, pose, H, 2 * H, supersample=ss, pole_scale=pole)
            info["render_cpu_s"] = time.process_time() - t0
            img = (r.rgb.clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
            report(scene, name + (f",ss={ss}" if ss != 2 else ""), img, ref, **info)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
