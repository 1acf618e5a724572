"""One training clip's conditions (warped RGB, mask, depth) and targets, as a cacheable unit following the stage contract."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.io.jsonio import write_json

NAME = "clip"
VERSION = "2"
ARTIFACT = "clip"
INPUTS = {
    "gt_index": Input("file", help="the scene's gt/gt.json (tracks, frame files)"),
    "source_rgb": Input("file", optional=True, help="source frame RGB (absent: rendered from the synthetic scene)"),
    "source_depth": Input("file", optional=True, help="source frame depth .npy (absent: rendered from the synthetic scene)"),
    "scene_glb": Input("file", optional=True, help="the scene's gt/scene.glb when frames are rendered on demand"),
}


@dataclass(kw_only=True)
class Params:
    track: int = 0
    """Index of the ground-truth track in gt.json."""
    start: int = 0
    """Track frame of the clip's first pose, whose panorama and depth are the warp source."""
    length: int = 81
    """Number of frames in the clip."""
    stride: float = 1
    """Traversal scale: track frames between consecutive clip frames (clip frame k = start + round(stride k))."""
    height: int = 480
    """Output ERP height (width = 2 x height)."""
    write_depth: bool = True
    """Also write warped depth (uint16 millimetres)."""
    write_targets: bool = True
    """Also write the ground-truth target frames of the clip."""


def frame_indices(params: Params) -> np.ndarray:
    return params.start + np.round(params.stride * np.arange(params.length)).astype(np.int64)


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from panoworld.conditions.warp import iter_conditions, write_conditions
    from panoworld.geometry.erp_mesh import erp_mesh_from_depth
    from panoworld.tools.dataset import DatasetScene

    scene = DatasetScene.from_gt_index(inputs["gt_index"])
    idx = frame_indices(params)
    n = scene.n_frames(params.track)
    if params.length < 1 or params.stride <= 0 or idx[-1] >= n or params.start < 0:
        raise StageInputError(f"{inputs['gt_index']}: clip frames {idx[0]}..{idx[-1]} outside track {params.track} (0..{n - 1})")
    h, w = params.height, 2 * params.height
    rgb, depth = scene.frame(params.track, params.start, h)
    valid = np.isfinite(depth) & (depth > 0)
    mesh = erp_mesh_from_depth(depth, rgb, valid)
    poses = scene.poses(params.track)[idx]
    canonical_from_world = np.linalg.inv(poses[0])
    rel = canonical_from_world[None] @ poses
    frames = iter_conditions(mesh, rel, h, w)  # the conditions stage's renderer and defaults
    # workers=0: one thread per process, so precompute scales with its process count
    info = write_conditions(out_dir / "cond", frames, rel, write_depth=params.write_depth, workers=0)
    targets = []
    if params.write_targets:
        import cv2

        (out_dir / "target").mkdir()
        for k, i in enumerate(idx):
            t_rgb, _ = scene.frame(params.track, int(i), h)
            name = f"target/{k:06d}.png"
            cv2.imwrite(str(out_dir / name), t_rgb[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1])
            targets.append(name)
    clip = {
        "scene": scene.name,
        "track": params.track,
        "start": params.start,
        "length": params.length,
        "stride": params.stride,
        "height": h,
        "width": w,
        "track_frames": idx.tolist(),
        "frame": "canonical: the clip's source camera (pose 0 = identity)",
        "poses": rel.tolist(),
        "world_from_canonical": poses[0].tolist(),
        "conditions": "cond/conditions.json",
        "targets": targets,
    }
    write_json(out_dir / "clip.json", clip)
    return info


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
