"""Differentiable rotations in torch (the numpy ones live in panoworld/core/conventions.py)."""

from __future__ import annotations

import torch


def rotmat_from_quat(q: torch.Tensor) -> torch.Tensor:
    """Quaternions (..., 4) in (w, x, y, z) order, normalised here -> rotation matrices (..., 3, 3); differentiable."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, -1).reshape(q.shape[:-1] + (3, 3))
