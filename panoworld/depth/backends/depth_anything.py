"""depth-anything: a Depth Anything V2 model on 6 overlapping cube views, merged into ERP depth (needs weights)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from panoworld.core.errors import InputError
from panoworld.core.params import param
from panoworld.core.registry import register
from panoworld.depth.outliers import mask_and_record


@dataclass(kw_only=True)
class DepthAnythingOptions:
    weights: Path | None = None
    """Local folder with config.json + model.safetensors (e.g. Depth-Anything-V2-Small-hf) or an `hf:` id; None = the
    first registered Depth Anything V2 weights in the local Hugging Face cache (`runner.py weights fetch NAME`)."""
    view_size: int = param(518, ge=14)
    """Side of each perspective cube view fed to the model (a multiple of 14)."""
    fov_deg: float = param(110.0, gt=90, lt=180)
    """Field of view of each of the 6 cube views (> 90 so neighbours overlap for alignment)."""
    device: str = "cpu"
    """Torch device."""


def has_weights(job) -> None:
    """Raise the one-line refusal when no weights are given or found on disk (the depth stage checks every panorama of
    a home with it before working on any)."""
    if job.options.weights is None:  # the depth stage puts weights found on disk here (trait finds_weights)
        raise InputError(
            f"{job.panorama_file}: no depth file in the scene and no depth model on disk; run "
            f"`python runner.py weights fetch depth-anything-v2-small` (or {job.depth_hint})"
        )


def predict(job):
    from panoworld.depth.backends import Result
    from panoworld.geometry.cube_views import erp_depth_from_model
    from panoworld.io.depth import DepthKind
    from panoworld.models.depth_anything import DepthAnything

    o: DepthAnythingOptions = job.options
    has_weights(job)
    model = DepthAnything.from_pretrained(o.weights, input_size=o.view_size, device=o.device)
    res = erp_depth_from_model(job.rgb, model, model.kind, fov_deg=o.fov_deg, view_size=o.view_size)
    if not res.valid.any():
        raise InputError(f"--depth-anything-weights {o.weights}: the model predicted no positive depth anywhere")
    info = dict(model_kind=model.kind.value, view_overlap_rel_rmse=res.overlap_rel_rmse,
                view_scales=res.scale.tolist(), view_shifts=res.shift.tolist())
    valid = mask_and_record(res.depth, res.valid, info, job.notes)  # before the floor-based rescale
    return Result(res.depth, valid, relative=model.kind == DepthKind.RELATIVE, info=info)


register("depth", "depth-anything", predict, options=DepthAnythingOptions, key="depth_anything", needs_inputs=(),
         finds_weights=True, preflight=has_weights)
