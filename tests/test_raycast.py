"""Raycaster.cast: the two-thread split gives every ray the result a one-thread cast gives it."""

from __future__ import annotations

import numpy as np

from panoworld.geometry import raycast
from panoworld.geometry.raycast import Raycaster


def test_split_cast_equals_one_thread_cast():
    rng = np.random.default_rng(3)
    n = 4000
    centres = rng.normal(size=(n, 3))
    centres *= 3.0 / np.linalg.norm(centres, axis=1, keepdims=True)
    tris = (centres[:, None, :] + rng.normal(size=(n, 3, 3)) * 0.3).reshape(-1, 3).astype(np.float32)
    rc = Raycaster(tris, np.arange(3 * n).reshape(n, 3))
    m = 3 * raycast.PARALLEL_MIN_RAYS + 7  # odd: the halves differ in length
    dirs = rng.normal(size=(m, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = rng.uniform(-0.2, 0.2, (m, 3))
    split = rc.cast(origins, dirs, chunk=5000)  # chunks that straddle the halves' boundary
    step = raycast.PARALLEL_MIN_RAYS - 1  # below the threshold: each piece traced on the calling thread alone
    pieces = [rc.cast(origins[s:s + step], dirs[s:s + step]) for s in range(0, m, step)]
    hit = split.face >= 0
    assert 0.2 < hit.mean() < 0.95  # both hits and misses are exercised
    np.testing.assert_array_equal(split.face, np.concatenate([p.face for p in pieces]))
    np.testing.assert_array_equal(split.distance, np.concatenate([p.distance for p in pieces]))
    np.testing.assert_array_equal(split.bary, np.concatenate([p.bary for p in pieces]))
    assert np.isinf(split.distance[~hit]).all() and (split.bary[~hit] == 0).all()
