"""The paper's voxel-aligned Gaussian head of PanoVGGT: global attention, confidence-weighted voxel fusion, KNN attention."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from panoworld.core.conventions import erp_dirs
from panoworld.geometry.voxels import fuse_voxels
from panoworld.io.gaussian_set import SH_C0, Gaussians
from panoworld.models.weights import JsonConfig

IN_CHANNELS = 10
"""Per-pixel input features: RGB (3), depth (1), ray direction d (3), moment o x d (3)."""


@dataclass(kw_only=True)
class GaussianHeadConfig(JsonConfig):
    """Architecture of the Gaussian head; its patch grid is the backbone's (PanoVGGTConfig.patch_size)."""

    backbone_layer: int = -1
    """Aggregator block pair whose (frame, global) patch tokens the head shares (-1 = the last)."""
    embed_dim: int = 384
    """Token width of the global multi-view attention."""
    num_heads: int = 6
    """Heads of the global attention."""
    global_layers: int = 6
    """Transformer layers of joint self-attention over all patches of all views."""
    feature_dim: int = 64
    """Channels of the upsampled per-pixel features that are fused into voxels."""
    voxel_size: float = 0.02
    """Voxel edge length in metres (the paper's epsilon)."""
    knn_k: int = 16
    """Neighbours (nearest voxel centres, itself included) each voxel token attends to."""
    knn_layers: int = 2
    """KNN attention layers over the voxel tokens."""
    knn_heads: int = 4
    """Heads of the KNN attention."""
    token_dim: int = 128
    """Width of the voxel tokens."""
    pe_freqs: int = 8
    """Frequencies of the sinusoidal encoding gamma(p) of voxel centres."""
    pe_scale: float = 16.0
    """Length in metres of the lowest frequency's period of gamma(p)."""
    mlp_hidden: int = 256
    """Hidden width of the Gaussian MLP phi_gs."""
    gaussians_per_voxel: int = 2
    """K Gaussians decoded per occupied voxel."""
    sh_degree: int = 1
    """Spherical-harmonic degree of the decoded colours (0-3)."""
    max_offset: float = 1.0
    """Centre offsets are tanh(.) * max_offset * voxel_size."""
    min_scale: float = 0.05
    """Lower bound of the scales, as a fraction of voxel_size (sigmoid-bounded between min and max)."""
    max_scale: float = 2.0
    """Upper bound of the scales, as a multiple of voxel_size."""
    max_sh_rest: float = 0.5
    """Higher-order SH coefficients are tanh(.) * max_sh_rest."""

    def __post_init__(self):
        if self.embed_dim % self.num_heads or self.token_dim % self.knn_heads:
            raise ValueError(f"{self.embed_dim=}/{self.num_heads=} and {self.token_dim=}/{self.knn_heads=} must divide")
        if self.sh_degree not in (0, 1, 2, 3):
            raise ValueError(f"{self.sh_degree=} but expected 0..3")
        if not 0 < self.min_scale < self.max_scale:
            raise ValueError(f"{self.min_scale=}, {self.max_scale=} but expected 0 < min < max")
        if not self.voxel_size > 0:
            raise ValueError(f"{self.voxel_size=} but expected > 0")

    @property
    def sh_coeffs(self) -> int:
        return (self.sh_degree + 1) ** 2


def plucker_features(images: torch.Tensor, depths: torch.Tensor, world_from_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """images (V, 3, H, W) in [0, 1], depths (V, H, W) ray distance, poses (V, 4, 4) ->
    (features f = [I, z, d, o x d] (V, 10, H, W), world points o + z d (V, H, W, 3))."""
    H, W = images.shape[-2:]
    dirs_cam = torch.from_numpy(erp_dirs(H, W)).to(images)
    R = world_from_cam[:, :3, :3].to(images)
    o = world_from_cam[:, :3, 3].to(images)
    d = torch.einsum("vij,hwj->vhwi", R, dirs_cam)
    m = torch.cross(o[:, None, None, :].expand_as(d), d, dim=-1)
    feats = torch.cat([images, depths[:, None], d.permute(0, 3, 1, 2), m.permute(0, 3, 1, 2)], 1)
    points = o[:, None, None, :] + depths[..., None] * d
    return feats, points


def sinusoidal_encoding(p: torch.Tensor, freqs: int, scale: float) -> torch.Tensor:
    """gamma(p) for points (N, 3): [p / scale, sin(2^k 2pi p / scale), cos(...)] for k < freqs -> (N, 3 + 6 freqs)."""
    k = (2.0 ** torch.arange(freqs, dtype=p.dtype, device=p.device)) * (2 * math.pi / scale)
    ang = (p[:, :, None] * k).reshape(p.shape[0], -1)
    return torch.cat([p / scale, torch.sin(ang), torch.cos(ang)], 1)


def knn_indices(centres: torch.Tensor, k: int) -> torch.Tensor:
    """Indices (V, k) of the k nearest voxel centres (itself first); k is capped at V."""
    from scipy.spatial import cKDTree

    pts = centres.detach().cpu().double().numpy()
    k = min(k, len(pts))
    _, idx = cKDTree(pts).query(pts, k=k)
    return torch.from_numpy(np.asarray(idx, np.int64).reshape(len(pts), k)).to(centres.device)


class KNNAttention(nn.Module):
    """Pre-norm multi-head attention of each voxel token over its k nearest voxels, with relative-position keys."""

    def __init__(self, dim: int, heads: int, voxel_size: float):
        super().__init__()
        self.heads = heads
        self.voxel_size = voxel_size
        self.norm = nn.LayerNorm(dim)
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.rel = nn.Sequential(nn.Linear(3, dim), nn.GELU(), nn.Linear(dim, dim))
        self.proj = nn.Linear(dim, dim)
        self.mlp = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, x: torch.Tensor, centres: torch.Tensor, nbr: torch.Tensor, chunk: int = 1 << 16) -> torch.Tensor:
        out = []
        for s in range(0, x.shape[0], chunk):
            out.append(self._block(x, centres, nbr[s : s + chunk], slice(s, s + chunk)))
        x = x + torch.cat(out)
        return x + self.mlp(x)

    def _block(self, x, centres, nbr, rows) -> torch.Tensor:
        n, k = nbr.shape
        h = self.norm(x)
        q = self.q(h[rows]).reshape(n, self.heads, 1, -1)
        rel = self.rel((centres[nbr] - centres[rows][:, None]) / self.voxel_size)
        kv = self.kv(h[nbr] + rel).reshape(n, k, 2, self.heads, -1).permute(2, 0, 3, 1, 4)
        att = F.scaled_dot_product_attention(q, kv[0], kv[1])
        return self.proj(att.reshape(n, -1))


class GaussianHead(nn.Module):
    """Context views (images, depth, poses) + the backbone's patch tokens -> voxel-aligned 3D Gaussians.

    The paper's head: f = [I, z, d, o x d] per pixel, patchified on the backbone's patch grid and summed with a
    projection of the shared backbone tokens; joint self-attention over all patches of all views; unpatchify to
    full resolution; per-pixel confidence w; the confidence-weighted voxel fusion of geometry.voxels.fuse_voxels (p_j and
    f_vox_j); KNN attention over the voxel tokens; phi_gs([f_vox, gamma(p)]) -> K Gaussians per voxel with bounded
    activations.
    """

    def __init__(self, cfg: GaussianHeadConfig, patch_size: int, backbone_dim: int):
        super().__init__()
        self.cfg = cfg
        self.patch_size = patch_size
        c = cfg
        self.patch_embed = nn.Conv2d(IN_CHANNELS, c.embed_dim, patch_size, stride=patch_size)
        self.backbone_norm = nn.LayerNorm(backbone_dim)
        self.backbone_proj = nn.Linear(backbone_dim, c.embed_dim)
        layer = nn.TransformerEncoderLayer(
            c.embed_dim, c.num_heads, 4 * c.embed_dim, dropout=0.0, activation="gelu", batch_first=True, norm_first=True
        )
        self.global_attn = nn.TransformerEncoder(layer, c.global_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(c.embed_dim)
        self.unpatch = nn.Linear(c.embed_dim, patch_size * patch_size * c.feature_dim)
        self.skip = nn.Conv2d(IN_CHANNELS, c.feature_dim, 1)
        self.refine = nn.Sequential(nn.GELU(), nn.Conv2d(c.feature_dim, c.feature_dim, 1))
        self.confidence = nn.Conv2d(c.feature_dim, 1, 1)
        pe_dim = 3 + 6 * c.pe_freqs
        self.token = nn.Linear(c.feature_dim + pe_dim, c.token_dim)
        self.knn = nn.ModuleList(KNNAttention(c.token_dim, c.knn_heads, c.voxel_size) for _ in range(c.knn_layers))
        self.per_gaussian = 3 + 3 + 4 + 1 + 3 * c.sh_coeffs
        self.head = nn.Sequential(
            nn.LayerNorm(c.token_dim + pe_dim), nn.Linear(c.token_dim + pe_dim, c.mlp_hidden), nn.GELU(),
            nn.Linear(c.mlp_hidden, c.mlp_hidden), nn.GELU(), nn.Linear(c.mlp_hidden, c.gaussians_per_voxel * self.per_gaussian),
        )

    def pixel_features(self, feats: torch.Tensor, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(V, 10, H, W) inputs + backbone patch tokens (V, h*w, Db) -> (features (V, C, H, W), confidence (V, H, W))."""
        V, _, H, W = feats.shape
        p = self.patch_size
        tok = self.patch_embed(feats)  # (V, E, h, w)
        h, w = tok.shape[-2:]
        if tokens.shape[:2] != (V, h * w):
            raise ValueError(f"{tuple(tokens.shape)=} but expected ({V}, {h * w}, D): the backbone's patch grid")
        tok = tok.flatten(2).transpose(1, 2) + self.backbone_proj(self.backbone_norm(tokens))
        tok = self.norm(self.global_attn(tok.reshape(1, V * h * w, -1))).reshape(V, h, w, -1)  # all views jointly
        up = self.unpatch(tok).reshape(V, h, w, self.cfg.feature_dim, p, p)
        up = up.permute(0, 3, 1, 4, 2, 5).reshape(V, self.cfg.feature_dim, H, W)
        x = up + self.skip(feats)
        x = x + self.refine(x)
        return x, torch.sigmoid(self.confidence(x))[:, 0]

    def forward(self, images: torch.Tensor, depths: torch.Tensor, world_from_cam: torch.Tensor,
                tokens: torch.Tensor) -> dict:
        """images (V, 3, H, W) in [0, 1], depths (V, H, W) metres (0 = none), world_from_cam (V, 4, 4), backbone
        patch tokens (V, (H/p)*(W/p), Db).

        Returns {"gaussians": Gaussians of torch tensors (N = K * voxels), "confidence": (V, H, W),
        "centres": (Nv, 3) fused voxel centres p_j, "inverse": (M,) voxel of each valid pixel}.
        """
        c = self.cfg
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"{tuple(images.shape)=} but expected (V, 3, H, W)")
        V, _, H, W = images.shape
        if depths.shape != (V, H, W) or world_from_cam.shape != (V, 4, 4):
            raise ValueError(f"{tuple(depths.shape)=} {tuple(world_from_cam.shape)=} but expected {(V, H, W)}, {(V, 4, 4)}")
        if W != 2 * H or H % self.patch_size:
            raise ValueError(f"frames are {W}x{H} (WxH) but the Gaussian head needs W = 2H with H a multiple of {self.patch_size}")
        depths = torch.nan_to_num(depths.float(), nan=0.0, posinf=0.0).clamp(min=0.0)
        feats, points = plucker_features(images.float(), depths, world_from_cam.float())
        pix, conf = self.pixel_features(feats, tokens.float())
        valid = (depths > 0).reshape(-1)
        if not bool(valid.any()):
            raise ValueError("Gaussian head: every depth is 0, inf or NaN")
        x = points.reshape(-1, 3)[valid]
        f = pix.permute(0, 2, 3, 1).reshape(-1, c.feature_dim)[valid]
        centres, f_vox, _, inverse = fuse_voxels(x, conf.reshape(-1)[valid], f, c.voxel_size)
        pe = sinusoidal_encoding(centres, c.pe_freqs, c.pe_scale)
        tok = self.token(torch.cat([f_vox, pe], 1))
        nbr = knn_indices(centres, c.knn_k)
        for layer in self.knn:
            tok = layer(tok, centres, nbr)
        raw = self.head(torch.cat([tok, pe], 1)).reshape(-1, c.gaussians_per_voxel, self.per_gaussian)
        return {"gaussians": self._activate(raw, centres), "confidence": conf, "centres": centres, "inverse": inverse}

    def _activate(self, raw: torch.Tensor, centres: torch.Tensor) -> Gaussians:
        """Bounded activations of the (Nv, K, 11 + 3 SH) raw outputs -> Gaussians (torch tensors)."""
        c = self.cfg
        off, s, q, o, sh = raw.split([3, 3, 4, 1, 3 * c.sh_coeffs], -1)
        means = centres[:, None] + torch.tanh(off) * (c.max_offset * c.voxel_size)
        scales = c.voxel_size * (c.min_scale + (c.max_scale - c.min_scale) * torch.sigmoid(s))
        quats = F.normalize(q + torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype, device=q.device), dim=-1)
        sh = sh.reshape(*sh.shape[:2], c.sh_coeffs, 3)
        dc = (torch.sigmoid(sh[:, :, 0]) - 0.5) / SH_C0
        rest = torch.tanh(sh[:, :, 1:]) * c.max_sh_rest
        return Gaussians(
            means=means.reshape(-1, 3), scales=scales.reshape(-1, 3), quats=quats.reshape(-1, 4),
            opacities=torch.sigmoid(o).reshape(-1), sh_dc=dc.reshape(-1, 3),
            sh_rest=rest.reshape(len(centres) * c.gaussians_per_voxel, c.sh_coeffs - 1, 3),
        )
