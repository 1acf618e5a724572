"""Batched symmetric 3x3 eigendecomposition (numba, cyclic Jacobi) with torch.linalg.eigh as its reference."""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit

from panoworld.core.shapes import check_shape

MAX_SWEEPS = 12
"""Jacobi sweeps at most; a 3x3 matrix converges to float64 precision in 4-6 (quadratic convergence)."""


@njit(inline="always")
def _rotate(a, v, p, q):
    """One Jacobi rotation zeroing a[p, q] (a symmetric 3x3, updated in place; v accumulates the rotations)."""
    apq = a[p, q]
    if apq == 0.0:
        return
    theta = (a[q, q] - a[p, p]) / (2.0 * apq)
    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
    if theta < 0.0:
        t = -t
    c = 1.0 / math.sqrt(t * t + 1.0)
    s = t * c
    for k in range(3):  # a <- a J (columns p, q)
        akp = a[k, p]
        akq = a[k, q]
        a[k, p] = c * akp - s * akq
        a[k, q] = s * akp + c * akq
    for k in range(3):  # a <- J^T a (rows p, q)
        apk = a[p, k]
        aqk = a[q, k]
        a[p, k] = c * apk - s * aqk
        a[q, k] = s * apk + c * aqk
    a[p, q] = 0.0
    a[q, p] = 0.0
    for k in range(3):
        vkp = v[k, p]
        vkq = v[k, q]
        v[k, p] = c * vkp - s * vkq
        v[k, q] = s * vkp + c * vkq


@njit(cache=True, nogil=True)
def _eig3(cov, evals, axes):
    # Serial (0.4 us a matrix): with prange, about one run in ten of the same gaussians stage gave one Gaussian's scale
    # a few float32 ulps apart, and a rerun must give the same bytes.
    for i in range(cov.shape[0]):
        a = np.empty((3, 3))
        v = np.zeros((3, 3))
        finite = True
        for r in range(3):
            v[r, r] = 1.0
            for c in range(3):
                a[r, c] = 0.5 * (cov[i, r, c] + cov[i, c, r])
                finite &= math.isfinite(a[r, c])
        if not finite:
            evals[i, :] = np.nan
            axes[i, :, :] = np.nan
            continue
        scale = abs(a[0, 0]) + abs(a[1, 1]) + abs(a[2, 2]) + abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
        for _ in range(MAX_SWEEPS):
            off = abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
            if off <= 1e-300 or off <= 1e-17 * scale:
                break
            for p, q in ((0, 1), (0, 2), (1, 2)):  # one call site: numba inlines _rotate's IR once
                _rotate(a, v, p, q)
        d0, d1, d2 = a[0, 0], a[1, 1], a[2, 2]
        o0, o1, o2 = 0, 1, 2  # ascending order, as eigh
        if d0 > d1:
            d0, d1, o0, o1 = d1, d0, o1, o0
        if d1 > d2:
            d1, d2, o1, o2 = d2, d1, o2, o1
        if d0 > d1:
            d0, d1, o0, o1 = d1, d0, o1, o0
        evals[i, 0], evals[i, 1], evals[i, 2] = d0, d1, d2
        for r in range(3):
            axes[i, r, 0] = v[r, o0]
            axes[i, r, 1] = v[r, o1]
            axes[i, r, 2] = v[r, o2]


def eigh3(cov: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric part of cov (N, 3, 3) -> (eigenvalues (N, 3) ascending, eigenvectors (N, 3, 3) as columns) in cov's
    dtype, as torch.linalg.eigh of the symmetric part (computed in float64; rows with a non-finite entry give NaN).
    Eigenvectors of repeated eigenvalues are any orthonormal basis of their space, as with eigh."""
    check_shape("cov", cov, "N 3 3")
    a = np.ascontiguousarray(cov.detach().cpu().numpy(), dtype=np.float64)
    evals = np.empty(a.shape[:2])
    axes = np.empty(a.shape)
    if len(a):
        _eig3(a, evals, axes)
    return torch.from_numpy(evals).to(cov.dtype), torch.from_numpy(axes).to(cov.dtype)
