"""PanoVGGT: a VGGT-style network on ERP frames with ERP-aligned coordinate encoding: camera, depth and Gaussian heads."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from panoworld.core.shapes import check_shape
from panoworld.models.gs_decoder import GaussianHead
from panoworld.models.panovggt_config import PanoVGGTConfig
from panoworld.models.panovggt_layers import Block, CameraHead, DepthHead, erp_coordinate_features
from panoworld.models.pose_refine import refine_sequence
from panoworld.models.weights import (
    MissingWeightsError,
    load_config_and_weights,
    save_config_and_weights,
)

if TYPE_CHECKING:
    from panoworld.io.gaussian_set import ContextFrames, FusionResult

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _run(block: nn.Module, x: torch.Tensor, checkpointed: bool) -> torch.Tensor:
    if checkpointed:
        from torch.utils.checkpoint import checkpoint

        return checkpoint(block, x, use_reentrant=False)
    return block(x)


class PanoVGGT(nn.Module):
    """Feed-forward panoramic reconstructor (paper Sec. "Feed-Forward Pose and Depth Estimation").

    VGGT with the perspective machinery removed: no intrinsics (ERP fixes the projection) and no 2D RoPE; patch
    tokens get the ERP-aligned coordinate encoding instead. Alternating frame-wise and global attention over
    [camera token, register tokens, patch tokens] of every frame; a camera head and a DPT-lite depth head.
    """

    def __init__(self, cfg: PanoVGGTConfig):
        super().__init__()
        self.cfg = cfg
        d, p = cfg.embed_dim, cfg.patch_size
        self.patch_embed = nn.Conv2d(3, d, p, stride=p)
        self.coord_embed = nn.Linear(4 * cfg.coord_frequencies, d)
        # Index 0: the first (reference) frame; index 1: all other frames.
        self.camera_token = nn.Parameter(torch.randn(2, 1, d) * 0.02)
        self.register_tokens = nn.Parameter(torch.randn(2, cfg.num_register_tokens, d) * 0.02)
        self.frame_blocks = nn.ModuleList(
            [Block(d, cfg.num_heads, cfg.mlp_ratio, cfg.layer_scale_init) for _ in range(cfg.depth)]
        )
        self.global_blocks = nn.ModuleList(
            [Block(d, cfg.num_heads, cfg.mlp_ratio, cfg.layer_scale_init) for _ in range(cfg.depth)]
        )
        self.camera_head = CameraHead(cfg)
        self.depth_head = DepthHead(cfg)
        gh = cfg.gaussian_head
        self.gaussian_head = GaussianHead(gh, p, 2 * d) if gh is not None else None
        self.gradient_checkpointing = False
        """Recompute each aggregator block in the backward pass instead of storing its activations (training)."""
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    @property
    def num_special_tokens(self) -> int:
        return 1 + self.cfg.num_register_tokens

    @property
    def gaussian_layer(self) -> int | None:
        """Aggregator block pair whose patch tokens the Gaussian head shares (None without the head)."""
        gh = self.cfg.gaussian_head
        return None if gh is None else gh.backbone_layer % self.cfg.depth

    def heads(self) -> dict[str, list[nn.Parameter]]:
        """Trainable parameter groups: backbone (aggregator), camera, depth, gaussian (empty without the head)."""
        groups = {"backbone": [], "camera": [], "depth": [], "gaussian": []}
        for name, prm in self.named_parameters():
            key = name.split(".")[0]
            groups[{"camera_head": "camera", "depth_head": "depth", "gaussian_head": "gaussian"}.get(key, "backbone")].append(prm)
        return groups

    def forward(self, images: torch.Tensor, *, with_tokens: bool = False) -> dict[str, torch.Tensor]:
        """images (B, S, 3, H, W) RGB in [0, 1], ERP 2:1 with H, W multiples of patch_size ->

        world_from_cam (B, S, 4, 4) float64 (frame 0 = identity), pose_enc (B, S, 7), depth (B, S, H, W) metres,
        depth_conf (B, S, H, W) >= 1; with_tokens adds "tokens" (B, S, P, 2D): the patch tokens the Gaussian head
        shares.
        """
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"{tuple(images.shape)=} but expected (B, S, 3, H, W)")
        b, s, _, h, w = images.shape
        p = self.cfg.patch_size
        if w != 2 * h or h % p:
            raise ValueError(f"frames are {w}x{h} (WxH) but PanoVGGT needs W = 2H with H a multiple of {p}")
        hp, wp = h // p, w // p
        x = (images.reshape(b * s, 3, h, w) - self.mean) / self.std
        x = self.patch_embed(x).flatten(2).transpose(1, 2)  # (B*S, P, D)
        coords = torch.from_numpy(erp_coordinate_features(hp, wp, self.cfg.coord_frequencies)).to(x)
        x = x + self.coord_embed(coords.reshape(hp * wp, -1))[None]
        first = torch.cat([self.camera_token[:1], self.register_tokens[:1]], dim=1)  # (1, 1+R, D)
        rest = torch.cat([self.camera_token[1:], self.register_tokens[1:]], dim=1)
        special = torch.cat([first, rest.expand(s - 1, -1, -1)], dim=0) if s > 1 else first
        x = torch.cat([special.repeat(b, 1, 1), x], dim=1)  # (B*S, T, D)
        t, d = x.shape[1], x.shape[2]
        keep = set(self.cfg.dpt_layers) | {self.cfg.depth - 1}
        if self.gaussian_layer is not None:
            keep.add(self.gaussian_layer)
        outputs: dict[int, torch.Tensor] = {}
        ckpt = self.gradient_checkpointing and self.training and torch.is_grad_enabled()
        for i in range(self.cfg.depth):
            x = _run(self.frame_blocks[i], x, ckpt)
            x_frame = x
            x = _run(self.global_blocks[i], x.reshape(b, s * t, d), ckpt).reshape(b * s, t, d)
            if i in keep:
                outputs[i] = torch.cat([x_frame, x], dim=-1)
        last = outputs[self.cfg.depth - 1]
        ns = self.num_special_tokens
        depth, conf = self.depth_head([outputs[i][:, ns:] for i in self.cfg.dpt_layers], (hp, wp), (h, w))
        world_from_cam, pose_enc = self.camera_head(last[:, 0].reshape(b, s, 2 * d),
                                                    last[:, ns:].reshape(b, s, hp * wp, 2 * d), (hp, wp),
                                                    depth.reshape(b, s, h, w))
        out = {
            "world_from_cam": world_from_cam,
            "pose_enc": pose_enc,
            "depth": depth.reshape(b, s, h, w),
            "depth_conf": conf.reshape(b, s, h, w),
        }
        if with_tokens:
            if self.gaussian_head is None:
                raise ValueError("with_tokens=True needs a model with a Gaussian head (config gaussian_head)")
            out["tokens"] = outputs[self.gaussian_layer][:, ns:].reshape(b, s, hp * wp, 2 * d)
        return out

    def require_gaussian_head(self, flag: str = "--weights") -> GaussianHead:
        if self.gaussian_head is None:
            raise MissingWeightsError(
                f"PanoVGGT: these weights have no Gaussian head (config.json gaussian_head is null); pass {flag} the "
                "export of a stage-2 run (python runner.py train recon --stage 2)"
            )
        return self.gaussian_head

    def gaussians(self, images: torch.Tensor, depth: torch.Tensor | None = None,
                  world_from_cam: torch.Tensor | None = None) -> dict:
        """One scene's context views images (S, 3, H, W) in [0, 1] -> the Gaussian head's output (see GaussianHead).

        Geometry: depth (S, H, W) metres and world_from_cam (S, 4, 4) when given (e.g. a poses artifact's), else the
        camera and depth heads' predictions. The backbone, camera and depth heads run without gradients (the paper's
        stage 2 trains the Gaussian head alone).
        """
        head = self.require_gaussian_head()
        with torch.no_grad():
            out = self(images[None], with_tokens=True)
        depth = out["depth"][0] if depth is None else depth
        world_from_cam = out["world_from_cam"][0] if world_from_cam is None else world_from_cam
        return head(images, depth, world_from_cam, out["tokens"][0])

    @torch.no_grad()
    def decode(self, frames: ContextFrames) -> FusionResult:
        """Gaussians from a gaussians stage's ContextFrames (their depth and poses), at the model's input size."""
        import cv2

        from panoworld.geometry.voxels import bbox_extent
        from panoworld.io.gaussian_set import FusionResult

        head = self.require_gaussian_head()
        h = self.cfg.image_height
        rgb, depth = frames.rgb, np.nan_to_num(np.asarray(frames.depth, np.float32), nan=0.0, posinf=0.0)
        if rgb.shape[1] != h:
            rgb = np.stack([cv2.resize(f, (2 * h, h), interpolation=cv2.INTER_AREA) for f in rgb])
            depth = np.stack([cv2.resize(d, (2 * h, h), interpolation=cv2.INTER_NEAREST) for d in depth])
        dev = next(self.parameters()).device
        x = torch.from_numpy(np.ascontiguousarray(rgb)).to(dev).permute(0, 3, 1, 2).float().div(255.0)
        out = self.eval().gaussians(x, torch.from_numpy(depth).to(dev),
                                    torch.from_numpy(np.asarray(frames.world_from_cam, np.float64)).to(dev))
        g = out["gaussians"].numpy()
        c = head.cfg
        n_vox = len(g) // c.gaussians_per_voxel
        return FusionResult(g, int((depth > 0).sum()), n_vox, 0, bbox_extent(g.means), c.voxel_size, backend="decoder")

    @torch.inference_mode()
    def predict(self, frames: np.ndarray) -> dict[str, np.ndarray]:
        """frames (S, H, W, 3) uint8 at the model's input size -> world_from_cam (S, 4, 4), depth (S, H, W), conf."""
        check_shape("frames", frames, "S H W 3", dtype=np.uint8)
        dev = next(self.parameters()).device
        x = torch.from_numpy(frames).to(dev).permute(0, 3, 1, 2).float().div(255.0)[None]
        out = self.eval()(x)
        world_from_cam = out["world_from_cam"][0]
        if self.cfg.pose_refine_iters > 0:
            world_from_cam = refine_sequence(world_from_cam, out["depth"][0].float(),
                                             iterations=self.cfg.pose_refine_iters)
        return {
            "world_from_cam": world_from_cam.cpu().numpy(),
            "depth": out["depth"][0].float().cpu().numpy(),
            "depth_conf": out["depth_conf"][0].float().cpu().numpy(),
        }

    def save_pretrained(self, root: Path | str) -> Path:
        """Write config.json and model.safetensors into the directory root."""
        return save_config_and_weights(self, self.cfg.to_json(), root)

    @classmethod
    def from_pretrained(cls, root: Path | str | None, *, flag: str = "--weights", device: str = "cpu") -> PanoVGGT:
        """Load from a local directory holding config.json and model.safetensors (never downloads).

        Missing or mismatching files raise MissingWeightsError (a StageInputError) naming `flag`.
        """
        return load_config_and_weights(
            lambda c: cls(PanoVGGTConfig.from_json(c)), root, model="PanoVGGT", flag=flag, device=device
        )

