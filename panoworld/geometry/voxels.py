"""Voxel fusion of weighted observations: packed voxel keys, per-voxel sums (exact in any order), fused values."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

FUSION_EPS = 1e-6
"""The paper's epsilon in the denominators of the voxel fusion equations."""


_KEY_BITS = 21


_KEY_HALF = 1 << (_KEY_BITS - 1)


def voxel_keys(points: torch.Tensor, voxel_size: float) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (M, 3) -> (packed int64 voxel keys (M,), integer voxel coords (M, 3)) of cells of size voxel_size."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{points.shape=} but expected (M, 3)")
    if not voxel_size > 0:
        raise ValueError(f"voxel_size={voxel_size} but expected > 0")
    ijk = torch.floor(points.detach().double() / voxel_size).long()
    if ijk.numel() and int(ijk.abs().max()) >= _KEY_HALF:
        raise ValueError(
            f"points reach {float(points.detach().abs().max()):.1f} m, beyond {_KEY_HALF} voxels of {voxel_size} m "
            "from the origin; increase voxel_size or drop far depth"
        )
    shifted = ijk + _KEY_HALF
    keys = (shifted[:, 0] << (2 * _KEY_BITS)) | (shifted[:, 1] << _KEY_BITS) | shifted[:, 2]
    return keys, ijk


def voxel_coords_from_keys(keys: torch.Tensor) -> torch.Tensor:
    """Inverse of voxel_keys' packing: keys (V,) -> integer voxel coords (V, 3)."""
    mask = (1 << _KEY_BITS) - 1
    return torch.stack([(keys >> (2 * _KEY_BITS)) & mask, (keys >> _KEY_BITS) & mask, keys & mask], 1) - _KEY_HALF


@dataclass
class VoxelSums:
    """Per-voxel sums of one or more batches of observations (linear, so batches reduce exactly in any order)."""

    keys: torch.Tensor
    """(V,) sorted unique voxel keys."""
    weight: torch.Tensor
    """(V,) sum of confidence weights w."""
    weighted: torch.Tensor
    """(V, C) sum of w * value."""
    count: torch.Tensor
    """(V,) number of observations."""

    def fused(self, eps: float = FUSION_EPS) -> torch.Tensor:
        """(V, C) the paper's fused values sum(w f) / (sum(w) + eps)."""
        return self.weighted / (self.weight[:, None] + eps)


def voxel_sums(keys: torch.Tensor, weights: torch.Tensor, values: torch.Tensor) -> tuple[VoxelSums, torch.Tensor]:
    """Scatter-add weights (M,) and weighted values (M, C) into the unique keys (M,); also returns inverse (M,)."""
    if keys.ndim != 1 or weights.shape != keys.shape or values.ndim != 2 or values.shape[0] != keys.shape[0]:
        raise ValueError(f"{keys.shape=} {weights.shape=} {values.shape=} but expected (M,), (M,), (M, C)")
    ukeys, inverse = torch.unique(keys, return_inverse=True)
    v = ukeys.shape[0]
    wsum = torch.zeros(v, dtype=weights.dtype, device=weights.device).index_add(0, inverse, weights)
    wval = torch.zeros(v, values.shape[1], dtype=values.dtype, device=values.device).index_add(
        0, inverse, values * weights[:, None]
    )
    count = torch.bincount(inverse, minlength=v)
    return VoxelSums(ukeys, wsum, wval, count), inverse


def merge_voxel_sums(parts: Sequence[VoxelSums]) -> VoxelSums:
    """Reduce several VoxelSums (e.g. one per frame) into one; exact since sums are linear."""
    if not parts:
        raise ValueError("no observations to fuse")
    keys = torch.cat([p.keys for p in parts])
    ukeys, inverse = torch.unique(keys, return_inverse=True)
    v = ukeys.shape[0]
    weight = torch.zeros(v, dtype=parts[0].weight.dtype).index_add(0, inverse, torch.cat([p.weight for p in parts]))
    weighted = torch.zeros(v, parts[0].weighted.shape[1], dtype=parts[0].weighted.dtype).index_add(
        0, inverse, torch.cat([p.weighted for p in parts])
    )
    count = torch.zeros(v, dtype=torch.long).index_add(0, inverse, torch.cat([p.count for p in parts]))
    return VoxelSums(ukeys, weight, weighted, count)


def fuse_voxels(
    points: torch.Tensor, weights: torch.Tensor, features: torch.Tensor, voxel_size: float, eps: float = FUSION_EPS
) -> tuple[torch.Tensor, torch.Tensor, VoxelSums, torch.Tensor]:
    """The paper's voxel fusion of observations x (M, 3) with confidences w (M,) and features f (M, C).

    Returns (p (V, 3), f_vox (V, C), sums, inverse (M,)) with f_vox = sum(w f) / (sum(w) + eps) and
    p = sum(w x) / (sum(w) + eps) over the observations falling in each occupied voxel of size voxel_size.
    Differentiable with respect to weights, points and features.
    """
    keys, _ = voxel_keys(points, voxel_size)
    sums, inverse = voxel_sums(keys, weights, torch.cat([points, features], 1))
    fused = sums.fused(eps)
    return fused[:, :3], fused[:, 3:], sums, inverse


def bbox_extent(points: np.ndarray) -> list[float]:
    """(N, 3) points -> [dx, dy, dz] of their bounding box (zeros when empty)."""
    return (points.max(0) - points.min(0)).astype(float).tolist() if len(points) else [0.0, 0.0, 0.0]
