"""A multimodal disocclusion toy in latent space that the paper's objective and samplers train and sample."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch

from panoworld.models import wan_layers as wl
from panoworld.models import wan_training as wt


@dataclass(kw_only=True)
class ToyConfig:
    z: int = 4
    """Latent channels of the toy (no VAE: the toy lives in latent space)."""
    height: int = 8
    """Latent rows (width = 2 x height, ERP)."""
    hole: int = 4
    """Side of the square disocclusion in frame 1 (latent pixels)."""
    modes: int = 4
    """Plausible fills per hole: the target fills it with one of them, uniformly (the multimodal part)."""
    jitter: float = 0.05
    """Per-pixel noise std on a fill (so a mode is a small cloud, not a point)."""
    max_shift: int = 2
    """Camera yaw between frame 0 and frame 1: a roll by U{-max_shift..max_shift} latent columns."""
    layers: int = 2
    """Transformer blocks of the tiny Wan base."""
    heads: int = 4
    """Attention heads (head dim 16)."""
    base_steps: int = 1500
    """Flow-matching steps pre-training the base (frame 0 anchored, no condition), then frozen."""
    steps: int = 1500
    """Steps of the paper's stage (LoRA + widened patch embedding + step-size embedding), same for both models."""
    batch: int = 32
    """Samples per step."""
    lr: float = 2e-3
    """AdamW learning rate (base and LoRA stage)."""
    lora_rank: int = 8
    """LoRA rank (alpha = rank)."""
    teacher_decay: float = 0.99
    """EMA decay of the self-consistency teacher (the trainer's default)."""
    shortcut_levels: int = 8
    """Finest shortcut step 1/shortcut_levels (the trainer: 128). The toy samples at <= 4 shortcut steps, so 8 levels
    (dt in {1, 1/2, 1/4}, the teacher's half of 1/4 is the plain flow) keep the bootstrap chain 3 links long."""
    sc_split: str = "iteration"
    """How rho shares the stage between the losses: "iteration" (the paper: each step goes to one loss) or "batch"
    (Frans et al.: every batch gives a 1 - rho share of its samples to the self-consistency loss)."""
    flow_shift: float = 1.0
    """Timestep shift of the flow sampler (1 = uniform sigmas; Wan's 5 is for high-resolution latents)."""


FILL_SEED = 4242  # the fills are a property of the toy world, shared by every split


def fills(cfg: ToyConfig) -> torch.Tensor:
    """(modes, z, hole, hole): the plausible fills, well separated (+-0.8 per channel, a stripe of its own phase)."""
    g = torch.Generator().manual_seed(FILL_SEED)
    sign = torch.randint(0, 2, (cfg.modes, cfg.z, 1, 1), generator=g).float() * 2 - 1
    ramp = torch.arange(cfg.hole).float()
    stripes = torch.stack([torch.cos(math.pi * (ramp[None, :] + ramp[:, None] + k)) for k in range(cfg.modes)])
    return 0.8 * sign + 0.3 * stripes[:, None]


def _background(cfg: ToyConfig, g: torch.Generator) -> torch.Tensor:
    """(z, H, W) smooth ERP-periodic field in about [-0.6, 0.6]: a scene's walls."""
    h, w = cfg.height, 2 * cfg.height
    y = torch.arange(h).float()[:, None] / h
    x = torch.arange(w).float()[None, :] / w
    out = torch.zeros(cfg.z, h, w)
    for c in range(cfg.z):
        for _ in range(3):
            fx, fy = int(torch.randint(1, 3, (1,), generator=g)), float(torch.rand(1, generator=g)) * 2
            ph = torch.rand(2, generator=g) * 2 * math.pi
            out[c] += 0.2 * torch.cos(2 * math.pi * fx * x + ph[0]) * torch.cos(math.pi * fy * y + ph[1])
    return out


def scene_seeds(split: str, n: int, seed: int = 0) -> list[int]:
    """Scene seeds of a split: train, val and test draw from disjoint ranges, so no scene is in two splits."""
    base = {"train": 0, "val": 1_000_000, "test": 2_000_000}[split]
    return [base + 10_000 * seed + i for i in range(n)]


class ToyScenes:
    """Scenes (backgrounds) from seeds; `batch(idx, g)` draws one clip per index: shift, hole and fill at random."""

    def __init__(self, cfg: ToyConfig, seeds: list[int]):
        self.cfg, self.seeds = cfg, seeds
        self.bg = torch.stack([_background(cfg, torch.Generator().manual_seed(s)) for s in seeds])
        self.fills = fills(cfg)

    def batch(self, idx: torch.Tensor, g: torch.Generator) -> dict[str, torch.Tensor]:
        """x0 (B, z, 2, H, W) target, cond (B, z + 1, 2, H, W) = masked target + valid mask, anchor, hole (B, 2),
        mode (B,)."""
        cfg, b = self.cfg, len(idx)
        h, w, k = cfg.height, 2 * cfg.height, cfg.hole
        bg = self.bg[idx]
        shift = torch.randint(-cfg.max_shift, cfg.max_shift + 1, (b,), generator=g)
        f1 = torch.stack([torch.roll(bg[i], int(shift[i]), dims=-1) for i in range(b)])
        r = torch.randint(0, h - k + 1, (b,), generator=g)
        c = torch.randint(0, w - k + 1, (b,), generator=g)
        mode = torch.randint(0, cfg.modes, (b,), generator=g)
        fill = self.fills[mode] + cfg.jitter * torch.randn(b, cfg.z, k, k, generator=g)
        valid = torch.ones(b, 1, h, w)
        for i in range(b):
            f1[i, :, r[i]:r[i] + k, c[i]:c[i] + k] = fill[i]
            valid[i, :, r[i]:r[i] + k, c[i]:c[i] + k] = 0
        x0 = torch.stack([bg, f1], dim=2)
        mask = torch.stack([torch.ones_like(valid), valid], dim=2)
        cond = torch.cat([x0 * mask, mask], dim=1)
        return {"x0": x0, "cond": cond, "anchor": x0[:, :, :1], "hole": torch.stack([r, c], 1), "mode": mode}


def hole_content(x: torch.Tensor, hole: torch.Tensor, k: int) -> torch.Tensor:
    """(B, z * k * k): frame 1's content inside each sample's hole."""
    return torch.stack([x[i, :, 1, r:r + k, c:c + k].flatten() for i, (r, c) in enumerate(hole.tolist())])


def sliced_wasserstein(a: torch.Tensor, b: torch.Tensor, projections: int = 512, seed: int = 0) -> float:
    """Sliced 1-Wasserstein distance between two equal-size point sets (N, D): the mean over random unit directions
    of the 1-D Wasserstein distance of the projections (sorted-sample matching)."""
    if a.shape != b.shape:
        raise ValueError(f"{a.shape=} {b.shape=}: expected equal-size sets")
    d = torch.randn(a.shape[1], projections, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    d = d / d.norm(dim=0, keepdim=True)
    pa, _ = torch.sort(a.double() @ d, dim=0)
    pb, _ = torch.sort(b.double() @ d, dim=0)
    return float((pa - pb).abs().mean())


def tiny_base(cfg: ToyConfig, seed: int):
    from diffusers import WanTransformer3DModel

    torch.manual_seed(seed)
    return WanTransformer3DModel(
        patch_size=(1, 2, 2), num_attention_heads=cfg.heads, attention_head_dim=16, in_channels=cfg.z,
        out_channels=cfg.z, text_dim=16, freq_dim=64, ffn_dim=4 * 16 * cfg.heads, num_layers=cfg.layers,
        rope_max_seq_len=64,
    )


def prompt(seed: int = 12345) -> torch.Tensor:
    return torch.randn(1, 4, 16, generator=torch.Generator().manual_seed(seed))


def _adamw(params, lr: float, steps: int):
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=0.0)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / 50))
    return opt, sched


def train_base(cfg: ToyConfig, data: ToyScenes, seed: int):
    """The frozen base: the tiny Wan transformer pre-trained with flow matching, frame 0 anchored, no condition."""
    tr = tiny_base(cfg, seed)
    opt, sched = _adamw(tr.parameters(), cfg.lr, cfg.base_steps)
    g = torch.Generator().manual_seed(seed + 1)
    emb = prompt()
    for _ in range(cfg.base_steps):
        bt = data.batch(torch.randint(0, len(data.seeds), (cfg.batch,), generator=g), g)
        x0 = bt["x0"]
        sigma = torch.rand(cfg.batch, generator=g)
        noise = torch.randn(x0.shape, generator=g)
        s = sigma.view(-1, 1, 1, 1, 1)
        v = wl.velocity(tr, (1 - s) * x0 + s * noise, sigma, None, None, emb.expand(cfg.batch, -1, -1), bt["anchor"])
        loss = ((v - (noise - x0))[:, :, 1:] ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(tr.parameters(), 1.0)
        opt.step()
        sched.step()
    return tr.eval().requires_grad_(False)


def passes_per_sample(rho: float) -> float:
    """Network passes a training sample costs, in forward equivalents (a backward ~ 2 forwards): FM 3; self-consistency
    5 (the teacher's two forwards without gradient, then the student's forward and backward)."""
    return 3.0 + 2.0 * (1.0 - rho)


def equal_compute_steps(steps: int, rho: float) -> int:
    """FM-only steps costing what `steps` steps at this rho cost (same batch): 700 for 600 at rho 0.75."""
    return round(steps * passes_per_sample(rho) / passes_per_sample(1.0))


def train_stage(cfg: ToyConfig, base, data: ToyScenes, *, rho: float, seed: int, steps: int | None = None):
    """The paper's stage on a copy of `base`: rho = 1 FM only, rho = 0.75 FM + shortcut self-consistency;
    `steps` (default cfg.steps) optimiser steps."""
    tr = copy.deepcopy(base)
    torch.manual_seed(seed + 3)
    params = wt.prepare_for_training(tr, cfg.z + 1, rank=cfg.lora_rank, alpha=float(cfg.lora_rank))
    teacher = wt.EmaTeacher(tr, cfg.teacher_decay) if rho < 1 else None
    opt, sched = _adamw(params, cfg.lr, cfg.steps)
    g = torch.Generator().manual_seed(seed + 3)
    emb = prompt()
    tr.train()
    for _ in range(cfg.steps if steps is None else steps):
        bt = data.batch(torch.randint(0, len(data.seeds), (cfg.batch,), generator=g), g)
        loss, _ = wt.shortcut_objective(tr, bt["x0"], bt["cond"], emb.expand(cfg.batch, -1, -1), rho=rho,
                                        anchor=bt["anchor"], generator=g, max_steps=cfg.shortcut_levels,
                                        teacher=teacher, split=cfg.sc_split)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        sched.step()
        if teacher is not None:
            teacher.update()
    return tr.eval()


def uniform_flow_schedule(steps: int, shift: float = 1.0) -> tuple[list[float], list[float]]:
    """N equal steps 1 -> 0 (time-shifted like Wan's s' = shift s / (1 + (shift - 1) s)), step size 0 (plain flow).
    Not diffusers' schedule: its linspace ends at sigma 1/1000, so its 2 steps are 1 -> 0.001 -> 0, one step."""
    grid = [1.0 - i / steps for i in range(steps + 1)]
    return [shift * s / (1 + (shift - 1) * s) for s in grid], [0.0] * steps


@torch.no_grad()
def sample(cfg: ToyConfig, tr, bt: dict, *, sampler: str, steps: int, seed: int) -> torch.Tensor:
    """Generated x (B, z, 2, H, W) for a batch's conditions with the video stage's samplers (frame 0 = anchor)."""
    from panoworld.models.wan_shortcut import euler_sample, shortcut_schedule

    sigmas, dts = shortcut_schedule(steps) if sampler == "shortcut" else uniform_flow_schedule(steps, cfg.flow_shift)
    b = bt["x0"].shape[0]
    emb = prompt().expand(b, -1, -1)

    def fn(x, sigma, dt, _positive):
        return wl.velocity(tr, x, torch.full((b,), sigma), torch.full((b,), dt), bt["cond"], emb, bt["anchor"])

    noise = torch.randn(bt["x0"].shape, generator=torch.Generator().manual_seed(seed))
    x, _ = euler_sample(fn, noise, sigmas, dts, progress=False)
    x[:, :, :1] = bt["anchor"]
    return x


def psnr(x: torch.Tensor, ref: torch.Tensor, peak: float = 2.0) -> float:
    """PSNR (dB) of frame 1 against the target, peak-to-peak range `peak` (toy latents live in about [-1, 1])."""
    mse = float(((x[:, :, 1] - ref[:, :, 1]) ** 2).mean())
    return 10 * math.log10(peak**2 / max(mse, 1e-12))


def evaluate(cfg: ToyConfig, tr, data: ToyScenes, *, sampler: str, steps: int, clips: int, seed: int) -> dict:
    """Sliced Wasserstein distance of the generated hole contents to a fresh draw of the true fills on the same
    conditions (lower is better), and PSNR of the whole generated frame 1 against the drawn target."""
    g = torch.Generator().manual_seed(seed + 777)
    idx = torch.arange(clips) % len(data.seeds)
    bt = data.batch(idx, g)
    x = sample(cfg, tr, bt, sampler=sampler, steps=steps, seed=seed + 99)
    ref = data.fills[torch.randint(0, cfg.modes, (clips,), generator=g)]
    ref = (ref + cfg.jitter * torch.randn(ref.shape, generator=g)).flatten(1)
    gen = hole_content(x, bt["hole"], cfg.hole)
    return {"swd": sliced_wasserstein(gen, ref), "psnr": psnr(x, bt["x0"]),
            "mode_error": float(np.mean(_nearest_mode_distance(gen, data.fills.flatten(1))))}


def swd_floor(cfg: ToyConfig, clips: int, seed: int = 0) -> float:
    """SWD between two independent draws of `clips` true fills: what a perfect sampler scores at this sample size."""
    g = torch.Generator().manual_seed(seed + 555)
    f = fills(cfg)

    def draw() -> torch.Tensor:
        ref = f[torch.randint(0, cfg.modes, (clips,), generator=g)]
        return (ref + cfg.jitter * torch.randn(ref.shape, generator=g)).flatten(1)

    return sliced_wasserstein(draw(), draw())


def _nearest_mode_distance(gen: torch.Tensor, modes: torch.Tensor) -> np.ndarray:
    """RMS distance of each generated hole to its nearest plausible fill (0 = on a mode; the mean of modes is far)."""
    d = torch.cdist(gen.double(), modes.double()) / math.sqrt(gen.shape[1])
    return d.min(1).values.numpy()
