"""Voxel-aligned 3D Gaussians (INRIA gaussians.ply + points.ply) fused from the video's frames, depth and poses."""

from __future__ import annotations

import enum
import sys
from dataclasses import dataclass
from pathlib import Path

from panoworld.fusion_params import FusionParams
from panoworld.params import param
from panoworld.stage import Input, StageInputError, stage_main

NAME = "gaussians"
VERSION = "3"
ARTIFACT = "gaussians"
INPUTS = {
    "video": Input("video", help="video artifact (video.json, frames/, depth/)"),
    "poses": Input("poses", help="poses artifact (poses.json, depth/)"),
    "depth": Input("depth", optional=True, help="a home: depth artifact whose panoramas are anchored (with --register)"),
    "register": Input("register", optional=True, help="a home: register artifact placing those panoramas"),
}


class Backend(enum.StrEnum):
    VOXEL_FUSION = "voxel-fusion"
    """Non-learned: confidence-weighted voxel fusion of back-projected pixels, one Gaussian per voxel part."""
    DECODER = "decoder"
    """The learned voxel-aligned Gaussian head of PanoVGGT (needs --weights: a stage-2 export)."""


@dataclass(kw_only=True)
class Params(FusionParams):
    backend: Backend = Backend.VOXEL_FUSION
    """Gaussian head."""
    context_views: int = param(0, ge=0)
    """Number of registered frames used, uniformly spaced (0 = all)."""
    height: int = param(0, ge=0)
    """Process frames resized to this ERP height (0 = as stored, capped at max_height; decoder: a multiple of its
    patch size)."""
    max_height: int = param(512, ge=0)
    """With height 0: frames taller than this are downscaled to it before fusion (0 = no cap). Frames are streamed
    from disk, so memory stays bounded by one frame of this size plus the occupied voxels; 512 rows sample 2 cm voxels
    at least once per pixel row up to about 3 m away."""
    weights: str | None = None
    """decoder: directory holding config.json and model.safetensors of PanoVGGT with a Gaussian head (runner.py train
    recon --stage 2 exports it; its voxel size and input height win)."""
    device: str = "cpu"
    """decoder: torch device (cpu, cuda)."""
    source_pixels: bool = True
    """voxel-fusion: the source view (video frame 0) becomes one Gaussian per pixel (its full detail at the capture
    point); the other frames are voxel-fused only where they see what the source does not."""
    source_height: int = param(640, ge=0)
    """ERP height of the source view's per-pixel Gaussians (0 = that of the other frames); rows near the poles keep
    every k-th pixel so kept pixels are about square on the sphere. 640 with source_scale 1.9: as sharp as 512 rows at
    the capture point and +0.6 dB on what it sees from ~1-2 m away (validation seed 1; docs/evaluation.md)."""
    source_scale: float = param(1.9, gt=0)
    """Footprint scale of the source's per-pixel Gaussians (scale_factor of the voxel Gaussians otherwise): large
    enough that neighbours leave no see-through cracks between them, small enough to keep the input's detail."""
    unseen_voxel_size: float = param(0.04, ge=0)
    """With source_pixels: voxel edge (metres) of what the other frames see that the source does not (0 =
    voxel_size). That is the generated (disoccluded) content, softer than the input: 4 cm voxels hold it with fewer,
    larger Gaussians and fewer see-through gaps than 2 cm (docs/evaluation.md, "Away from the capture point")."""
    source_tol: float = param(0.03, gt=0)
    """Observations of the other frames within this relative depth of the source's surface (or in front of it) count
    as seen by the source and are not fused."""
    fit_iters: int = param(10, ge=0)
    """With source_pixels: conjugate-gradient steps of a colour fit at the capture point (0 = none): for the fixed
    geometry the ERP render there is linear in the Gaussians' colours, which are refitted (least squares, damped
    towards their fused values) so it reproduces the source frame, undoing the blur of overlapping splats
    (docs/evaluation.md, "Colour fit at the capture point")."""
    fit_height: int = param(0, ge=0)
    """ERP height of that fit's render and target (0 = source_height)."""
    eval_views: int = param(1, ge=0)
    """Context views rendered back from the Gaussians to report PSNR/SSIM/WS-PSNR in the manifest (0 = none)."""
    eval_height: int = param(128, ge=8)
    """ERP height of those renders (and of preview.png)."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from panoworld.gaussians import context_source, voxel_fusion
    from panoworld.gaussians_artifact import write_artifact
    from panoworld.home.layout import capture_poses
    from panoworld.pixel_gaussians import source_anchored_fusion

    frames = context_source(inputs["video"], inputs["poses"], context_views=params.context_views,
                            height=params.height, max_height=params.max_height)
    try:
        if params.backend == Backend.DECODER:
            from panoworld.models.panovggt import PanoVGGT

            model = PanoVGGT.from_pretrained(params.weights, flag="--weights", device=params.device)
            model.require_gaussian_head("--weights")
            result = model.decode(frames.load())
        elif params.source_pixels and len(captures := capture_poses(inputs.get("register"))) >= 2:
            from panoworld.home.gaussians import home_anchored_fusion
            from panoworld.home.layout import home_depth_dirs
            from panoworld.home.mesh import load_sources

            dirs = home_depth_dirs(inputs["depth"]) if inputs.get("depth") else None
            if dirs is None:
                raise StageInputError("the register artifact places several panoramas: give --depth, the home's depth "
                                      "artifact (its panoramas are anchored)")
            names, rgbs, depths = load_sources(dirs, captures)
            result = home_anchored_fusion(frames, {n: (rgbs[n], depths[n], captures[n]) for n in names}, params,
                                          source_height=params.source_height, tol=params.source_tol,
                                          source_scale=params.source_scale,
                                          unseen_voxel_size=params.unseen_voxel_size, progress=True)
        elif params.source_pixels:
            result = source_anchored_fusion(frames, params, source_height=params.source_height, tol=params.source_tol,
                                            source_scale=params.source_scale,
                                            unseen_voxel_size=params.unseen_voxel_size, fit_iters=params.fit_iters,
                                            fit_height=params.fit_height, progress=True)
        else:
            result = voxel_fusion(frames, params, progress=True)
    except StageInputError:
        raise
    except ValueError as e:  # empty depth, nothing left after pruning, bad params
        raise StageInputError(str(e)) from None
    return write_artifact(out_dir, result, frames, eval_views=params.eval_views, eval_height=params.eval_height)


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
