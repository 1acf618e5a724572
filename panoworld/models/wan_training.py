"""The paper's generator objective: flow matching mixed (rho = 0.75) with shortcut self-consistency; LoRA setup."""

from __future__ import annotations

import math

import torch
from torch import nn

from panoworld.models import wan_layers as wl


def prepare_for_training(
    transformer: nn.Module,
    cond_channels: int,
    *,
    rank: int = 48,
    alpha: float = 48,
    target_modules: tuple[str, ...] = wl.DEFAULT_LORA_TARGETS,
) -> list[nn.Parameter]:
    """Widen + step-size embed the transformer, add the LoRA adapter, freeze the backbone; return the trainable
    parameters (LoRA, patch embedding, step-size embedding), as in the paper."""
    wl.import_diffusers()
    from peft import LoraConfig

    wl.prepare_transformer(transformer, cond_channels)
    transformer.requires_grad_(False)
    config = LoraConfig(r=rank, lora_alpha=alpha, init_lora_weights=True, target_modules=list(target_modules))
    transformer.add_adapter(config, adapter_name=wl.ADAPTER_NAME)
    transformer.set_adapter(wl.ADAPTER_NAME)
    for name, p in transformer.named_parameters():
        p.requires_grad_("lora_" in name or name.startswith(wl.EXTRA_PREFIXES))
    return [p for p in transformer.parameters() if p.requires_grad]


def _noised(x0: torch.Tensor, sigma: torch.Tensor, generator: torch.Generator | None):
    noise = torch.randn(x0.shape, generator=generator, device="cpu").to(x0)
    s = sigma.view(-1, *([1] * (x0.ndim - 1)))
    return (1 - s) * x0 + s * noise, noise - x0


def _mse(pred: torch.Tensor, target: torch.Tensor, anchored: bool) -> torch.Tensor:
    if anchored:  # the clean first frame is given, not generated
        pred, target = pred[:, :, 1:], target[:, :, 1:]
    return torch.mean((pred - target) ** 2)


def flow_matching_loss(
    transformer: nn.Module,
    x0: torch.Tensor,
    condition: torch.Tensor,
    prompt_embeds: torch.Tensor,
    *,
    anchor: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """L_FM = || s(x_t, sigma, dt=0) - (eps - x0) ||^2 with x_t = (1 - sigma) x0 + sigma eps, sigma ~ U(0, 1).

    x0 (B, z, T_lat, h, w) clean normalised latents; condition, prompt_embeds, anchor as in wan_layers.velocity.
    """
    b = x0.shape[0]
    sigma = torch.rand(b, generator=generator).to(x0.device)
    x_t, target = _noised(x0, sigma, generator)
    v = wl.velocity(transformer, x_t, sigma, torch.zeros_like(sigma), condition, prompt_embeds, anchor)
    return _mse(v, target, anchor is not None)


def self_consistency_loss(
    transformer: nn.Module,
    x0: torch.Tensor,
    condition: torch.Tensor,
    prompt_embeds: torch.Tensor,
    *,
    anchor: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    max_steps: int = 128,
) -> torch.Tensor:
    """L_SC = || s(x_t, sigma, dt) - (v1 + v2) / 2 ||^2: the model itself (no grad) takes two half steps of dt / 2.

    dt ~ {1, 1/2, ..., 2/max_steps}, sigma on the grid of dt; the finest half step (1/max_steps) is the plain flow
    (step size 0), which is what L_FM trains.
    """
    b = x0.shape[0]
    levels = int(math.log2(max_steps))
    k = torch.randint(0, levels, (b,), generator=generator)
    dt = 0.5 ** k.double()
    j = torch.floor(torch.rand(b, generator=generator, dtype=torch.float64) * 2.0**k) + 1  # 1 .. 1/dt
    sigma = (j * dt).float().to(x0.device)
    dt = dt.float().to(x0.device)
    half = dt / 2
    teacher_dt = torch.where(half <= 1.0 / max_steps, torch.zeros_like(half), half)
    x_t, _ = _noised(x0, sigma, generator)
    with torch.no_grad():
        v1 = wl.velocity(transformer, x_t, sigma, teacher_dt, condition, prompt_embeds, anchor)
        x_mid = x_t - half.view(-1, 1, 1, 1, 1) * v1
        v2 = wl.velocity(transformer, x_mid, sigma - half, teacher_dt, condition, prompt_embeds, anchor)
        target = (v1 + v2) / 2
    v = wl.velocity(transformer, x_t, sigma, dt, condition, prompt_embeds, anchor)
    return _mse(v, target, anchor is not None)


def shortcut_objective(
    transformer: nn.Module,
    x0: torch.Tensor,
    condition: torch.Tensor,
    prompt_embeds: torch.Tensor,
    *,
    rho: float = 0.75,
    anchor: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    max_steps: int = 128,
) -> tuple[torch.Tensor, str]:
    """L_video = b L_FM + (1 - b) L_SC with b ~ Bernoulli(rho); returns (loss, 'fm' or 'sc')."""
    if torch.rand((), generator=generator).item() < rho:
        return flow_matching_loss(
            transformer, x0, condition, prompt_embeds, anchor=anchor, generator=generator
        ), "fm"
    return self_consistency_loss(
        transformer, x0, condition, prompt_embeds, anchor=anchor, generator=generator, max_steps=max_steps
    ), "sc"
