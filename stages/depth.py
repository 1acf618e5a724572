"""ERP metric depth (ray distance, metres) + validity mask + the panorama they belong to."""

from __future__ import annotations

import enum
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.choices import Rescale, RigMode
from panoworld.stage import Input, StageInputError, stage_main

NAME = "depth"
VERSION = "3"
ARTIFACT = "depth"
INPUTS = {
    "panorama": Input("file", help="equirectangular RGB panorama (2:1)"),
    "depth": Input("file", optional=True, help="measured ERP depth: .npy (metres), .exr (metres) or 16-bit .png"),
    "rig_mask": Input("file", optional=True, help="2:1 grayscale mask, white where the capture rig is (overrides detection)"),
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
    max_gap_px: int = -1
    """Invalid runs of at most this many pixels between valid ones along a row or column are interpolated (the
    scan-line gaps of sparse LiDAR depth, e.g. 6); 0 = off; -1 = auto: a width found from the depth when most
    invalid pixels lie in such short runs (sparse LiDAR), else off (panoworld.depth.auto_gap_px)."""
    weights: Path | None = None
    """depth-anything: local folder with config.json + model.safetensors (e.g. Depth-Anything-V2-Small-hf)."""
    view_size: int = 518
    """depth-anything: side of each perspective cube view fed to the model (a multiple of 14)."""
    fov_deg: float = 110.0
    """depth-anything: field of view of each of the 6 cube views (> 90 so neighbours overlap for alignment)."""
    device: str = "cpu"
    """depth-anything: torch device."""
    rescale: Rescale = Rescale.AUTO
    """When to rescale depth so the floor lies camera_height below the camera: auto = relative depth, and provided
    depth whose floor is no plausible capture height (0.9-2.4 m: unknown units); always: e.g. raw sensor units."""
    camera_height: float = 1.6
    """Camera height above the floor in metres, used when rescaling."""
    max_height: int = 1024
    """Resolution policy: panoramas taller than this are area-averaged (depth: nearest) to max_height x 2 max_height
    before anything else, so memory stays bounded downstream (8192x4096 -> 2048x1024); 0 = never."""
    min_depth_m: float = 0.1
    """Metric depths nearer than this (sensor noise, the capture rig) are invalid: they never become geometry."""
    rig: RigMode = RigMode.AUTO
    """Capture rig at the nadir (tripod, mount, nadir mask): auto = detect it without weights and remove it (floor
    inpainted, depth from the floor plane; a scene rig_mask.png overrides detection); keep = leave it (docs/rig.md)."""
    complete_poles: bool = True
    """Depth missing at the poles or in bands (LiDAR blind zones) is completed from the fitted floor and ceiling
    planes, within the room's extent (panoworld.depth_complete)."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    import cv2

    from panoworld import depth as dep

    notes: list[str] = []
    rgb = dep.read_panorama(inputs["panorama"], notes)
    H0, W0 = rgb.shape[:2]
    H, W = dep.working_size(H0, params.max_height)
    rgb = dep.resize_panorama(rgb, H)
    backend = params.backend
    if backend == Backend.AUTO:
        backend = Backend.PROVIDED if inputs.get("depth") else Backend.DEPTH_ANYTHING
    info: dict = {"backend": backend.value, "height": H, "width": W, "input_size": [W0, H0]}
    if (H, W) != (H0, W0):
        notes.append(f"panorama {W0}x{H0} is taller than max_height {params.max_height}: working at {W}x{H}")
    if backend == Backend.PROVIDED:
        path = inputs.get("depth")
        if path is None:
            raise StageInputError("backend provided needs --depth FILE (depth.npy, depth.exr or a 16-bit depth.png)")
        raw = dep.read_depth(path, png_scale=params.png_scale)
        if raw.shape[0] > H:  # fill at most at the working resolution (nearest: invalid never blends in)
            raw, note = dep.conform_depth(raw, H, W, str(path))
            notes.append(note)
        valid = dep.valid_depth_mask(raw)
        info["valid_fraction_input"] = float(valid.mean())
        if not valid.any():
            raise StageInputError(f"{path}: no valid depth (all NaN, inf or <= 0); give a depth map with values in metres")
        gap = params.max_gap_px
        if gap < 0:
            gap, share = dep.auto_gap_px(valid)
            info["short_gap_share"] = share
            if gap:
                notes.append(f"sparse depth ({share:.0%} of invalid pixels in short runs): scan-line gaps up to {gap} px filled")
        info["max_gap_px"] = gap
        depth, valid, n_filled = dep.fill_small_holes(raw, valid, params.max_hole_px, gap)
        info["filled_pixels"] = n_filled
        depth, note = dep.conform_depth(depth, H, W, str(path))
        if note:
            valid = depth > 0
            notes.append(note)
            info["resized"] = note
        relative = False
    else:
        if params.weights is None:
            raise StageInputError(
                f"{inputs['panorama']}: no depth file in the scene and no depth model weights; run "
                "`python runner.py weights fetch depth-anything-v2-small` and pass --set depth.weights=DIR "
                "(or put a metric depth.npy|exr|png next to the panorama)"
            )
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
    if scale_info.get("scale_note"):
        notes.append(scale_info["scale_note"])
    near = valid & (depth < params.min_depth_m)
    if near.any():
        valid &= ~near
        notes.append(f"{int(near.sum())} pixels nearer than min_depth_m {params.min_depth_m} m made invalid")
    if not valid.any():
        raise StageInputError(f"{inputs.get('depth') or inputs['panorama']}: no depth left beyond min_depth_m {params.min_depth_m} m")
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    if params.rig != RigMode.KEEP:
        from panoworld.rig import nadir_crop, rig_step

        before = rgb
        rgb, depth, valid, info["rig"], det = rig_step(rgb, depth, valid, info.get("camera_height_estimated_after"),
                                                         user_mask=inputs.get("rig_mask"))
        notes.append(f"capture rig {'removed' if det.found else 'not found'}: {det.reason}")
        if det.found:
            cv2.imwrite(str(out_dir / "rig_mask.png"), det.mask.astype(np.uint8) * 255)
            crops = np.concatenate([nadir_crop(before), nadir_crop(rgb)], axis=1)
            cv2.imwrite(str(out_dir / "nadir_before_after.jpg"), cv2.cvtColor(crops, cv2.COLOR_RGB2BGR))
    if params.complete_poles:
        from panoworld.depth_complete import complete_poles

        depth, valid, info["pole_completion"] = complete_poles(depth, valid)
        if info["pole_completion"]["completed_fraction"] > 0:
            notes.append(f"{info['pole_completion']['completed_fraction']:.1%} of the pixels (poles, bands) completed "
                         "from the floor/ceiling planes")
    info["valid_fraction"] = float(valid.mean())
    info["depth_range_m"] = [float(depth[valid].min()), float(depth[valid].max())]
    info["decisions"] = notes
    np.save(out_dir / "depth.npy", depth)
    cv2.imwrite(str(out_dir / "valid.png"), valid.astype(np.uint8) * 255)
    cv2.imwrite(str(out_dir / "panorama.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return info


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
