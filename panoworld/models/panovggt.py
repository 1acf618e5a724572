"""PanoVGGT: a VGGT-style network on ERP frames with ERP-aligned coordinate encoding: camera, depth and Gaussian heads."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from panoworld.core.conventions import erp_lonlat_from_pixel
from panoworld.core.rotations import rotmat_from_quat
from panoworld.core.shapes import check_shape
from panoworld.models.gs_decoder import GaussianHead, GaussianHeadConfig
from panoworld.models.pose_refine import refine_sequence
from panoworld.models.weights import (
    JsonConfig,
    MissingWeightsError,
    load_config_and_weights,
    save_config_and_weights,
)

if TYPE_CHECKING:
    from panoworld.io.gaussian_set import ContextFrames, FusionResult

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(kw_only=True)
class PanoVGGTConfig(JsonConfig):
    """Architecture of PanoVGGT; the defaults follow VGGT-1B (ViT-L width, 24 frame/global block pairs)."""

    patch_size: int = 14
    """Side of the square patches in pixels; input H and W must be multiples of it."""
    embed_dim: int = 1024
    """Token width."""
    depth: int = 24
    """Number of (frame attention, global attention) block pairs in the aggregator."""
    num_heads: int = 16
    """Attention heads per block."""
    mlp_ratio: float = 4.0
    """Hidden width of the block MLPs relative to embed_dim."""
    num_register_tokens: int = 4
    """Register tokens per frame (separate learned sets for frame 0 and the other frames, as in VGGT)."""
    coord_frequencies: int = 8
    """ERP coordinate encoding: sin/cos of k*lon and k*lat for k = 1..coord_frequencies (integer k: 2pi-periodic in lon)."""
    layer_scale_init: float = 0.01
    """Initial LayerScale of every residual branch."""
    camera_trunk_depth: int = 4
    """Transformer blocks of the camera head (attending across frames)."""
    camera_iterations: int = 4
    """Iterative refinement steps of the camera head."""
    pose_correlation: int = 0
    """Channels of the camera head's panoramic correlation cues (0 = off, VGGT's head): each frame's patch features
    correlated with the first frame's at every whole-patch turn about the vertical axis (ErpCorrelation). Not in the
    paper; a from-scratch tiny model does not learn to find the turn between two frames without it."""
    dpt_layers: tuple[int, ...] = (4, 11, 17, 23)
    """Aggregator block pairs whose tokens feed the depth head (four, shallow to deep)."""
    dpt_features: int = 256
    """Channels of the depth head's fusion path."""
    dpt_out_channels: tuple[int, ...] = (256, 512, 1024, 1024)
    """Channels of the four reassembled feature maps of the depth head."""
    image_height: int = 392
    """Input ERP height the weights were trained at (width = 2 * height); frames are resized to it."""
    pose_refine_iters: int = 0
    """Depth-consistency pose refinement in predict(): Gauss-Newton steps of every frame against frame 0, then two
    sweeps over neighbouring frames (pose_refine.refine_sequence), so that the predicted depth maps agree; 0 = off,
    the camera head's poses as VGGT. Not in the paper; no learned parameters; training losses always see the head's
    own poses."""
    gaussian_head: GaussianHeadConfig | None = None
    """The voxel-aligned Gaussian head sharing the aggregator's tokens (None = camera and depth heads only)."""

    def __post_init__(self):
        if isinstance(self.gaussian_head, dict):
            self.gaussian_head = GaussianHeadConfig.from_json(self.gaussian_head)
        if self.gaussian_head is not None and not -self.depth <= self.gaussian_head.backbone_layer < self.depth:
            raise ValueError(f"gaussian_head.backbone_layer={self.gaussian_head.backbone_layer} must index the "
                             f"{self.depth} aggregator block pairs")
        self.dpt_layers = tuple(int(i) for i in self.dpt_layers)
        self.dpt_out_channels = tuple(int(c) for c in self.dpt_out_channels)
        if len(self.dpt_layers) != 4 or len(self.dpt_out_channels) != 4:
            raise ValueError(f"{self.dpt_layers=} and {self.dpt_out_channels=} must both have 4 entries")
        if max(self.dpt_layers) >= self.depth or min(self.dpt_layers) < 0:
            raise ValueError(f"{self.dpt_layers=} must index the {self.depth} aggregator block pairs")
        if self.embed_dim % self.num_heads:
            raise ValueError(f"{self.embed_dim=} is not divisible by {self.num_heads=}")
        if self.image_height % self.patch_size:
            raise ValueError(f"{self.image_height=} is not a multiple of {self.patch_size=}")
        if self.pose_refine_iters < 0:
            raise ValueError(f"{self.pose_refine_iters=} but expected >= 0 (0 = off)")


def erp_coordinate_features(
    grid_h: int, grid_w: int, frequencies: int, lon_offset: float = 0.0
) -> np.ndarray:
    """ERP-aligned coordinate encoding of a patch grid -> (grid_h, grid_w, 4 * frequencies) float32.

    Each patch centre's (lon, lat) (conventions.erp_lonlat_from_pixel, grid_w patches spanning 2pi) is encoded
    as [sin(k lon), cos(k lon), sin(k lat), cos(k lat)] for integer k = 1..frequencies. Integer k makes the
    encoding 2pi-periodic in longitude, so it is continuous across the ERP seam: shifting lon by one patch
    (lon_offset = 2pi / grid_w) equals rolling the grid by one column.
    """
    u = (np.arange(grid_w) + 0.5)[None, :]
    v = (np.arange(grid_h) + 0.5)[:, None]
    lon, lat = erp_lonlat_from_pixel(u, v, grid_h, grid_w)
    lon, lat = np.broadcast_arrays(lon + lon_offset, lat)
    k = np.arange(1, frequencies + 1, dtype=np.float64)
    klon, klat = lon[..., None] * k, lat[..., None] * k
    feats = np.concatenate([np.sin(klon), np.cos(klon), np.sin(klat), np.cos(klat)], axis=-1)
    return feats.astype(np.float32)


class Attention(nn.Module):
    """Multi-head self-attention with QK-norm (as VGGT), via scaled_dot_product_attention."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.q_norm = nn.LayerNorm(dim // num_heads)
        self.k_norm = nn.LayerNorm(dim // num_heads)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, d // self.num_heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(self.q_norm(q), self.k_norm(k), v)
        return self.proj(out.transpose(1, 2).reshape(b, n, d))


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale residuals."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, layer_scale_init: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, num_heads)
        self.ls1 = nn.Parameter(torch.full((dim,), layer_scale_init))
        self.norm2 = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))
        self.ls2 = nn.Parameter(torch.full((dim,), layer_scale_init))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1 * self.attn(self.norm1(x))
        return x + self.ls2 * self.mlp(self.norm2(x))


class ErpConv2d(nn.Conv2d):
    """Conv2d on ERP feature maps: circular padding across the seam (columns), replicate padding at the poles (rows)."""

    def __init__(self, in_ch: int, out_ch: int, kernel_size: int = 3, stride: int = 1):
        super().__init__(in_ch, out_ch, kernel_size, stride=stride, padding=0)
        self.pad = kernel_size // 2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.pad:
            x = F.pad(x, (self.pad, self.pad, 0, 0), mode="circular")
            x = F.pad(x, (0, 0, self.pad, self.pad), mode="replicate")
        return super().forward(x)


def erp_resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear resize of ERP maps (B, C, h, w) to size (H, W), wrapping across the seam when W is a multiple of w."""
    h, w = x.shape[-2:]
    if size[1] % w:
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    s = size[1] // w
    xp = F.pad(x, (1, 1, 0, 0), mode="circular")
    out = F.interpolate(xp, size=(size[0], size[1] + 2 * s), mode="bilinear", align_corners=False)
    return out[..., s:-s]


class ResidualConvUnit(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.conv1 = ErpConv2d(ch, ch)
        self.conv2 = ErpConv2d(ch, ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """DPT fusion: add the skip map (after a residual unit), refine, upsample x2, 1x1 projection."""

    def __init__(self, ch: int, has_skip: bool):
        super().__init__()
        self.skip_unit = ResidualConvUnit(ch) if has_skip else None
        self.unit = ResidualConvUnit(ch)
        self.out = nn.Conv2d(ch, ch, 1)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None, size: tuple[int, int] | None = None):
        if skip is not None:
            x = x + self.skip_unit(skip)
        x = self.unit(x)
        size = size or (x.shape[-2] * 2, x.shape[-1] * 2)
        return self.out(erp_resize(x, size))


class DepthHead(nn.Module):
    """DPT-lite: reassemble tokens of four blocks at x4, x2, x1, x1/2 of the patch grid, fuse, upsample to (H, W).

    Outputs depth = exp(.) (metres, Euclidean ray distance) and confidence = 1 + exp(.), as VGGT's depth head.
    """

    def __init__(self, cfg: PanoVGGTConfig):
        super().__init__()
        d_in, ch, feat = 2 * cfg.embed_dim, cfg.dpt_out_channels, cfg.dpt_features
        self.norm = nn.LayerNorm(d_in)
        self.projects = nn.ModuleList([nn.Conv2d(d_in, c, 1) for c in ch])
        self.resize = nn.ModuleList(
            [
                nn.ConvTranspose2d(ch[0], ch[0], 4, stride=4),
                nn.ConvTranspose2d(ch[1], ch[1], 2, stride=2),
                nn.Identity(),
                ErpConv2d(ch[3], ch[3], 3, stride=2),
            ]
        )
        self.layer_rn = nn.ModuleList([ErpConv2d(c, feat) for c in ch])
        self.fusion = nn.ModuleList([FusionBlock(feat, has_skip=i < 3) for i in range(4)])
        self.head = nn.Sequential(ErpConv2d(feat, feat // 2))
        self.out = nn.Sequential(ErpConv2d(feat // 2, 32), nn.ReLU(), nn.Conv2d(32, 2, 1))

    def forward(self, tokens: list[torch.Tensor], grid: tuple[int, int], size: tuple[int, int]):
        """tokens: four (B*S, P, 2D) patch-token tensors; grid = (Hp, Wp); size = (H, W) -> (depth, conf) (B*S, H, W)."""
        maps = []
        for i, t in enumerate(tokens):
            x = self.norm(t).transpose(1, 2).reshape(t.shape[0], -1, *grid)
            maps.append(self.layer_rn[i](self.resize[i](self.projects[i](x))))
        x = self.fusion[3](maps[3], size=maps[2].shape[-2:])
        x = self.fusion[2](x, maps[2], size=maps[1].shape[-2:])
        x = self.fusion[1](x, maps[1], size=maps[0].shape[-2:])
        x = self.fusion[0](x, maps[0])
        x = self.out(erp_resize(self.head(x), size))
        depth = torch.exp(x[:, 0].clamp(max=12.0))
        conf = 1.0 + torch.exp(x[:, 1].clamp(max=12.0))
        return depth, conf


quat_wxyz_to_rotmat = rotmat_from_quat


class ErpCorrelation(nn.Module):
    """Pose cues per frame from correlating its patch features with the first frame's at every whole-patch turn.

    A turn about the vertical axis rolls ERP columns, so corr[delta] = mean over patches of <f_0(r, c), f_i(r, c +
    delta)> (features projected and unit-normalised) peaks at the turn; a softmax over delta reads it as the expected
    (cos, sin) of the roll angle (with the peak and mean correlation: 4 numbers). A translation moves the columns of
    frame 0 by different amounts (away from the direction of travel, towards the opposite one; most at 90 degrees from
    it): the per-column expected shift relative to the turn, and how well each column matches, over the column's
    longitude, read by their first and second circular harmonics (4 more numbers). With the depth head's depth (given,
    not differentiated), the horizon band's depth of frame 0 minus frame i's (turned back by the expected roll) is
    read by its mean and first harmonic (3 more, in metres: moving by t towards a wall at longitude phi shortens its
    depth by about t cos(phi - heading)). The 11 are embedded to the camera head's width. Independent of the grid and
    image size, so the same weights run at any input resolution.
    """

    CUES = 11

    def __init__(self, in_dim: int, out_dim: int, channels: int):
        super().__init__()
        self.norm = nn.LayerNorm(in_dim)
        self.proj = nn.Linear(in_dim, channels)
        self.log_temperature = nn.Parameter(torch.tensor(2.3))
        self.embed = nn.Linear(self.CUES, out_dim)

    def forward(self, patch_tokens: torch.Tensor, grid: tuple[int, int], depth: torch.Tensor) -> torch.Tensor:
        """patch_tokens (B, S, hp * wp, C), depth (B, S, H, W) metres -> (B, S, out_dim)."""
        return self.embed(self.cue(patch_tokens, grid, depth))

    def cue(self, patch_tokens: torch.Tensor, grid: tuple[int, int], depth: torch.Tensor) -> torch.Tensor:
        """patch_tokens (B, S, hp * wp, C), depth (B, S, H, W) -> (B, S, 11): expected cos and sin of the roll angle,
        peak and mean correlation; first harmonic (cos, sin) of the per-column shift; second harmonic of the
        per-column match; mean and first harmonic of the horizon depth difference."""
        b, s, _, _ = patch_tokens.shape
        hp, wp = grid
        f = F.normalize(self.proj(self.norm(patch_tokens)), dim=-1).reshape(b, s, hp, wp, -1)
        cols = torch.stack([(f[:, :1] * f.roll(-d, dims=3)).sum(-1).mean(2) for d in range(wp)], 2)  # (B, S, D, wp)
        corr = cols.mean(-1)  # (B, S, D)
        temp = self.log_temperature.exp()
        prob = torch.softmax(corr * temp, dim=-1)
        angle = torch.arange(wp, device=f.device, dtype=f.dtype) * (2 * np.pi / wp)
        cos_g, sin_g = (prob * angle.cos()).sum(-1), (prob * angle.sin()).sum(-1)
        prob_col = torch.softmax(cols * temp, dim=2)
        cos_c, sin_c = (prob_col * angle.cos()[:, None]).sum(2), (prob_col * angle.sin()[:, None]).sum(2)  # (B, S, wp)
        shift = sin_c * cos_g[..., None] - cos_c * sin_g[..., None]  # sin(column's shift - the turn)
        match = (prob[..., None] * cols).sum(2)  # (B, S, wp)
        lon = (torch.arange(wp, device=f.device, dtype=f.dtype) + 0.5) * (2 * np.pi / wp)
        h, w = depth.shape[-2:]
        band = depth.detach()[..., h // 3: h - h // 3, :].mean(-2).to(f.dtype)  # (B, S, W): |latitude| < 30 deg
        step = w // wp
        back = torch.stack([band.roll(-d * step, dims=-1) for d in range(wp)], 2)  # (B, S, D, W)
        diff = band[:, :1] - (prob[..., None] * back).sum(2)  # (B, S, W)
        lon_px = (torch.arange(w, device=f.device, dtype=f.dtype) + 0.5) * (2 * np.pi / w)
        return torch.stack([cos_g, sin_g, corr.amax(-1), corr.mean(-1),
                            (shift * lon.cos()).mean(-1), (shift * lon.sin()).mean(-1),
                            (match * (2 * lon).cos()).mean(-1), (match * (2 * lon).sin()).mean(-1),
                            diff.mean(-1), 2 * (diff * lon_px.cos()).mean(-1), 2 * (diff * lon_px.sin()).mean(-1)], -1)


class CameraHead(nn.Module):
    """Per-frame pose (translation, quaternion wxyz) from the camera tokens, refined iteratively across frames.

    The raw 7-vectors are poses P_i in a latent frame; the output world_from_cam_i = P_0^-1 P_i, so frame 0 is the
    identity by construction and the world is the canonical frame (camera 0, OpenCV axes).
    """

    def __init__(self, cfg: PanoVGGTConfig):
        super().__init__()
        d = 2 * cfg.embed_dim
        self.iterations = cfg.camera_iterations
        self.norm = nn.LayerNorm(d)
        self.pose_embed = nn.Linear(7, d)
        self.trunk = nn.Sequential(
            *[Block(d, cfg.num_heads, cfg.mlp_ratio, cfg.layer_scale_init) for _ in range(cfg.camera_trunk_depth)]
        )
        self.trunk_norm = nn.LayerNorm(d)
        self.delta = nn.Linear(d, 7)
        self.correlation = ErpCorrelation(d, d, cfg.pose_correlation) if cfg.pose_correlation else None

    def forward(self, cam_tokens: torch.Tensor, patch_tokens: torch.Tensor | None = None,
                grid: tuple[int, int] | None = None, depth: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """cam_tokens (B, S, 2D) [, patch_tokens (B, S, P, 2D) on a grid (hp, wp) and depth (B, S, H, W), for the
        correlation cues] ->
        (world_from_cam (B, S, 4, 4), pose encoding (B, S, 7) = [t, q_wxyz] of P_i)."""
        b, s, _ = cam_tokens.shape
        tokens = self.norm(cam_tokens)
        if self.correlation is not None:
            tokens = tokens + self.correlation(patch_tokens, grid, depth)
        pose = torch.zeros(b, s, 7, dtype=tokens.dtype, device=tokens.device)
        pose[..., 3] = 1.0
        for _ in range(self.iterations):
            x = self.trunk_norm(self.trunk(tokens + self.pose_embed(pose.detach())))
            pose = pose + self.delta(x)
        P = torch.zeros(b, s, 4, 4, dtype=torch.float64, device=tokens.device)
        P[..., :3, :3] = quat_wxyz_to_rotmat(pose[..., 3:].double())
        P[..., :3, 3] = pose[..., :3].double()
        P[..., 3, 3] = 1.0
        world_from_cam = torch.linalg.inv(P[:, :1]) @ P
        world_from_cam[:, 0] = torch.eye(4, dtype=torch.float64, device=tokens.device)
        return world_from_cam, pose


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

