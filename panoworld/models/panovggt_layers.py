"""PanoVGGT's parts: ERP coordinate encoding, transformer blocks, ERP convolutions, the depth and camera heads."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from panoworld.core.conventions import erp_lonlat_from_pixel
from panoworld.core.rotations import rotmat_from_quat
from panoworld.models.panovggt_config import PanoVGGTConfig


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
