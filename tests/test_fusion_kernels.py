"""fusion_kernels against their numpy/torch oracles (frame_observations' numpy, geometry.voxels.voxel_sums / merge_voxel_sums): bit for bit."""

import numpy as np
import pytest
import torch

from panoworld.gaussians.fusion import Observations, _moment_values
from panoworld.gaussians.fusion_kernels import frame_moment_sums, merge_sums
from panoworld.geometry.voxels import merge_voxel_sums, voxel_keys, voxel_sums


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
    _assert_equal(merge_sums(parts[:1]), _as_tuple(merge_voxel_sums([_torch_sums(frames[0], 0.05)])))


def test_far_points_refused_like_voxel_keys():
    pts = np.array([[0.0, 0.0, 0.0], [1e6, 0.0, 0.0]])
    with pytest.raises(ValueError, match="beyond"):
        voxel_keys(torch.from_numpy(pts), 0.02)
    with pytest.raises(ValueError, match="beyond"):
        frame_moment_sums(pts, np.zeros((2, 3)), np.zeros((2, 2, 3)), np.ones(2), 0.02)


def _frame_points_reference(depth, dirs, world_from_cam, max_depth):
    """frame_observations' numpy before the kernel: the kernel's oracle."""
    d = depth.astype(np.float64)
    valid = np.isfinite(d) & (d > 0)
    if max_depth > 0:
        valid &= d <= max_depth
    pts = np.where(valid[..., None], dirs * np.where(valid, d, 0.0)[..., None], np.nan)
    px = np.flatnonzero(valid)
    return pts, px, np.einsum("mi,ji->mj", pts.reshape(-1, 3)[px], world_from_cam[:3, :3]) + world_from_cam[:3, 3]


@pytest.mark.parametrize("max_depth", [0.0, 4.0])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_frame_points_equal_numpy_bitwise(max_depth, dtype):
    from scipy.spatial.transform import Rotation

    from panoworld.core.conventions import erp_dirs
    from panoworld.gaussians.fusion_kernels import frame_points

    rng = np.random.default_rng(2)
    depth = rng.uniform(0.3, 8.0, (64, 128)).astype(dtype)
    depth[rng.random(depth.shape) < 0.1] = 0.0
    depth[rng.random(depth.shape) < 0.05] = np.nan
    depth[rng.random(depth.shape) < 0.05] = np.inf
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [0.3, -1.2, 0.7]).as_matrix()
    pose[:3, 3] = [1.5, -0.2, 3.1]
    dirs = erp_dirs(64, 128, dtype=np.float64)
    ours = frame_points(depth, dirs, pose, max_depth)
    ref = _frame_points_reference(depth, dirs, pose, max_depth)
    assert 0 < len(ref[1]) < depth.size
    for a, b in zip(ours, ref):
        assert a.shape == b.shape and a.dtype == b.dtype
        assert np.array_equal(a, b, equal_nan=True)


def test_frame_footprints_equal_numpy_bitwise():
    from panoworld.core.conventions import erp_dirs
    from panoworld.gaussians.fusion import _neighbour_steps
    from panoworld.gaussians.fusion_kernels import frame_footprints, frame_points

    rng = np.random.default_rng(4)
    h, w = 48, 96
    depth = rng.uniform(0.5, 6.0, (h, w))
    depth[:, 20:40] = 2.0  # smooth stretches beside rough ones: steps of equal length both ways
    depth[rng.random(depth.shape) < 0.15] = 0.0
    dirs = erp_dirs(h, w, dtype=np.float64)
    pts, px, _ = frame_points(depth, dirs, np.eye(4))
    a, b, area, cos = frame_footprints(pts, px, dirs)
    a0, b0 = _neighbour_steps(pts, px)  # frame_observations' numpy before the kernel
    normal = np.cross(a0, b0)
    area0 = np.linalg.norm(normal, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos0 = np.abs(np.einsum("mc,mc->m", normal, dirs.reshape(-1, 3)[px])) / area0
    assert (px < w).any() and (px >= (h - 1) * w).any()  # both poles' rows, where one latitude step is missing
    for x, y in ((a, a0), (b, b0), (area, area0), (cos, cos0)):
        assert np.array_equal(x, y, equal_nan=True)
