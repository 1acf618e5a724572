"""Options of the paper's generator (Wan2.2-TI2V-5B + LoRA, shortcut sampling); light to import (no torch)."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

from panoworld.core.params import param

DEFAULT_PROMPT = "a panoramic video walking through an indoor scene"


def resolve_device(name: str) -> str:
    """`auto` -> "cuda" when CUDA is available, else "cpu"; any other device name unchanged."""
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


class Sampler(enum.StrEnum):
    SHORTCUT = "shortcut"
    FLOW = "flow"


@dataclass(kw_only=True)
class WanShortcutConfig:
    weights: Path | None = None
    """Local Wan2.2-TI2V-5B-Diffusers directory (transformer/, vae/, optionally text_encoder/ + tokenizer/)."""
    lora: Path | None = None
    """LoRA safetensors of the trained generator (rank 48, alpha 48; diffusers Wan LoRA layout)."""
    extra_weights: Path | None = None
    """Safetensors of the other trained weights: widened patch_embedding.* and step_embedder.*."""
    prompt_embeds: Path | None = None
    """Precomputed UMT5 prompt embeddings (.safetensors/.pt with 'prompt_embeds' (1, L, 4096) and optionally
    'negative_prompt_embeds'); needed when the weights directory has no text_encoder/."""
    sampler: Sampler = Sampler.SHORTCUT
    """shortcut: few large Euler steps told their step size (the paper); flow: plain flow-matching Euler."""
    steps: int = param(4, ge=1)
    """Denoising steps (a power of two for the shortcut sampler)."""
    guidance: float = param(1.0, ge=0)
    """Classifier-free guidance scale; 1 = guidance-free (one forward per step), otherwise two."""
    shift: float = param(5.0, gt=0)
    """Timestep shift of the flow sampler's schedule (Wan's flow_shift); the shortcut sampler uses uniform steps."""
    dtype: str = "bfloat16"
    """Transformer (and text encoder) dtype; the VAE runs in float32."""
    device: str = "auto"
    """Execution device (the video stage's wan-shortcut backend also takes auto = cuda when available, else cpu)."""
    cpu_offload: bool = False
    """Keep models on the CPU and move each to the device only while it runs (fits a 24 GB GPU)."""
    vae_tiling: bool = True
    """Encode/decode with the VAE in spatial tiles (lower memory for 704x1408 ERP)."""
    seed: int = 0
    """Seed of the initial noise (drawn on the CPU, so equal across devices)."""
    prompt: str = DEFAULT_PROMPT
    """Text prompt; ignored when prompt_embeds is given."""
    negative_prompt: str = ""
    """Negative prompt for guidance != 1 (an all-zero embedding when only prompt_embeds without a negative is given)."""
    anchor_first_frame: bool = True
    """When frame 0's condition is the input panorama (>= 99 % valid), keep its latent clean (Wan2.2 TI2V rule)."""
