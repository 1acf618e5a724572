"""Geometry-warped ERP RGB, depth and disocclusion mask at every trajectory pose (rendered from the scene mesh)."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from panoworld.conditions.warp import Backend
from panoworld.core.params import param
from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.io.rgb_image import RgbFormat

NAME = "conditions"
VERSION = "1"
ARTIFACT = "conditions"
INPUTS = {
    "mesh": Input("mesh", help="mesh artifact (mesh.ply with per-face valid flags)"),
    "trajectory": Input("trajectory", help="trajectory artifact (trajectory.json poses in the mesh's frame)"),
}


@dataclass(kw_only=True)
class Params:
    height: int = param(720, ge=2, le=8192)
    """Height of the condition frames in pixels (ERP, so width must be 2 x height)."""
    width: int = param(1440, ge=4, le=16384)
    """Width of the condition frames in pixels (2 x height)."""
    backend: Backend = Backend.RASTER
    """raster: numba ERP triangle rasteriser; raycast: Embree per-pixel rays (the slower exact reference)."""
    write_depth: bool = True
    """Also write the warped depth as uint16 millimetre PNGs."""
    split_silhouettes: bool = True
    """Cut stretched faces at their depth jumps so fore- and background extend half a pixel (tighter masks)."""
    preview_mp4: bool = False
    """Also write preview.mp4 (warped rgb | mask side by side, H.264) for a quick look."""
    rgb_format: RgbFormat = RgbFormat.JPEG
    """Format of rgb/ (what the video backend reads): jpeg (of rgb_quality, about 4x smaller) or png (lossless; masks
    and depth are always lossless PNG)."""
    rgb_quality: int = param(93, ge=1, le=100)
    """JPEG quality of rgb/ (as video.frame_quality)."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from plyfile import PlyParseError

    from panoworld.conditions.warp import iter_conditions, write_conditions
    from panoworld.core.conventions import check_erp_shape, check_poses
    from panoworld.geometry.erp_mesh import load_erp_mesh
    from panoworld.io.trajectory import load_trajectory

    try:
        check_erp_shape(params.height, params.width, "--height/--width")
    except ValueError as e:
        raise StageInputError(f"{e}; pass e.g. --height 720 --width 1440") from None
    traj = Path(inputs["trajectory"])
    try:
        poses = check_poses(load_trajectory(traj), f"{traj}/trajectory.json poses")
    except ValueError as e:
        raise StageInputError(f"{e}; rerun the trajectory stage or fix the trajectory file") from None
    mesh_dir = Path(inputs["mesh"])
    try:
        mesh = load_erp_mesh(mesh_dir)
    except (OSError, ValueError, KeyError, PlyParseError) as e:
        raise StageInputError(f"{mesh_dir}/mesh.ply: unreadable mesh ({e}); rerun the mesh stage") from None
    if len(mesh.faces) == 0:
        raise StageInputError(f"{mesh_dir}/mesh.ply: the mesh has no faces; check the depth artifact it came from")
    frames = iter_conditions(
        mesh, poses, params.height, params.width, backend=params.backend,
        split_silhouettes=params.split_silhouettes, progress=True,
    )
    info = write_conditions(out_dir, frames, poses, write_depth=params.write_depth, preview_mp4=params.preview_mp4,
                            rgb_format=params.rgb_format, rgb_quality=params.rgb_quality)
    info["backend"] = str(params.backend)
    info["num_faces"] = len(mesh.faces)
    info["ms_per_frame_render"] = round(1000.0 * info["render_s"] / info["num_frames"], 2)
    return info


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
