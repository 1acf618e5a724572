"""ERP metric depth (ray distance, metres) + validity mask + the panorama they belong to."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from panoworld.core import registry as backends
from panoworld.core.params import options, param
from panoworld.depth.backends import Job
from panoworld.depth.backends.depth_anything import DepthAnythingOptions
from panoworld.depth.backends.provided import ProvidedOptions
from panoworld.depth.clean import clean_depth
from panoworld.depth.options import Rescale, RigMode
from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.register.inputs import DEPTH_SUFFIXES, PANORAMA_SUFFIXES, RIG_MASK_SUFFIXES

NAME = "depth"
VERSION = "3"
ARTIFACT = "depth"
INPUTS = {
    "panorama": Input("file", optional=True, help="equirectangular RGB panorama (2:1); or --panoramas"),
    "depth": Input("file", optional=True, help="measured ERP depth: .npy (metres), .exr (metres) or 16-bit .png"),
    "rig_mask": Input("file", optional=True, help="2:1 grayscale mask, white where the capture rig is (overrides detection)"),
    "panoramas": Input("dir", optional=True, suffixes=PANORAMA_SUFFIXES, help="a home: directory of two or more panoramas NAME.png|jpg (docs/multi.md)"),
    "depths": Input("dir", optional=True, suffixes=DEPTH_SUFFIXES, help="a home: directory of depth files NAME.npy|exr|png (same stems)"),
    "rig_masks": Input("dir", optional=True, suffixes=RIG_MASK_SUFFIXES, help="a home: rig masks NAME.png (2:1, white = rig; same stems as the "
                       "panoramas), each overriding detection on its panorama"),
}


@dataclass(kw_only=True)
class Params:
    backend: str = param("auto", choices=("auto", *backends.names(NAME)))
    """Where depth comes from: the scene's depth file (provided), a Depth Anything V2 model on cube views
    (depth-anything), or auto: provided when a depth file is given, else depth-anything (with depth_anything.weights,
    else the Depth Anything V2 weights found in the local Hugging Face cache) (panoworld/depth/backends/)."""
    rescale: Rescale = Rescale.AUTO
    """When to rescale depth so the floor lies camera_height below the camera: auto = relative depth, and provided
    depth whose floor is no plausible capture height (0.9-2.4 m: millimetres or centimetres converted to metres, else
    unknown units); always: e.g. raw sensor units."""
    camera_height: float = param(1.6, gt=0)
    """Camera height above the floor in metres, used when rescaling."""
    max_height: int = param(1024, ge=0)
    """Resolution policy: panoramas taller than this are area-averaged (depth: nearest) to max_height x 2 max_height
    before anything else, so memory stays bounded downstream (8192x4096 -> 2048x1024); 0 = never."""
    min_depth_m: float = param(0.1, ge=0)
    """Metric depths nearer than this (sensor noise, the capture rig) are invalid: they never become geometry."""
    rig: RigMode = RigMode.AUTO
    """Capture rig at the nadir (tripod, mount, nadir mask): auto = detect it without weights and remove it (floor
    inpainted, depth from the floor plane; a scene rig_mask.png overrides detection); keep = leave it (docs/rig.md)."""
    rig_detector: str = param("heuristic", choices=backends.names("rig"))
    """How rig=auto finds the rig: heuristic (colour and shape tests, no weights) or learned (a small U-Net trained
    by bench/train_rig.py on synthetic rigs; weights in rig_weights); both keep seen objects (panoworld/depth/rig/backends/)."""
    rig_weights: Path | None = None
    """Directory with the rig U-Net's config.json + model.safetensors (rig_detector=learned)."""
    rig_device: str = "cpu"
    """Torch device of the learned rig detector."""
    level: bool = True
    """A panorama taken 1-45 deg off level (its vertical lines, checked by its depth's floor where it shows one) is
    levelled before anything else: the scene is built in the levelled camera's frame, the manifest's info.level
    gives the rotation (panoworld/depth/level.py, docs/conventions.md); false = build it as taken."""
    complete_poles: bool = True
    """Depth missing at the poles or in bands (LiDAR blind zones) is completed from the fitted floor and ceiling
    planes, within the room's extent (panoworld.depth.complete)."""
    complete_dropouts: bool = True
    """Depth still missing after that (dropouts inside the scan: glass, dark surfaces, object silhouettes) is
    completed: the rim's plane where it has one, else smooth continuation of the rim where that agrees with the
    nearest depth, else the nearest depth (a step at a silhouette) (panoworld.depth.complete.complete_dropouts)."""
    provided: ProvidedOptions = options(ProvidedOptions, "provided")
    """provided's options."""
    depth_anything: DepthAnythingOptions = options(DepthAnythingOptions, "depth-anything")
    """depth-anything's options."""

    RENAMED: ClassVar[dict[str, str]] = {
        **{k: f"provided.{k}" for k in ("png_scale", "max_hole_px", "max_gap_px")},
        **{k: f"depth_anything.{k}" for k in ("weights", "view_size", "fov_deg", "device")},
    }


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    if inputs.get("panoramas") is None:
        if inputs.get("panorama") is None:
            raise StageInputError("give --panorama FILE (one panorama) or --panoramas DIR (a home, docs/multi.md)")
        if inputs.get("rig_masks") is not None:
            raise StageInputError(f"{inputs['rig_masks']}: rig_masks/ is for a home (panoramas/); one panorama's mask "
                                  "is --rig-mask FILE (SCENE/rig_mask.png)")
        return depth_of_panorama(inputs, params, out_dir)
    from panoworld.io.home import HOME_DIR, HOME_INFO
    from panoworld.io.safe_write import inside
    from panoworld.register.inputs import DEPTHS_DIR, find_home_files

    home = find_home_files(inputs["panoramas"], inputs.get("depths"), inputs.get("rig_masks"))
    names = home.names
    depth_dir = inputs.get("depths") or inputs["panoramas"].parent / DEPTHS_DIR
    hints = {name: f"give its metric depth as {depth_dir / name}.npy|exr|png" for name in names}
    for name in names:  # a panorama the depth cannot come from fails the home at once, not after the others' work
        given = {"panorama": home.panoramas[name], "depth": home.depths.get(name)}
        backend, opts, _ = _backend(params, given, [])
        if backend.traits.get("preflight") is not None:
            backend.traits["preflight"](Job(rgb=None, depth_file=given["depth"], panorama_file=given["panorama"],
                                            options=opts, depth_hint=hints[name]))
    infos, dirs = {}, {}
    for k, name in enumerate(names):  # the first panorama's files at the top level: the world frame's panorama
        sub = out_dir if k == 0 else inside(out_dir / HOME_DIR, name)
        sub.mkdir(parents=True, exist_ok=True)
        infos[name] = depth_of_panorama({"panorama": home.panoramas[name], "depth": home.depths.get(name),
                                         "rig_mask": home.rig_masks.get(name)}, params, sub, depth_hint=hints[name])
        dirs[name] = sub.relative_to(out_dir).as_posix()
    return {**infos[names[0]], HOME_INFO: {"names": names, "dirs": dirs, "panoramas": infos}}


def depth_of_panorama(inputs: dict[str, Path | None], params: Params, out_dir: Path, *,
                      depth_hint: str | None = None) -> dict:
    """Depth, validity and the cleaned panorama (rig removed, poles completed) of one panorama into out_dir;
    depth_hint: where the user would give its depth (the backends' error messages)."""
    import cv2

    from panoworld.depth import depth_map as dep
    from panoworld.depth.level import level_panorama
    from panoworld.geometry.level import levelled, levelled_depth
    from panoworld.io.depth import read_panorama
    from panoworld.io.images import read_rig_mask

    notes: list[str] = []
    rgb = read_panorama(inputs["panorama"], notes)
    H0, W0 = rgb.shape[:2]
    H, W = dep.working_size(H0, params.max_height)
    rgb = dep.resize_panorama(rgb, H)
    if (H, W) != (H0, W0):
        notes.append(f"panorama {W0}x{H0} is taller than max_height {params.max_height}: working at {W}x{H}")
    backend, opts, found = _backend(params, inputs, notes)
    info: dict = {"backend": backend.name, "height": H, "width": W, "input_size": [W0, H0]}
    res = backend.impl(Job(rgb=rgb, depth_file=inputs.get("depth"), panorama_file=inputs["panorama"],
                           options=opts, notes=notes, depth_hint=depth_hint or Job.depth_hint))
    info.update(res.info)
    if found is not None:
        info["weights_found"] = found
    depth, valid, rig_mask = res.depth, res.valid, inputs.get("rig_mask")
    if params.level:
        lev = level_panorama(rgb, depth, valid)
        info["level"] = lev.info
        notes.extend([lev.note] if lev.note else [])
        if (R := lev.level_from_cam) is not None:
            rgb, depth = levelled(rgb, R), levelled_depth(np.where(valid, depth, 0), R)
            valid = levelled(valid, R, nearest=True)
            if rig_mask is not None and params.rig != RigMode.KEEP:
                rig_mask = levelled(read_rig_mask(rig_mask, (H, W)), R, nearest=True)
    rig_backend = None if params.rig == RigMode.KEEP else backends.get("rig", params.rig_detector).impl
    c = clean_depth(rgb, depth, valid, relative=res.relative, rescale=params.rescale,
                    camera_height=params.camera_height, min_depth_m=params.min_depth_m,
                    detect_rig=None if rig_backend is None else (lambda *a: rig_backend(*a, params)),
                    rig_mask=rig_mask, complete_poles=params.complete_poles,
                    complete_dropouts=params.complete_dropouts, source=inputs.get("depth") or inputs["panorama"])
    info.update(c.info)
    info["decisions"] = notes + c.notes
    if c.rig is not None and c.rig.found:
        from panoworld.depth.rig.face import nadir_crop
        from panoworld.io.home import RIG_MASK_PNG

        cv2.imwrite(str(out_dir / RIG_MASK_PNG), c.rig.mask.astype(np.uint8) * 255)
        crops = np.concatenate([nadir_crop(rgb), nadir_crop(c.rgb)], axis=1)
        cv2.imwrite(str(out_dir / "nadir_before_after.jpg"), cv2.cvtColor(crops, cv2.COLOR_RGB2BGR))
    rgb, depth, valid = c.rgb, c.depth, c.valid
    np.save(out_dir / "depth.npy", depth)
    cv2.imwrite(str(out_dir / "valid.png"), valid.astype(np.uint8) * 255)
    cv2.imwrite(str(out_dir / "panorama.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return info


def _backend(params: Params, inputs: dict[str, Path | None], notes: list[str]) -> tuple:
    """The depth backend of a panorama's inputs (params.backend, auto: the one using the most of them) with its options,
    weights found on disk filled in (_with_weights_on_disk): (backend, options, what was found or None)."""
    backend = backends.pick(NAME, params.backend, inputs)
    return (backend, *_with_weights_on_disk(backend, backend.options_of(params), notes))


def _with_weights_on_disk(backend, opts, notes: list[str]) -> tuple:
    """A backend with trait finds_weights and no weights given takes the first registered weights of its param in the
    local Hugging Face cache (`runner.py weights fetch NAME`): (its options, what was found for the manifest)."""
    if not backend.traits.get("finds_weights") or opts is None or opts.weights is not None:
        return opts, None
    from dataclasses import replace

    from panoworld.framework.hub.resolve import find_local_weights

    param = f"{NAME}.{backend.key}.weights"
    hit = find_local_weights(param)
    if hit is None:
        return opts, None
    entry, path, commit = hit
    notes.append(f"no depth file: depth from {entry.name} found on disk (hf:{entry.repo} {commit[:12]}; another: "
                 f"--set {param}=DIR)")
    return replace(opts, weights=path), {"name": entry.name, "spec": f"hf:{entry.repo}", "commit": commit,
                                         "path": str(path)}


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
