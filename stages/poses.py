"""Per-frame canonical poses of the panoramic video (COLMAP SfM, planned, or PanoVGGT) with depth, a COLMAP model and transforms.json."""

from __future__ import annotations

import enum
import sys
from dataclasses import dataclass
from pathlib import Path

from panoworld.choices import Alignment, Matcher, RenderType
from panoworld.stage import Input, StageInputError, stage_main

NAME = "poses"
VERSION = "2"
ARTIFACT = "poses"
INPUTS = {
    "video": Input("video", help="video artifact (video.json, frames/, depth/)"),
    "trajectory": Input(
        "trajectory", optional=True,
        help="planned trajectory artifact (trajectory.json); without it the poses recorded in video.json are the plan",
    ),
}


class Backend(enum.StrEnum):
    COLMAP = "colmap"
    """COLMAP panorama SfM (pycolmap), Sim(3)-aligned to the planned trajectory for metric scale and canonical frame."""
    PLANNED = "planned"
    """The planned trajectory as it is (for generators that follow it exactly)."""
    VGGT = "vggt"
    """The feed-forward PanoVGGT (needs --weights): poses and dense depth."""


class Mapper(enum.StrEnum):
    GLOBAL = "global"
    """COLMAP's global mapper (GLOMAP): rotation averaging, global positioning, one bundle adjustment."""
    INCREMENTAL = "incremental"
    """COLMAP's incremental mapper: registers frames one by one with repeated bundle adjustment (slower)."""


class DepthSource(enum.StrEnum):
    AUTO = "auto"
    """The video's depth when it has some, else the backend's (vggt), else none."""
    VIDEO = "video"
    """The video's depth (error if it has none)."""
    BACKEND = "backend"
    """The backend's predicted depth (vggt only)."""
    NONE = "none"
    """Write no depth."""


@dataclass(kw_only=True)
class Params:
    backend: Backend = Backend.COLMAP
    """Pose estimator."""
    render_type: RenderType = RenderType.SPHERICAL
    """colmap: native equirectangular camera (spherical) or rigs of perspective views (fallback for hard cases)."""
    matcher: Matcher = Matcher.SEQUENTIAL
    """colmap: which frame pairs are matched."""
    overlap: int = 10
    """colmap sequential: each frame is matched with this many successors (and quadratic overlap beyond)."""
    mapper: Mapper = Mapper.GLOBAL
    """colmap spherical: how the matched frames become a model."""
    max_image_size: int = 1024
    """colmap spherical: SIFT runs on frames downscaled to at most this width (0 = as stored); keypoints are scaled
    back, so the model stays in the video's pixel coordinates."""
    max_features: int = 2048
    """colmap spherical: SIFT features per frame."""
    upsample_features: bool = False
    """colmap spherical: start SIFT's pyramid at the 2x upsampled frame (COLMAP's default; ~3x the extraction time).
    Always on for frames narrower than 640 px, where the plain pyramid finds too few features."""
    num_threads: int = -1
    """colmap: CPU threads (-1 = all)."""
    seed: int = 0
    """colmap: random seed of RANSAC and the mapper."""
    align: Alignment = Alignment.SIM3
    """How estimates enter the canonical frame: sim3 to the plan (colmap needs it), se3 (keep the estimated metric
    scale), or none (vggt's own camera-0 frame)."""
    weights: str | None = None
    """vggt: directory holding config.json and model.safetensors of PanoVGGT."""
    device: str = "cpu"
    """vggt: torch device (cpu, cuda, cuda:1)."""
    refine_iters: int | None = None
    """vggt: steps of depth-consistency pose refinement on the model's own depth (None = the weights' config.json
    pose_refine_iters; 0 = the camera head's poses alone)."""
    depth_source: DepthSource = DepthSource.AUTO
    """Where depth/NNNNNN.png (uint16 millimetres) comes from."""
    copy_frames: bool = False
    """Copy the frames into images/ (a self-contained dataset) instead of referencing ../video/frames."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from panoworld.poses import (
        colmap_estimate,
        planned_estimate,
        read_planned_trajectory,
        read_video_frames,
        vggt_estimate,
        write_poses_artifact,
    )

    video = read_video_frames(inputs["video"])
    planned = read_planned_trajectory(inputs["trajectory"]) if inputs.get("trajectory") else video.poses
    if planned is not None and len(planned) != video.num_frames:
        raise StageInputError(
            f"the planned trajectory has {len(planned)} poses but video.json lists {video.num_frames} frames; "
            "rerun the video stage on this trajectory"
        )
    if planned is None and (params.backend != Backend.VGGT or params.align != Alignment.NONE):
        raise StageInputError(
            f"backend {params.backend} with align {params.align} needs planned poses: give --trajectory "
            "(or a video.json with poses)"
        )
    if params.backend == Backend.COLMAP:
        from panoworld.poses import SfmOptions

        sfm = SfmOptions(max_image_size=params.max_image_size, max_features=params.max_features,
                         upsample=params.upsample_features, mapper=str(params.mapper), overlap=params.overlap,
                         num_threads=params.num_threads, seed=params.seed)
        est = colmap_estimate(video.rgb, planned, render_type=params.render_type, matcher=params.matcher, sfm=sfm,
                              alignment=params.align)
    elif params.backend == Backend.PLANNED:
        est = planned_estimate(planned)
    else:
        from panoworld.models.panovggt import PanoVGGT

        model = PanoVGGT.from_pretrained(params.weights, flag="--weights", device=params.device)
        if params.refine_iters is not None:
            if params.refine_iters < 0:
                raise StageInputError(f"refine_iters={params.refine_iters} but expected >= 0 (0 = off)")
            model.cfg.pose_refine_iters = params.refine_iters
        est = vggt_estimate(video.rgb, model, planned, alignment=params.align, out_hw=(video.height, video.width))

    depth, depth_from = _choose_depth(params.depth_source, video, est)
    info = write_poses_artifact(out_dir, est, video, planned, depth=depth, copy_frames=params.copy_frames)
    return {**info, "depth_source": depth_from}


def _choose_depth(src: DepthSource, video, est) -> tuple[list | None, str]:
    """Per-frame depth to write (PNG paths to copy or arrays in metres) and where it came from."""
    from panoworld.poses import DEPTH_SCALE, read_depth_png

    if src == DepthSource.VIDEO and not video.has_depth:
        raise StageInputError("depth_source=video but video.json has no depth; use --depth-source auto or none")
    if src in (DepthSource.AUTO, DepthSource.VIDEO) and video.has_depth:
        if abs(video.depth_scale - DEPTH_SCALE) > 1e-12:
            return [read_depth_png(p, video.depth_scale) for p in video.depth], "video"
        return list(video.depth), "video"
    if src in (DepthSource.AUTO, DepthSource.BACKEND) and est.depth is not None:
        return list(est.depth), "backend"
    if src == DepthSource.BACKEND:
        raise StageInputError(f"depth_source=backend but backend {est.backend} predicts no depth; use --backend vggt")
    return None, "none"


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
