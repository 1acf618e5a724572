"""The Gaussian head of PanoVGGT on a tiny random config: shapes, bounded outputs, shared confidence fusion, gradients."""

from __future__ import annotations

import pytest
import torch

from panoworld.geometry.voxels import fuse_voxels
from panoworld.io.gaussian_set import SH_C0
from panoworld.models.gs_decoder import (
    GaussianHead,
    GaussianHeadConfig,
    plucker_features,
    sinusoidal_encoding,
)

torch.set_num_threads(1)

TINY = {
    "embed_dim": 32, "num_heads": 2, "global_layers": 1, "feature_dim": 8, "voxel_size": 0.25,
    "knn_k": 4, "knn_layers": 1, "knn_heads": 2, "token_dim": 16, "pe_freqs": 2, "mlp_hidden": 32,
    "gaussians_per_voxel": 2, "sh_degree": 1,
}
PATCH, BACKBONE_DIM = 8, 24


def inputs(V=2, H=16, W=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(V, 3, H, W, generator=g)
    depth = 1.0 + 2.0 * torch.rand(V, H, W, generator=g)
    depth[0, 0, :4] = 0.0  # no depth there
    poses = torch.eye(4).repeat(V, 1, 1)
    poses[1, :3, 3] = torch.tensor([0.3, 0.0, -0.2])
    tokens = torch.randn(V, (H // PATCH) * (W // PATCH), BACKBONE_DIM, generator=g)
    return img, depth, poses, tokens


@pytest.fixture(scope="module")
def head():
    torch.manual_seed(0)
    return GaussianHead(GaussianHeadConfig(**TINY), PATCH, BACKBONE_DIM).eval()


def test_shapes_and_bounded_outputs(head):
    cfg = head.cfg
    img, depth, poses, tokens = inputs()
    with torch.no_grad():
        out = head(img, depth, poses, tokens)
    g = out["gaussians"]
    nv = out["centres"].shape[0]
    assert len(g) == cfg.gaussians_per_voxel * nv
    assert g.sh_rest.shape == (len(g), 3, 3) and out["confidence"].shape == (2, 16, 32)
    assert out["inverse"].shape == (int((depth > 0).sum()),)
    offs = (g.means.reshape(nv, -1, 3) - out["centres"][:, None]).abs()
    assert float(offs.max()) <= cfg.max_offset * cfg.voxel_size + 1e-6
    assert float(g.scales.min()) >= cfg.min_scale * cfg.voxel_size - 1e-7
    assert float(g.scales.max()) <= cfg.max_scale * cfg.voxel_size + 1e-7
    assert torch.allclose(g.quats.norm(dim=-1), torch.ones(len(g)), atol=1e-5)
    assert float(g.opacities.min()) > 0 and float(g.opacities.max()) < 1
    rgb = 0.5 + SH_C0 * g.sh_dc
    assert float(rgb.min()) >= 0 and float(rgb.max()) <= 1
    assert float(g.sh_rest.abs().max()) <= cfg.max_sh_rest


def test_centres_are_the_confidence_weighted_fusion(head):
    img, depth, poses, tokens = inputs()
    with torch.no_grad():
        out = head(img, depth, poses, tokens)
        _, points = plucker_features(img, depth, poses)
    valid = (depth > 0).reshape(-1)
    x = points.reshape(-1, 3)[valid]
    w = out["confidence"].reshape(-1)[valid]
    p, _, _, inv = fuse_voxels(x, w, torch.zeros(len(x), 1), head.cfg.voxel_size)
    assert torch.allclose(out["centres"], p, atol=1e-6) and torch.equal(out["inverse"], inv)
    # p_j = sum w x / (sum w + eps) for one voxel, written out.
    j = int(inv[0])
    m = inv == j
    assert torch.allclose(p[j], (w[m, None] * x[m]).sum(0) / (w[m].sum() + 1e-6), atol=1e-6)


def test_backbone_tokens_change_the_gaussians(head):
    img, depth, poses, tokens = inputs()
    with torch.no_grad():
        a = head(img, depth, poses, tokens)["gaussians"]
        b = head(img, depth, poses, tokens + 1.0)["gaussians"]
    assert a.means.shape == b.means.shape and not torch.allclose(a.sh_dc, b.sh_dc)
    with pytest.raises(ValueError, match="backbone's patch grid"):
        head(img, depth, poses, tokens[:, :-1])


def test_plucker_features_and_encoding():
    img, depth, poses, _ = inputs()
    f, pts = plucker_features(img, depth, poses)
    assert f.shape == (2, 10, 16, 32)
    d, m = f[:, 4:7], f[:, 7:10]
    assert torch.allclose(d.norm(dim=1), torch.ones(2, 16, 32), atol=1e-5)
    o = poses[1, :3, 3]
    assert torch.allclose(m[1, :, 3, 5], torch.linalg.cross(o, d[1, :, 3, 5]), atol=1e-6)
    assert torch.allclose(pts[1, 3, 5], o + depth[1, 3, 5] * d[1, :, 3, 5], atol=1e-5)
    pe = sinusoidal_encoding(torch.zeros(1, 3), 2, 16.0)
    assert pe.shape == (1, 15) and torch.equal(pe[0, 3:9], torch.zeros(6)) and torch.equal(pe[0, 9:], torch.ones(6))


def test_deterministic_and_trainable(head):
    img, depth, poses, tokens = inputs()
    with torch.no_grad():
        a = head(img, depth, poses, tokens)["gaussians"]
        b = head(img, depth, poses, tokens)["gaussians"]
    assert torch.equal(a.means, b.means) and torch.equal(a.sh_dc, b.sh_dc)
    out = head(img, depth, poses, tokens)
    loss = out["gaussians"].means.sum() + out["gaussians"].sh_dc.square().mean()
    loss.backward()
    assert head.confidence.weight.grad.abs().sum() > 0  # through the fused centres
    assert head.patch_embed.weight.grad.abs().sum() > 0  # through global attention
    assert head.backbone_proj.weight.grad.abs().sum() > 0  # the shared backbone features are used
    head.zero_grad()


def test_bad_inputs_raise(head):
    img, depth, poses, tokens = inputs()
    with pytest.raises(ValueError, match="W = 2H"):
        head(img[..., :24], depth[..., :24], poses, tokens)
    with pytest.raises(ValueError, match="every depth"):
        head(img, torch.zeros_like(depth), poses, tokens)
    with pytest.raises(ValueError, match="must divide"):
        GaussianHeadConfig(**{**TINY, "num_heads": 3})
