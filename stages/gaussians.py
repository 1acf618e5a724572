"""Voxel-aligned 3D Gaussians (INRIA gaussians.ply, SPZ gaussians.spz) fused from the video's frames, depth and poses."""

from __future__ import annotations

import sys
from dataclasses import dataclass, fields
from pathlib import Path
from typing import ClassVar

from panoworld.core import registry as backends
from panoworld.core.params import options, param
from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.gaussians.backends.decoder import DecoderOptions
from panoworld.gaussians.backends.voxel_fusion import VoxelFusionOptions

NAME = "gaussians"
VERSION = "6"
ARTIFACT = "gaussians"
INPUTS = {
    "video": Input("video", help="video artifact (video.json, frames/, depth/)"),
    "poses": Input("poses", help="poses artifact (poses.json, depth/)"),
    "depth": Input("depth", optional=True, help="a home: depth artifact whose panoramas are anchored (with --register)"),
    "register": Input("register", optional=True, help="a home: register artifact placing those panoramas"),
    "navmesh": Input("navmesh", optional=True, help="navmesh artifact (voxel_fusion.back_sides: where a wall's back "
                     "is walkable)"),
}


@dataclass(kw_only=True)
class Params:
    backend: str = param("voxel-fusion", choices=backends.names(NAME))
    """Gaussian head: voxel-fusion (no weights) or decoder (the paper's learned head, needs decoder.weights)
    (panoworld/gaussians/backends/)."""
    context_views: int = param(0, ge=0)
    """Number of registered frames used, uniformly spaced (0 = all)."""
    height: int = param(0, ge=0)
    """Process frames resized to this ERP height (0 = as stored, capped at max_height; decoder: a multiple of its
    patch size)."""
    max_height: int = param(512, ge=0)
    """With height 0: frames taller than this are downscaled to it before fusion (0 = no cap). Frames are streamed
    from disk, so memory stays bounded by one frame of this size plus the occupied voxels; 512 rows sample 2 cm voxels
    at least once per pixel row up to about 3 m away."""
    eval_views: int = param(1, ge=0)
    """Context views rendered back from the Gaussians to report PSNR/SSIM/WS-PSNR in the manifest (0 = none)."""
    eval_height: int = param(128, ge=8)
    """ERP height of those renders (and of preview.png)."""
    ply_full_sh: bool = False
    """Write gaussians.ply in the full INRIA layout for tools that insist on it (nx ny nz and all 45 f_rest_*,
    degree-3 SH zero-padded); by default it holds only the SH degree the Gaussians use and no normals, which 3DGS
    viewers ignore."""
    points_ply: bool = False
    """Also write points.ply (the Gaussian centres with their base colours) for point-cloud tools (MeshLab,
    CloudCompare); no stage reads it."""
    voxel_fusion: VoxelFusionOptions = options(VoxelFusionOptions, "voxel-fusion")
    """voxel-fusion's options."""
    decoder: DecoderOptions = options(DecoderOptions, "decoder")
    """decoder's options."""

    RENAMED: ClassVar[dict[str, str]] = {
        **{f.name: f"voxel_fusion.{f.name}" for f in fields(VoxelFusionOptions)},
        **{k: f"decoder.{k}" for k in ("weights", "device")},
    }


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from panoworld.gaussians.artifact import write_artifact
    from panoworld.gaussians.backends import Job
    from panoworld.gaussians.fusion import context_source

    frames = context_source(inputs["video"], inputs["poses"], context_views=params.context_views,
                            height=params.height, max_height=params.max_height)
    backend = backends.get(NAME, params.backend)
    try:
        result = backend.impl(Job(frames=frames, options=backend.options_of(params), depth=inputs.get("depth"),
                                  register=inputs.get("register"), navmesh=inputs.get("navmesh")))
    except StageInputError:
        raise
    except ValueError as e:  # empty depth, nothing left after pruning, bad params
        raise StageInputError(str(e)) from None
    return write_artifact(out_dir, result, frames, eval_views=params.eval_views, eval_height=params.eval_height,
                          full_sh=params.ply_full_sh, points=params.points_ply)


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
