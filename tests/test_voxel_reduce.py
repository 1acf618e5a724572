"""voxel_reduce's numba sums against their torch oracle (gaussians.voxel_sums / merge_voxel_sums): equal bit for bit."""

import numpy as np
import pytest
import torch

from panoworld.gaussians import Observations, _moment_values, merge_voxel_sums, voxel_keys, voxel_sums
from panoworld.voxel_reduce import frame_moment_sums, merge_sums


def _observations(rng, m, spread):
    pts = rng.normal(size=(m, 3)) * spread + rng.normal(size=3) * 3
    return Observations(torch.from_numpy(pts), torch.from_numpy(rng.random((m, 3))),
                        torch.from_numpy(rng.normal(size=(m, 2, 3)) * 0.01), torch.from_numpy(rng.random(m) * 5))


def _torch_sums(obs, voxel_size):
    keys, ijk = voxel_keys(obs.points, voxel_size)
    centre = (ijk.double() + 0.5) * voxel_size
    return voxel_sums(keys, obs.weights, _moment_values(obs, centre))[0]


def _as_tuple(s):
    return s.keys.numpy(), s.weight.numpy(), s.weighted.numpy(), s.count.numpy()


def _assert_equal(a, b):
    assert len(a) == len(b) == 4
    for x, y in zip(a, b):
        assert x.shape == y.shape and x.dtype == y.dtype
        assert np.array_equal(x, y)  # bit for bit: the same products summed in the same order


@pytest.mark.parametrize("voxel_size", [0.04, 0.1])
def test_frame_sums_equal_torch_bitwise(voxel_size):
    rng = np.random.default_rng(0)
    obs = _observations(rng, 20000, 0.08)  # many observations per voxel: the summation order shows
    ours = frame_moment_sums(obs.points.numpy(), obs.colors.numpy(), obs.steps.numpy(), obs.weights.numpy(),
                             voxel_size)
    ref = _as_tuple(_torch_sums(obs, voxel_size))
    assert len(ref[0]) < 20000 / 4
    _assert_equal(ours, ref)


def test_merge_equals_torch_bitwise():
    rng = np.random.default_rng(1)
    frames = [_observations(rng, int(rng.integers(1, 5000)), 0.2) for _ in range(7)]
    ref = merge_voxel_sums([_torch_sums(o, 0.05) for o in frames])
    ours = merge_sums([frame_moment_sums(o.points.numpy(), o.colors.numpy(), o.steps.numpy(), o.weights.numpy(), 0.05)
                       for o in frames])
    _assert_equal(ours, _as_tuple(ref))
    # merging in groups (voxel_fusion merges every MERGE_EVERY frames) is the same left fold
    parts = [frame_moment_sums(o.points.numpy(), o.colors.numpy(), o.steps.numpy(), o.weights.numpy(), 0.05)
             for o in frames]
    _assert_equal(merge_sums([merge_sums(parts[:3]), *parts[3:]]), ours)


def test_far_points_refused_like_voxel_keys():
    pts = np.array([[0.0, 0.0, 0.0], [1e6, 0.0, 0.0]])
    with pytest.raises(ValueError, match="beyond"):
        voxel_keys(torch.from_numpy(pts), 0.02)
    with pytest.raises(ValueError, match="beyond"):
        frame_moment_sums(pts, np.zeros((2, 3)), np.zeros((2, 2, 3)), np.ones(2), 0.02)
