"""The gaussians artifact: gaussians.ply, gaussians.spz, optionally points.ply and a preview rendered back, with fit metrics."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from panoworld.gaussians.fusion import ContextSource, uniform_subset
from panoworld.io.gaussian_set import ContextFrames, FusionResult
from panoworld.io.splat_ply import used_sh_degree, write_gaussians_ply, write_points_ply
from panoworld.io.splat_spz import write_gaussians_spz
from panoworld.render.erp import render_erp
from panoworld.render.metrics import psnr, ssim, ws_psnr


def write_artifact(out_dir: Path, result: FusionResult, frames: ContextFrames | ContextSource, *, eval_views: int = 1,
                   eval_height: int = 128, full_sh: bool = False, points: bool = False) -> dict:
    """Write gaussians.ply (the SH degree the Gaussians use; the full INRIA layout with full_sh), gaussians.spz,
    points.ply (with points) and preview.png (the first context view rendered back); return manifest info
    with PSNR/SSIM/WS-PSNR of eval_views context views re-rendered as ERP at eval_height (frame 0, after a colour
    fit: the fit's own render of the final Gaussians, area-downsampled from the fit's height)."""
    g = result.gaussians.numpy()
    out_dir = Path(out_dir)
    write_gaussians_ply(out_dir / "gaussians.ply", g, full_sh=full_sh)
    write_gaussians_spz(out_dir / "gaussians.spz", g)
    if points:
        write_points_ply(out_dir / "points.ply", g.means, g.base_colors())
    evals = []
    for k in uniform_subset(range(len(frames.indices)), eval_views) if eval_views > 0 else []:
        if frames.indices[k] == 0 and result.fit_render is not None:  # the colour fit rendered it already
            rgb, alpha = (cv2.resize(a, (2 * eval_height, eval_height), interpolation=cv2.INTER_AREA)
                          for a in result.fit_render)
            how = f"the colour fit's render at {len(result.fit_render[1])} rows, area-downsampled"
        else:
            out = render_erp(g, frames.world_from_cam[k], eval_height, 2 * eval_height)
            rgb, alpha = out.rgb.numpy(), out.alpha.numpy()
            how = "render_erp"
        img = (np.clip(rgb, 0, 1) * 255.0).round().astype(np.uint8)
        ref = frames.rgb_at(k)
        if ref.shape[0] != eval_height:
            ref = cv2.resize(ref, (2 * eval_height, eval_height), interpolation=cv2.INTER_AREA)
        if not evals:
            cv2.imwrite(str(out_dir / "preview.png"), img[..., ::-1])
        covered = alpha > 0.5
        evals.append({"frame": frames.indices[k], "render": how, "psnr": psnr(img, ref), "ws_psnr": ws_psnr(img, ref),
                      "ssim": ssim(img, ref), "coverage": float(alpha.mean()),
                      "psnr_covered": psnr(img, ref, covered) if covered.any() else None})
    warnings = []
    if max(result.extent_m) < 2 * result.voxel_size:
        warnings.append(f"the scene spans {max(result.extent_m):.3f} m, under two voxels of {result.voxel_size} m; "
                        "lower voxel_size")
    return {
        "backend": result.backend,
        "num_gaussians": len(g),
        "sh_degree": used_sh_degree(g.sh_rest),
        "num_voxels": result.num_voxels,
        "num_pruned_voxels": result.num_pruned,
        "num_observations": result.num_observations,
        "num_source_gaussians": result.num_source,
        "color_fit": result.color_fit,
        "back_sides": result.back_sides,
        "own_fill": result.own_fill,
        "voxel_size": result.voxel_size,
        "frames": frames.indices,
        "fusion_height": int(frames.height) if isinstance(frames, ContextSource) else int(frames.rgb.shape[1]),
        "depth_source": frames.depth_source,
        "extent_m": result.extent_m,
        "eval": evals,
        "context_psnr": float(np.mean([e["psnr"] for e in evals])) if evals else None,
        # Where the frame has no depth (a LiDAR's zenith/nadir) there are no Gaussians, while the video is filled.
        "context_psnr_covered": float(np.mean([e["psnr_covered"] for e in evals])) if evals and all(
            e["psnr_covered"] is not None for e in evals) else None,
        "warnings": warnings,
        "frame": "canonical world: metres, camera 0 = identity, OpenCV axes, y down = gravity",
    }
