"""Per-frame canonical poses of the panoramic video (COLMAP SfM, planned, or PanoVGGT) with depth, a COLMAP model and transforms.json."""

from __future__ import annotations

import enum
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from panoworld.core import registry as backends
from panoworld.core.params import options, param
from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.poses.backends import Job, pick
from panoworld.poses.backends.vggt import VggtOptions
from panoworld.poses.options import Alignment, ColmapOptions

NAME = "poses"
VERSION = "3"
ARTIFACT = "poses"
INPUTS = {
    "video": Input("video", help="video artifact (video.json, frames/, depth/)"),
    "trajectory": Input(
        "trajectory", optional=True,
        help="planned trajectory artifact (trajectory.json); without it the poses recorded in video.json are the plan",
    ),
}


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
    backend: str = param("auto", choices=("auto", *backends.names(NAME)))
    """Pose estimator: colmap, planned or vggt (panoworld/poses/backends/); auto = planned when the video backend renders
    every frame at its planned pose (warp-inpaint, frame-inpaint), else vggt when vggt.weights is given, else colmap
    (a generated video, wan-shortcut). colmap on a rendered video checks the renderer against the plan."""
    align: Alignment = Alignment.SIM3
    """How estimates enter the canonical frame: sim3 to the plan (colmap needs it), se3 (keep the estimated metric
    scale), or none (vggt's own camera-0 frame)."""
    depth_source: DepthSource = DepthSource.AUTO
    """Where depth/NNNNNN.png (uint16 millimetres) comes from."""
    copy_frames: bool = False
    """Copy the frames into images/ (a self-contained dataset) instead of referencing ../video/frames."""
    colmap: ColmapOptions = options(ColmapOptions, "colmap")
    """colmap's options."""
    vggt: VggtOptions = options(VggtOptions, "vggt")
    """vggt's options."""

    RENAMED: ClassVar[dict[str, str]] = {
        **{k: f"colmap.{k}" for k in ("render_type", "matcher", "overlap", "mapper", "max_image_size", "max_features",
                                      "upsample_features", "num_threads", "seed")},
        **{k: f"vggt.{k}" for k in ("weights", "device", "refine_iters")},
    }


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from panoworld.io.video import read_video_frames
    from panoworld.poses.estimate import read_planned_trajectory, write_poses_artifact

    video = read_video_frames(inputs["video"])
    planned = read_planned_trajectory(inputs["trajectory"]) if inputs.get("trajectory") else video.poses
    if planned is not None and len(planned) != video.num_frames:
        raise StageInputError(
            f"the planned trajectory has {len(planned)} poses but video.json lists {video.num_frames} frames; "
            "rerun the video stage on this trajectory"
        )
    backend, decisions = pick(params.backend, _video_backend(Path(inputs["video"]), video.meta), params)
    if planned is not None and backend.traits.get("needs_baseline") and np.ptp(planned[:, :3, 3], axis=0).max() < 1e-6:
        decisions.append(f"the trajectory does not move (rotation only: no room to move), so {backend.name} has no "
                         "baseline; planned poses used")
        backend = backends.with_trait(NAME, "copies_plan")
    if planned is None and (backend.traits["needs_plan"] or params.align != Alignment.NONE):
        raise StageInputError(
            f"backend {backend.name} with align {params.align} needs planned poses: give --trajectory "
            "(or a video.json with poses)"
        )
    est = backend.impl(Job(video=video, planned=planned, align=params.align, options=backend.options_of(params)))

    depth, depth_from = _choose_depth(params.depth_source, video, est)
    info = write_poses_artifact(out_dir, est, video, planned, depth=depth, copy_frames=params.copy_frames)
    return {**info, "depth_source": depth_from, "decisions": decisions, "backend_requested": str(params.backend)}


def _video_backend(video_dir: Path, video_json: dict) -> str | None:
    """The video backend that produced the video artifact: its manifest's params, else what video.json records."""
    from panoworld.io.manifest import ArtifactError, read_manifest

    try:
        return str(read_manifest(video_dir, "video")["params"]["backend"])
    except (ArtifactError, KeyError, TypeError):
        return video_json.get("backend")


def _choose_depth(src: DepthSource, video, est) -> tuple[list | None, str]:
    """Per-frame depth to write (PNG paths to copy or arrays in metres) and where it came from."""
    from panoworld.io.depth_png import read_depth_png
    from panoworld.io.video import DEPTH_SCALE

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
