"""Configuration of `train video`: one dataclass, the `tiny` (CPU proof) and `paper` presets."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class BaseModel(enum.StrEnum):
    WAN = "wan"
    """A local Wan2.2-TI2V-5B-Diffusers directory (--weights): the paper's frozen backbone and VAE."""
    TINY = "tiny"
    """A tiny Wan-architecture VAE + transformer built here, pre-trained on the clips (stand-in for Wan on a CPU)."""


class ScSplit(enum.StrEnum):
    ITERATION = "iteration"
    """The paper: b ~ Bernoulli(rho) per iteration, the whole batch goes to one loss."""
    BATCH = "batch"
    """Frans et al.'s code: a 1 - rho share of every batch goes to the self-consistency loss, the rest to FM."""


@dataclass(kw_only=True)
class VideoTrainConfig:
    base: BaseModel = BaseModel.WAN
    """wan: load the frozen backbone + VAE from --weights; tiny: build and pre-train a tiny Wan-architecture base."""
    frames: int = 81
    """Frames per training clip (4k + 1; longer clips are cut, shorter ones skipped)."""
    height: int = 704
    """Training ERP height (width = 2 x height; a multiple of the VAE's spatial factor x patch size)."""
    val_fraction: float = 0.1
    """Fraction of the scenes held out for validation (split by scene, deterministic in split_seed)."""
    split_seed: int = 0
    """Seed of the scene split."""
    steps: int = 4000
    """Optimiser steps of the paper's stage: LoRA + condition projection + step-size embedding."""
    batch_size: int = 1
    """Clips per optimiser step and rank."""
    lr: float = 1e-4
    """AdamW learning rate of the LoRA stage."""
    weight_decay: float = 0.01
    """AdamW weight decay."""
    warmup_steps: int = 100
    """Linear learning-rate warm-up (then constant)."""
    grad_clip: float = 1.0
    """Gradient-norm clip (0 = off)."""
    rho: float = 0.75
    """Probability of routing a step to the flow-matching loss (else self-consistency); 1 = the FM-only ablation."""
    sc_split: ScSplit = ScSplit.ITERATION
    """How rho shares training between the losses: iteration (the paper) or batch (Frans et al.'s code)."""
    shortcut_levels: int = 128
    """Finest shortcut step 1/shortcut_levels (dt in {1, 1/2, ..., 2/shortcut_levels})."""
    sigma_levels: int = 0
    """0: sigma ~ U(0, 1) in L_FM; N_t > 0: the paper's discrete sigma = t / N_t (paper preset: 1000)."""
    teacher_decay: float = 0.99
    """EMA decay of the frozen self-consistency teacher (0 = a stop-gradient copy of the current student)."""
    lora_rank: int = 48
    """LoRA rank (the paper: 48)."""
    lora_alpha: float = 48.0
    """LoRA alpha (the paper: 48)."""
    prompt: str = "a panoramic video walking through an indoor scene"
    """Text prompt of every clip (encoded once with the local UMT5; tiny: a fixed random embedding)."""
    anchor_first_frame: bool = True
    """Keep the first latent frame clean (the source panorama, Wan2.2 TI2V rule), as the video stage does."""
    cache_latents: bool = True
    """Encode targets and conditions with the frozen VAE once (RUN_DIR/latents) instead of every step."""
    workers: int = 0
    """DataLoader worker processes that decode the PNG clips (for the latent cache)."""
    device: str = "auto"
    """auto = cuda when available."""
    threads: int = 0
    """torch CPU threads (0 = torch's default; 1 on a shared 2-core machine: oversubscribed threads run far slower)."""
    mixed_precision: str = "auto"
    """auto = bf16 on CUDA, no on CPU; or no / bf16."""
    grad_checkpointing: bool = True
    """Gradient checkpointing of the transformer blocks (GPU memory; ignored on CPU)."""
    use_accelerate: bool = False
    """Run under `accelerate launch` (multi-GPU; DeepSpeed ZeRO-1 via docs/accelerate_zero1.yaml)."""
    checkpoint_every: int = 500
    """Save a checkpoint every N steps (and at the end of every phase)."""
    keep_checkpoints: int = 2
    """Checkpoints kept."""
    log_every: int = 10
    """Training loss rows in metrics.jsonl every N steps."""
    val_every: int = 500
    """Held-out flow-matching loss every N steps (fixed noise and sigmas, so the curve is comparable)."""
    val_clips: int = 16
    """Held-out clips used by validation."""
    val_sample_every: int = 0
    """Every N steps (0 = only at the end) also sample the held-out clips (4-step shortcut and 4-step flow) and
    score PSNR against the targets."""
    val_sample_clips: int = 4
    """Held-out clips sampled by the sampling validation."""
    flow_shift: float = 5.0
    """Timestep shift of the flow sampler in validation (the video stage's default)."""
    seed: int = 0
    """Seed of initialisation, data order and loss noise."""
    # ---- tiny base (base = tiny): pre-training that stands in for the pretrained Wan2.2 VAE and backbone
    vae_steps: int = 0
    """tiny: autoencoder steps training the tiny VAE on target clips (then frozen)."""
    vae_lr: float = 2e-3
    """tiny: VAE learning rate."""
    base_steps: int = 0
    """tiny: flow-matching steps pre-training the tiny transformer (then frozen)."""
    base_lr: float = 1e-3
    """tiny: base pre-training learning rate."""
    tiny_z: int = 12
    """tiny: VAE latent channels."""
    tiny_layers: int = 4
    """tiny: transformer blocks."""
    tiny_heads: int = 4
    """tiny: attention heads (head dim 16)."""
    tiny_text_dim: int = 32
    """tiny: prompt embedding width."""


PRESETS: dict[str, dict] = {
    "paper": {
        "base": "wan", "frames": 81, "height": 704, "steps": 4000, "batch_size": 1, "lr": 1e-4, "rho": 0.75,
        "sigma_levels": 1000, "lora_rank": 48, "lora_alpha": 48.0, "mixed_precision": "bf16", "grad_checkpointing": True,
        "checkpoint_every": 500, "val_every": 500, "val_sample_every": 2000,
    },
    "tiny": {
        "base": "tiny", "frames": 13, "height": 64, "val_fraction": 0.2, "steps": 500, "batch_size": 4, "lr": 2e-3,
        "warmup_steps": 20, "lora_rank": 8, "lora_alpha": 8.0, "vae_steps": 200, "base_steps": 400,
        "checkpoint_every": 100, "log_every": 10, "val_every": 50, "val_clips": 16, "val_sample_clips": 8,
        "mixed_precision": "no", "grad_checkpointing": False, "device": "cpu", "threads": 1,
    },
}

MATRIX3D_LORA = (
    "not applied: the paper initialises the LoRA from Matrix-3D, but Matrix-3D's released video LoRA "
    "(pano_video_gen_720p.bin / _480p.ckpt, loaded by code/panoramic_image_to_video.py) adapts Wan2.1-I2V-14B "
    "(40 blocks, width 5120, CLIP image cross-attention), and our base is Wan2.2-TI2V-5B (30 blocks, width 3072): "
    "no adapter tensor has a matching shape, so the LoRA starts at zero (B = 0) as PEFT initialises it"
)
"""Why the paper's 'LoRA initialized from Matrix-3D' is not reproduced (github.com/SkyworkAI/Matrix-3D, README)."""

SOURCES: dict[str, dict[str, str]] = {
    "paper": {
        "base": "paper, Implementation details: Wan2.2-TI2V-5B, backbone and 3D VAE frozen",
        "frames": "paper, Implementation details: 81 frames",
        "height": "paper: 720 x 1440; ours: 704 = 720 rounded down to the model's multiple of 32 (VAE 16 x patch 2)",
        "steps": "ours, not in the paper: a budget of 4000 LoRA steps (no data behind it)",
        "batch_size": "ours, not in the paper: one 81 x 704 x 1408 clip per GPU (memory)",
        "lr": "ours, not in the paper: 1e-4, a usual LoRA rate (DiffSynth-Studio's Wan trainer, which Matrix-3D "
              "ships, defaults to 1e-5)",
        "weight_decay": "torch AdamW's default 0.01 (not in the paper; DiffSynth-Studio's trainer keeps it too)",
        "warmup_steps": "ours, not in the paper: 100 linear warm-up steps",
        "grad_clip": "ours, not in the paper: clip at 1.0",
        "rho": "paper, Shortcut-model training: rho = 0.75",
        "sc_split": "paper, Training objective: b ~ Bernoulli(rho) per iteration (the toy uses Frans et al.'s per-batch "
                    "split: docs/training.md)",
        "sigma_levels": "paper: sigma = t / N_t; N_t = 1000 = Wan's num_train_timesteps",
        "shortcut_levels": "Frans et al., shortcut models: finest step 1/128",
        "teacher_decay": "ours: the paper says 'a frozen teacher'; Frans et al. allow an EMA; 0.99 from a toy study "
                         "(docs/training.md, Teacher)",
        "lora_rank": "paper, Implementation details: rank 48",
        "lora_alpha": "paper, Implementation details: alpha 48",
        "lora_init": MATRIX3D_LORA,
        "mixed_precision": "paper: bf16",
        "grad_checkpointing": "paper: gradient checkpointing",
        "use_accelerate": "paper: DeepSpeed ZeRO-1 (accelerate_zero1.yaml; set under `accelerate launch`)",
        "anchor_first_frame": "Wan2.2 TI2V: the first latent frame is the given image, kept clean",
        "checkpoint_every": "ours: bookkeeping, no effect on the weights",
        "val_every": "ours: bookkeeping, no effect on the weights",
        "val_sample_every": "ours: bookkeeping, no effect on the weights",
    },
    "tiny": {key: "ours: CPU-proof sizes, every value chosen to run in minutes on 2 cores" for key in PRESETS["tiny"]},
}
"""Where each value of a preset (and each default the paper preset relies on) comes from."""
