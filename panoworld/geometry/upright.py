"""Rotations of upright (gravity-aligned) cameras about the vertical axis (camera y, down)."""

from __future__ import annotations

import numpy as np


def yaw_matrix(yaw: float) -> np.ndarray:
    """(3, 3) rotation about the camera y axis (gravity, down) by yaw radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def yaw_matrix_xz(yaw: float | np.ndarray) -> np.ndarray:
    """(..., 2, 2) yaw_matrix acting on (x, z) alone: [[c, s], [-s, c]] (yaw radians, scalar or array)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)


def wrap_angle(a: float | np.ndarray) -> np.ndarray:
    """Angles (radians) wrapped into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def yaw_of(R: np.ndarray) -> float:
    """The yaw (radians) of the rotation about y nearest to R (3, 3)."""
    return float(np.arctan2(R[0, 2] - R[2, 0], R[0, 0] + R[2, 2]))
