"""A room of random surfels around the origin: the density of a voxel-fused indoor scene, for render benches and tests."""

from __future__ import annotations

import numpy as np

from panoworld.io.gaussian_set import Gaussians

ROOM_HALF_M = (3.0, 1.5, 3.0)
"""Half extents of the room (x, y, z), metres: a 6 x 3 x 6 m room centred on the origin."""


def room_surfels(n: int, seed: int = 0) -> Gaussians:
    """n Gaussians on the walls, floor and ceiling of the room (scales 1-4 cm, random rotations, opacity 0.5-1,
    random colours), numpy float32."""
    rng = np.random.default_rng(seed)
    half = np.array(ROOM_HALF_M)
    pts = rng.uniform(-1, 1, (n, 3)) * half
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = rng.choice([-1.0, 1.0], n) * half[axis]
    return Gaussians(
        means=pts.astype(np.float32), scales=rng.uniform(0.01, 0.04, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32), opacities=rng.uniform(0.5, 1, n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
    )
