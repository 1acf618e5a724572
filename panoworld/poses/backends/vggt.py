"""vggt: the feed-forward PanoVGGT (needs weights): poses and dense depth."""

from __future__ import annotations

from dataclasses import dataclass

from panoworld.core.params import param
from panoworld.core.registry import register


@dataclass(kw_only=True)
class VggtOptions:
    weights: str | None = None
    """Directory holding config.json and model.safetensors of PanoVGGT."""
    device: str = "cpu"
    """Torch device (cpu, cuda, cuda:1)."""
    refine_iters: int | None = param(None, ge=0)
    """Steps of depth-consistency pose refinement on the model's own depth (None = the weights' config.json
    pose_refine_iters; 0 = the camera head's poses alone)."""


def estimate(job):
    from panoworld.models.panovggt import PanoVGGT
    from panoworld.poses.estimate import vggt_estimate

    o: VggtOptions = job.options
    model = PanoVGGT.from_pretrained(o.weights, flag="--vggt-weights", device=o.device)
    if o.refine_iters is not None:
        model.cfg.pose_refine_iters = o.refine_iters
    return vggt_estimate(job.video.rgb, model, job.planned, alignment=job.align,
                         out_hw=(job.video.height, job.video.width))


register("poses", "vggt", estimate, options=VggtOptions, key="vggt", needs_plan=False, recovers=True,
         weights=True)
