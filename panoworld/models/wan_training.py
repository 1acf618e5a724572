"""The paper's generator objective: flow matching mixed (rho = 0.75) with shortcut self-consistency; LoRA setup."""

from __future__ import annotations

import contextlib
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


class EmaTeacher:
    """The frozen teacher of the self-consistency loss: an exponential moving average of the student's *trainable*
    tensors (LoRA, patch and step-size embeddings), swapped into the student for the teacher's forwards.

    Only the trainable tensors are copied (the frozen 5B backbone is shared), the teacher is never an optimiser
    parameter and gets no gradient; `update()` (after the optimiser step) is the only thing that changes it.
    decay 0 = a stop-gradient snapshot of the current student (Frans et al.'s default bootstrap target); decay
    0.99 = an EMA just slow enough to smooth the targets (a toy study found slower EMAs lag the student and
    hurt the 4-step sampler: /work/shared/notes/facts.md).
    """

    def __init__(self, model: nn.Module, decay: float = 0.99):
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"{decay=} but expected 0 <= decay < 1")
        self.decay = decay
        self.params = {n: p for n, p in model.named_parameters() if p.requires_grad}
        if not self.params:
            raise ValueError("the model has no trainable parameters to build a teacher from")
        self.shadow = {n: p.detach().clone() for n, p in self.params.items()}

    @torch.no_grad()
    def update(self) -> None:
        """shadow <- decay * shadow + (1 - decay) * student (call after each optimiser step)."""
        for n, p in self.params.items():
            self.shadow[n].lerp_(p.detach().to(self.shadow[n].dtype), 1.0 - self.decay)

    @contextlib.contextmanager
    def swapped(self):
        """Within the block the model computes with the teacher's weights (no grad); the student's come back after."""
        saved = {n: p.data for n, p in self.params.items()}
        try:
            for n, p in self.params.items():
                p.data = self.shadow[n].to(p.dtype)
            with torch.no_grad():
                yield
        finally:
            for n, p in self.params.items():
                p.data = saved[n]

    def state_dict(self) -> dict:
        return {"decay": self.decay, "shadow": {n: t.clone() for n, t in self.shadow.items()}}

    def load_state_dict(self, state: dict) -> None:
        if set(state["shadow"]) != set(self.shadow):
            raise ValueError("teacher state does not match the model's trainable parameters")
        self.decay = float(state["decay"])
        for n, t in state["shadow"].items():
            self.shadow[n].copy_(t)


def sample_sigma(b: int, levels: int = 0, generator: torch.Generator | None = None) -> torch.Tensor:
    """(b,) noise levels: sigma ~ U(0, 1) when levels == 0, else the paper's discrete sigma = t / N_t with
    t ~ U{1..N_t} (N_t = levels, e.g. 1000 as Wan's num_train_timesteps)."""
    if levels < 0:
        raise ValueError(f"{levels=} but expected 0 (continuous) or N_t >= 1")
    if levels == 0:
        return torch.rand(b, generator=generator)
    return torch.randint(1, levels + 1, (b,), generator=generator).float() / levels


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
    sigma_levels: int = 0,
) -> torch.Tensor:
    """L_FM = || s(x_t, sigma, dt=0) - (eps - x0) ||^2 with x_t = (1 - sigma) x0 + sigma eps, sigma ~ U(0, 1)
    (or sigma = t / N_t with sigma_levels = N_t, the paper's discrete noise level; see sample_sigma).

    x0 (B, z, T_lat, h, w) clean normalised latents; condition, prompt_embeds, anchor as in wan_layers.velocity.
    """
    b = x0.shape[0]
    sigma = sample_sigma(b, sigma_levels, generator).to(x0.device)
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
    teacher: EmaTeacher | None = None,
) -> torch.Tensor:
    """L_SC = || s(x_t, sigma, dt) - (v1 + v2) / 2 ||^2: the frozen teacher takes two half steps of dt / 2.

    teacher: the EmaTeacher whose weights give v1, v2 (the paper); None = the student itself under no_grad.
    dt ~ {1, 1/2, ..., 2/max_steps}, sigma = j dt on the grid of dt (a discrete sigma = t / N_t with N_t = max_steps,
    as the paper); the finest half step (1/max_steps) is the plain flow (step size 0), which is what L_FM trains.
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
    with teacher.swapped() if teacher is not None else torch.no_grad():
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
    teacher: EmaTeacher | None = None,
    sigma_levels: int = 0,
    split: str = "iteration",
) -> tuple[torch.Tensor, str]:
    """L_video = b L_FM + (1 - b) L_SC; returns (loss, 'fm', 'sc' or 'mixed').

    split "iteration" (the paper): b ~ Bernoulli(rho) per iteration, the whole batch goes to one loss. split "batch"
    (Frans et al.): every batch gives round((1 - rho) B) samples (at least one, when rho < 1) to L_SC and the rest to
    L_FM, and the loss is the per-sample mean over the whole batch. rho = 1 is the paper's "+Mixed Training, FM only"
    ablation (no self-consistency, no teacher forwards)."""
    if split not in ("iteration", "batch"):
        raise ValueError(f"{split=} but expected 'iteration' or 'batch'")
    fm = {"generator": generator, "sigma_levels": sigma_levels}
    sc = {"generator": generator, "max_steps": max_steps, "teacher": teacher}
    if split == "batch" and rho < 1:
        b = x0.shape[0]
        n = min(b, max(1, round((1 - rho) * b)))  # the first n samples go to L_SC, the rest to L_FM

        def part(sl: slice) -> tuple:
            return x0[sl], condition[sl], prompt_embeds[sl], None if anchor is None else anchor[sl]

        x, c, e, a = part(slice(None, n))
        total = n * self_consistency_loss(transformer, x, c, e, anchor=a, **sc)
        if n < b:
            x, c, e, a = part(slice(n, None))
            total = total + (b - n) * flow_matching_loss(transformer, x, c, e, anchor=a, **fm)
        return total / b, "mixed"
    if torch.rand((), generator=generator).item() < rho:
        return flow_matching_loss(transformer, x0, condition, prompt_embeds, anchor=anchor, **fm), "fm"
    return self_consistency_loss(transformer, x0, condition, prompt_embeds, anchor=anchor, **sc), "sc"
