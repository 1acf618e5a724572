"""decoder: the learned voxel-aligned Gaussian head of PanoVGGT (a stage-2 export of `runner.py train recon`)."""

from __future__ import annotations

from dataclasses import dataclass

from panoworld.core.registry import register


@dataclass(kw_only=True)
class DecoderOptions:
    weights: str | None = None
    """Directory holding config.json and model.safetensors of PanoVGGT with a Gaussian head (runner.py train recon
    --stage 2 exports it; its voxel size and input height win)."""
    device: str = "cpu"
    """Torch device (cpu, cuda)."""


def decode(job):
    from panoworld.models.panovggt import PanoVGGT

    o: DecoderOptions = job.options
    model = PanoVGGT.from_pretrained(o.weights, flag="--decoder-weights", device=o.device)
    model.require_gaussian_head("--decoder-weights")
    return model.decode(job.frames.load())


register("gaussians", "decoder", decode, options=DecoderOptions, key="decoder", weights=True)
