"""eig3.eigh3 against its reference, torch.linalg.eigh."""

import numpy as np
import torch

from panoworld.gaussians.eig3 import eigh3


def _covs(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    b = a * torch.exp(1.5 * torch.randn(n, 1, 3, generator=g, dtype=torch.float64))  # anisotropic: flat and thin
    c = b @ b.transpose(1, 2)
    c[:50] = torch.diag(torch.tensor([2.0, 2.0, 1e-9], dtype=torch.float64))  # a disc: a repeated eigenvalue
    c[50:60] = 0.0
    c[60:70] = torch.eye(3, dtype=torch.float64) * 5.0
    return c


def test_eigh3_matches_torch_eigh():
    c = _covs(5000)
    e, v = eigh3(c)
    e0, _ = torch.linalg.eigh(c)
    top = e0.abs().max(1, keepdim=True).values.clamp_min(1e-300)
    assert ((e - e0).abs() / top).max() < 1e-13
    assert (e[:, 1:] >= e[:, :-1]).all()
    eye = torch.eye(3, dtype=torch.float64)
    assert (v.transpose(1, 2) @ v - eye).abs().max() < 1e-13
    recon = v @ torch.diag_embed(e) @ v.transpose(1, 2)
    assert ((recon - c).abs().amax((1, 2)) / top[:, 0]).max() < 1e-13


def test_eigh3_symmetric_part_dtype_and_nan():
    c = _covs(200, seed=1).float()
    c[5, 0, 1] += 1.0  # not symmetric: its symmetric part is decomposed, as gaussians_from_cov did before
    c[7, 2, 2] = float("nan")
    e, v = eigh3(c)
    assert e.dtype == torch.float32 and v.dtype == torch.float32
    sym = 0.5 * (c + c.transpose(1, 2))
    ok = torch.ones(len(c), dtype=torch.bool)
    ok[7] = False
    e0, _ = torch.linalg.eigh(sym[ok].double())
    assert np.allclose(e[ok].double(), e0, rtol=0, atol=2e-6 * float(e0.abs().max()))
    assert torch.isnan(e[7]).all() and torch.isnan(v[7]).all()
    assert eigh3(torch.zeros(0, 3, 3))[0].shape == (0, 3)
