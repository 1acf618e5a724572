"""Configuration of a reconstruction training run and its presets (`tiny` for a CPU, `paper` for the paper's sizes)."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class YawAugment(enum.StrEnum):
    """Exact ERP yaw augmentation of a training batch (columns rolled, poses turned about the camera's vertical axis)."""

    NONE = "none"
    """Frames as rendered (the synthetic tracks' cameras start looking along the path)."""
    SHARED = "shared"
    """One random turn for all frames of a batch: relative rotations unchanged, the direction of travel in the first
    camera's frame uniform (the model must see it in the images, not assume 'forward')."""
    PER_FRAME = "per-frame"
    """An independent random turn per frame: relative rotations uniform in yaw too."""


class Geometry(enum.StrEnum):
    """Depth and poses the Gaussian head is given in stage 2."""

    PREDICTED = "predicted"
    """The frozen camera and depth heads' predictions (the paper)."""
    GT = "gt"
    """The ground truth (an ablation: the head alone, as the pipeline's decoder backend fed a poses artifact)."""


@dataclass(kw_only=True)
class ReconConfig:
    """One training run of PanoVGGT (stage 1: camera + depth heads; stage 2: the Gaussian head, the rest frozen)."""

    stage: int = 1
    """1 or 2 (set by --stage)."""
    seed: int = 0
    """Seeds the model initialisation and every batch (batch k uses the generator seeded by (seed, k))."""
    steps: int = 0
    """Optimiser steps (0 = the stage's default: 12000 in stage 1, 500 in stage 2, whose steps render and cost ~10x)."""
    lr: float = 1e-3
    """Peak AdamW learning rate (linear warm-up, then cosine decay to lr_min_ratio * lr)."""
    lr_min_ratio: float = 0.05
    """Final learning rate as a fraction of lr."""
    warmup_steps: int = 30
    """Linear warm-up steps."""
    weight_decay: float = 0.05
    """AdamW weight decay."""
    grad_clip: float = 1.0
    """Clip the global gradient norm to this (0 = off)."""
    image_height: int = 32
    """ERP height frames are resized to (width = 2 * height; the paper: 392); a multiple of patch_size."""
    min_frames: int = 2
    """Fewest frames of a batch (the paper: 2)."""
    max_frames: int = 8
    """Most frames of a batch (the paper: 32)."""
    yaw_augment: YawAugment = YawAugment.SHARED
    """Turn training cameras about their vertical axis by random whole numbers of pixel columns (exact for ERP: the
    image rolls, the pose rotates): none, shared (one turn per batch) or per-frame."""
    val_scenes: int = 4
    """The last val_scenes scenes of DATASET_DIR (by name) validate and never train."""
    val_every: int = 100
    """Validate every this many steps (and at the end)."""
    val_batches: int = 6
    """Fixed validation batches (the same every time)."""
    ckpt_every: int = 100
    """Checkpoint every this many steps (and at the end)."""
    keep_checkpoints: int = 2
    """Newest checkpoints kept."""
    log_every: int = 10
    """Write train metrics every this many steps."""
    # model (ignored when --init gives a model)
    patch_size: int = 8
    """Patch side in pixels (the paper's 14 divides 392 x 784)."""
    embed_dim: int = 64
    """Token width (VGGT-1B: 1024)."""
    depth: int = 4
    """Aggregator (frame, global) block pairs (VGGT-1B: 24)."""
    num_heads: int = 4
    """Attention heads (VGGT-1B: 16)."""
    num_register_tokens: int = 2
    """Register tokens per frame."""
    camera_trunk_depth: int = 2
    """Camera head transformer blocks."""
    camera_iterations: int = 2
    """Camera head refinement steps."""
    pose_correlation: int = 32
    """Channels of the camera head's panoramic correlation cues (0 = VGGT's head; PanoVGGTConfig.pose_correlation)."""
    dpt_features: int = 32
    """Depth head fusion channels."""
    pose_refine_iters: int = 20
    """Depth-consistency pose refinement steps the export runs at inference (PanoVGGTConfig.pose_refine_iters; 0 =
    the camera head's poses as VGGT). Written into the export's config.json, also for an --init model; never
    trained through."""
    # stage 1 losses
    camera_weight: float = 1.0
    """Weight of the camera loss."""
    rot_weight: float = 1.0
    """Weight of the rotation term inside the camera loss."""
    depth_weight: float = 1.0
    """Weight of the depth loss."""
    silog_lambda: float = 0.85
    """lambda of the scale-invariant log-depth loss (1 = fully scale invariant)."""
    conf_alpha: float = 0.05
    """Weight of the -log(confidence) regulariser of the depth loss."""
    # stage 2
    geometry: Geometry = Geometry.PREDICTED
    """Depth and poses given to the Gaussian head."""
    context_views: int = 3
    """Most context views per stage-2 batch (at least min_frames)."""
    target_views: int = 2
    """Held-out views per stage-2 batch (rendered, never input)."""
    render_context: int = 1
    """Context views also rendered into the loss per batch."""
    render_height: int = 32
    """ERP height of the renders the L2 loss compares."""
    gs_embed_dim: int = 64
    """Gaussian head: global attention width."""
    gs_layers: int = 1
    """Gaussian head: global attention layers."""
    gs_heads: int = 4
    """Gaussian head: attention heads."""
    gs_feature_dim: int = 16
    """Gaussian head: per-pixel feature channels."""
    gs_token_dim: int = 32
    """Gaussian head: voxel token width."""
    gs_knn_k: int = 8
    """Gaussian head: KNN neighbours."""
    gs_knn_layers: int = 1
    """Gaussian head: KNN attention layers."""
    gs_knn_heads: int = 4
    """Gaussian head: KNN attention heads (divide gs_token_dim)."""
    gs_mlp_hidden: int = 64
    """Gaussian head: hidden width of phi_gs."""
    gs_per_voxel: int = 2
    """Gaussian head: Gaussians per voxel (K)."""
    gs_sh_degree: int = 0
    """Gaussian head: SH degree of the colours."""
    voxel_size: float = 0.08
    """Gaussian head: voxel size in metres (the paper's epsilon)."""
    gs_max_scale: float = 2.0
    """Gaussian head: largest scale as a multiple of voxel_size."""
    # runtime
    device: str = "auto"
    """cpu, cuda, cuda:1 or auto (cuda when available)."""
    mixed_precision: str = "auto"
    """no, bf16 or auto (bf16 on CUDA)."""
    use_accelerate: bool = False
    """Run under `accelerate launch` (multi-GPU data parallel: each rank draws its own batches)."""
    num_threads: int = 0
    """torch CPU threads (0 = torch's default)."""
    grad_checkpointing: bool = False
    """Recompute the aggregator blocks in the backward pass (stage 1 at the paper's 32 frames needs it)."""

    def __post_init__(self):
        if self.steps == 0:
            self.steps = 12000 if self.stage == 1 else 500

    def check(self) -> None:
        if self.stage not in (1, 2):
            raise ValueError(f"stage={self.stage} but expected 1 or 2")
        if self.image_height % self.patch_size or self.render_height < 8:
            raise ValueError(f"image_height={self.image_height} must be a multiple of patch_size={self.patch_size} "
                             f"and render_height={self.render_height} >= 8")
        if not 2 <= self.min_frames <= self.max_frames:
            raise ValueError(f"min_frames={self.min_frames}, max_frames={self.max_frames}: need 2 <= min <= max")
        if self.stage == 2 and (self.context_views < 1 or self.target_views < 0 or self.render_context < 0):
            raise ValueError("stage 2 needs context_views >= 1, target_views >= 0, render_context >= 0")


PRESETS: dict[str, dict] = {
    "tiny": {},
    "paper": {
        "steps": 160_000, "lr": 2e-4, "warmup_steps": 8000, "image_height": 392, "min_frames": 2, "max_frames": 32,
        "val_every": 2000, "val_batches": 32, "ckpt_every": 2000, "log_every": 50, "val_scenes": 50,
        "patch_size": 14, "embed_dim": 1024, "depth": 24, "num_heads": 16, "num_register_tokens": 4,
        "camera_trunk_depth": 4, "camera_iterations": 4, "pose_correlation": 0, "dpt_features": 256,
        "pose_refine_iters": 0,
        "context_views": 8, "target_views": 4, "render_context": 4, "render_height": 392,
        "gs_embed_dim": 384, "gs_layers": 6, "gs_heads": 6, "gs_feature_dim": 64, "gs_token_dim": 128,
        "gs_knn_k": 16, "gs_knn_layers": 2, "gs_mlp_hidden": 256, "gs_per_voxel": 2, "gs_sh_degree": 1,
        "voxel_size": 0.02, "grad_checkpointing": True,
    },
}

SOURCES: dict[str, dict[str, str]] = {
    "paper": {
        "steps": "VGGT (the paper: 'following the hyperparameter settings of the original VGGT'): 160K iterations",
        "lr": "VGGT: AdamW, peak lr 2e-4, cosine decay",
        "warmup_steps": "VGGT: 8K warm-up iterations",
        "image_height": "paper, Implementation details: 392 x 784",
        "min_frames": "paper: 2 to 32 frames per batch",
        "max_frames": "paper: 2 to 32 frames per batch",
        "val_every": "ours: bookkeeping", "val_batches": "ours: bookkeeping", "ckpt_every": "ours: bookkeeping",
        "log_every": "ours: bookkeeping", "val_scenes": "ours: the scenes held out from training",
        "patch_size": "VGGT-1B: patch 14", "embed_dim": "VGGT-1B: 1024", "depth": "VGGT-1B: 24 block pairs",
        "num_heads": "VGGT-1B: 16", "num_register_tokens": "VGGT-1B: 4 register tokens",
        "camera_trunk_depth": "VGGT camera head: trunk depth 4", "camera_iterations": "VGGT camera head: 4 iterations",
        "pose_correlation": "VGGT's camera head (our correlation cues are off: not in the paper)",
        "dpt_features": "VGGT DPT head: 256 features",
        "dpt_layers": "VGGT DPT head: layers (4, 11, 17, 23) (dpt_layers(24))",
        "pose_refine_iters": "paper: feed-forward, no per-scene optimisation (the refinement is ours, off)",
        "context_views": "ours, not in the paper: 8 context views for stage 2",
        "target_views": "ours, not in the paper: 4 held-out views", "render_context": "ours, not in the paper",
        "render_height": "paper: the training resolution 392",
        "gs_embed_dim": "ours, not in the paper (no head sizes given)", "gs_layers": "ours, not in the paper",
        "gs_heads": "ours, not in the paper", "gs_feature_dim": "ours, not in the paper",
        "gs_token_dim": "ours, not in the paper", "gs_knn_k": "ours, not in the paper",
        "gs_knn_layers": "ours, not in the paper", "gs_mlp_hidden": "ours, not in the paper",
        "gs_per_voxel": "ours, not in the paper", "gs_sh_degree": "ours, not in the paper",
        "voxel_size": "ours, not in the paper (the paper's epsilon has no value)",
        "grad_checkpointing": "ours: needed for 32 frames at 392 x 784 on 80 GB",
        "weight_decay": "VGGT: AdamW weight decay 0.05",
    },
    "tiny": {"all": "ours: CPU-proof sizes and steps (stage 1: 12 000 steps, picked on validation scenes only)"},
}
"""Where each value of a preset comes from."""


def model_config(cfg: ReconConfig, with_head: bool):
    """PanoVGGTConfig of a fresh model of this run (the Gaussian head only for stage 2)."""
    from panoworld.models.panovggt_config import PanoVGGTConfig

    d = cfg.depth
    dpt = dpt_layers(d)
    w = cfg.dpt_features
    return PanoVGGTConfig(
        patch_size=cfg.patch_size, embed_dim=cfg.embed_dim, depth=d, num_heads=cfg.num_heads,
        num_register_tokens=cfg.num_register_tokens, coord_frequencies=8, camera_trunk_depth=cfg.camera_trunk_depth,
        camera_iterations=cfg.camera_iterations, pose_correlation=cfg.pose_correlation,
        pose_refine_iters=cfg.pose_refine_iters, dpt_layers=dpt, dpt_features=w,
        dpt_out_channels=(w, 2 * w, 4 * w, 4 * w),
        image_height=cfg.image_height, gaussian_head=head_config(cfg) if with_head else None,
    )


VGGT_DPT_LAYERS = (4, 11, 17, 23)
"""VGGT's DPT head reads these of its 24 aggregator block pairs (vggt/heads/dpt_head.py, intermediate_layer_idx)."""


def dpt_layers(depth: int) -> tuple[int, ...]:
    """VGGT's (4, 11, 17, 23) scaled to `depth` block pairs: floor(i * depth / 24) (4 -> (0, 1, 2, 3))."""
    return tuple(i * depth // 24 for i in VGGT_DPT_LAYERS)


def head_config(cfg: ReconConfig):
    from panoworld.models.gs_decoder import GaussianHeadConfig

    return GaussianHeadConfig(
        embed_dim=cfg.gs_embed_dim, num_heads=cfg.gs_heads, global_layers=cfg.gs_layers, feature_dim=cfg.gs_feature_dim,
        voxel_size=cfg.voxel_size, knn_k=cfg.gs_knn_k, knn_layers=cfg.gs_knn_layers, knn_heads=cfg.gs_knn_heads,
        token_dim=cfg.gs_token_dim, pe_freqs=6, pe_scale=16.0, mlp_hidden=cfg.gs_mlp_hidden,
        gaussians_per_voxel=cfg.gs_per_voxel, sh_degree=cfg.gs_sh_degree, max_scale=cfg.gs_max_scale,
    )
