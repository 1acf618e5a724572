"""ERP metric depth (ray distance, metres) + validity mask + the panorama they belong to."""

from __future__ import annotations

import enum
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.choices import Rescale
from panoworld.stage import Input, StageInputError, stage_main

NAME = "depth"
VERSION = "1"
ARTIFACT = "depth"
INPUTS = {
    "panorama": Input("file", help="equirectangular RGB panorama (2:1)"),
    "depth": Input("file", optional=True, help="measured ERP depth: .npy (metres), .exr (metres) or 16-bit .png"),
}


class Backend(enum.StrEnum):
    AUTO = "auto"
    """provided when a depth file is given, else depth-anything."""
    PROVIDED = "provided"
    DEPTH_ANYTHING = "depth-anything"


@dataclass(kw_only=True)
class Params:
    backend: Backend = Backend.AUTO
    """Where depth comes from: the scene's depth file (provided), a Depth Anything V2 model on cube views, or auto."""
    png_scale: float = 0.001
    """Metres per unit of a 16-bit depth PNG (0.001 = millimetres; Matterport-style PNGs use 0.00025)."""
    max_hole_px: int = 64
    """Invalid regions (NaN, inf, <= 0) of at most this many pixels are filled (harmonic); larger ones stay invalid."""
    max_gap_px: int = 0
    """Invalid runs of at most this many pixels between valid ones along a row or column are interpolated (the
    scan-line gaps of sparse LiDAR depth, e.g. 6); 0 = off."""
    weights: Path | None = None
    """depth-anything: local folder with config.json + model.safetensors (e.g. Depth-Anything-V2-Small-hf)."""
    view_size: int = 518
    """depth-anything: side of each perspective cube view fed to the model (a multiple of 14)."""
    fov_deg: float = 110.0
    """depth-anything: field of view of each of the 6 cube views (> 90 so neighbours overlap for alignment)."""
    device: str = "cpu"
    """depth-anything: torch device."""
    rescale: Rescale = Rescale.RELATIVE_ONLY
    """When to rescale depth so the floor lies camera_height below the camera (always: e.g. raw sensor units)."""
    camera_height: float = 1.6
    """Camera height above the floor in metres, used when rescaling."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    import cv2

    from panoworld import depth as dep

    rgb = dep.read_panorama(inputs["panorama"])
    H, W = rgb.shape[:2]
    backend = params.backend
    if backend == Backend.AUTO:
        backend = Backend.PROVIDED if inputs.get("depth") else Backend.DEPTH_ANYTHING
    info: dict = {"backend": backend.value, "height": H, "width": W}
    if backend == Backend.PROVIDED:
        path = inputs.get("depth")
        if path is None:
            raise StageInputError("backend provided needs --depth FILE (depth.npy, depth.exr or a 16-bit depth.png)")
        raw = dep.read_depth(path, png_scale=params.png_scale)
        raw, note = dep.conform_depth(raw, H, W, str(path))
        if note:
            info["resized"] = note
        valid = dep.valid_depth_mask(raw)
        info["valid_fraction_input"] = float(valid.mean())
        if not valid.any():
            raise StageInputError(f"{path}: no valid depth (all NaN, inf or <= 0); give a depth map with values in metres")
        depth, valid, n_filled = dep.fill_small_holes(raw, valid, params.max_hole_px, params.max_gap_px)
        info["filled_pixels"] = n_filled
        relative = False
    else:
        from panoworld.models.depth_anything import DepthAnything

        model = DepthAnything.from_pretrained(params.weights, input_size=params.view_size, device=params.device)
        res = dep.erp_depth_from_model(rgb, model, model.kind, fov_deg=params.fov_deg, view_size=params.view_size)
        depth, valid = res.depth, res.valid
        relative = model.kind == dep.DepthKind.RELATIVE
        info.update(model_kind=model.kind.value, view_overlap_rel_rmse=res.overlap_rel_rmse,
                    view_scales=res.scale.tolist(), view_shifts=res.shift.tolist())
        if not valid.any():
            raise StageInputError(f"--weights {params.weights}: the model predicted no positive depth anywhere")
    depth, scale_info = dep.metric_rescale(
        depth, valid, relative=relative, rescale=params.rescale, camera_height=params.camera_height
    )
    info.update(scale_info)
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    info["valid_fraction"] = float(valid.mean())
    info["depth_range_m"] = [float(depth[valid].min()), float(depth[valid].max())]
    np.save(out_dir / "depth.npy", depth)
    cv2.imwrite(str(out_dir / "valid.png"), valid.astype(np.uint8) * 255)
    cv2.imwrite(str(out_dir / "panorama.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return info


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
