"""provided: the scene's measured depth file (.npy or .exr in metres, or a 16-bit .png), small holes filled."""

from __future__ import annotations

from dataclasses import dataclass

from panoworld.core.errors import InputError
from panoworld.core.params import param
from panoworld.core.registry import register
from panoworld.depth.outliers import mask_and_record


@dataclass(kw_only=True)
class ProvidedOptions:
    png_scale: float = param(0.001, gt=0)
    """Metres per unit of a 16-bit depth PNG (0.001 = millimetres; Matterport-style PNGs use 0.00025)."""
    max_hole_px: int = param(64, ge=0)
    """Invalid regions (NaN, inf, <= 0) of at most this many pixels are filled (harmonic); larger ones stay invalid."""
    max_gap_px: int = param(-1, ge=-1)
    """Invalid runs of at most this many pixels between valid ones along a row or column are interpolated (the
    scan-line gaps of sparse LiDAR depth, e.g. 6); 0 = off; -1 = auto: a width found from the depth when most
    invalid pixels lie in such short runs (sparse LiDAR), else off (panoworld.depth.depth_map.auto_gap_px)."""


def has_depth_file(job) -> None:
    """Raise the one-line refusal when the panorama has no depth file (the depth stage checks every panorama of a home
    with it before working on any)."""
    if job.depth_file is None:
        raise InputError(f"{job.panorama_file}: backend provided needs its depth file; {job.depth_hint}")


def read(job):
    from panoworld.depth import depth_map as dep
    from panoworld.depth.backends import Result
    from panoworld.io.depth import read_depth

    o: ProvidedOptions = job.options
    has_depth_file(job)
    path = job.depth_file
    H, W = job.rgb.shape[:2]
    info: dict = {}
    raw = read_depth(path, png_scale=o.png_scale)
    if raw.shape[0] > H:  # fill at most at the working resolution (invalid never blends in)
        raw, note = dep.conform_depth(raw, H, W, str(path))
        job.notes.append(note)
    valid = dep.valid_depth_mask(raw)
    info["valid_fraction_input"] = float(valid.mean())
    if not valid.any():
        raise InputError(f"{path}: no valid depth (all NaN, inf or <= 0); give a depth map with values in metres")
    valid = mask_and_record(raw, valid, info, job.notes)  # before hole filling (lone spikes get filled) and the rescale
    gap = o.max_gap_px
    if gap < 0:
        gap, share = dep.auto_gap_px(valid)
        info["short_gap_share"] = share
        if gap:
            job.notes.append(f"sparse depth ({share:.0%} of invalid pixels in short runs): scan-line gaps up to {gap} px filled")
    info["max_gap_px"] = gap
    depth, valid, n_filled = dep.fill_small_holes(raw, valid, o.max_hole_px, gap)
    info["filled_pixels"] = n_filled
    depth, note = dep.conform_depth(depth, H, W, str(path))
    if note:
        valid = depth > 0
        job.notes.append(note)
        info["resized"] = note
    return Result(depth, valid, relative=False, info=info)


register("depth", "provided", read, options=ProvidedOptions, key="provided", needs_inputs=("depth",),
         preflight=has_depth_file)
