"""Depth-consistency pose refinement (models/pose_refine.py) against exact synthetic geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from panoworld.core.conventions import erp_dirs
from panoworld.models.pose_refine import depth_edges, refine_relative_poses, refine_sequence, sample_range, so3_exp


@pytest.fixture(scope="module")
def track():
    """Four frames of a ci-tiny synthetic track at 32x64: GT ray depth (4, 32, 64) and cam0_from_cam (4, 4, 4)."""
    from panoworld.tools.synth.generate import generate_scene

    scene = generate_scene(3, "ci-tiny")
    poses = scene.tracks[0].world_from_cam
    idx = np.round(np.linspace(0, len(poses) - 1, 4)).astype(int)
    depth = np.stack([scene.render(poses[i], 32, 64)[1] for i in idx])
    assert np.isfinite(depth).all()
    rel = np.linalg.inv(poses[idx[0]]) @ poses[idx]
    return torch.from_numpy(depth), torch.from_numpy(rel)


def yaw(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    m = np.eye(4)
    m[[0, 0, 2, 2], [0, 2, 0, 2]] = [np.cos(a), np.sin(a), -np.sin(a), np.cos(a)]
    return m


def errors(pred: torch.Tensor, gt: torch.Tensor) -> tuple[float, float]:
    """Largest translation error (m) and rotation error (deg) over the frames."""
    dt = (pred[:, :3, 3] - gt[:, :3, 3]).norm(dim=-1).max().item()
    rel = pred[:, :3, :3].transpose(1, 2) @ gt[:, :3, :3]
    cos = ((torch.diagonal(rel, dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)
    return dt, float(np.rad2deg(torch.arccos(cos).max().item()))


def test_so3_exp_matches_rodrigues_and_is_a_rotation():
    w = torch.tensor([[0.0, 0.3, 0.0], [0.1, -0.2, 0.4], [0.0, 0.0, 0.0]], dtype=torch.float64)
    R = so3_exp(w)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(3, 3, 3), atol=1e-12)
    assert torch.allclose(R[0], torch.from_numpy(yaw(np.rad2deg(0.3))[:3, :3]), atol=1e-12)
    assert torch.allclose(R[2], torch.eye(3, dtype=torch.float64))


def test_sample_range_reads_back_the_depth_of_every_pixel_ray_across_the_seam():
    h, w = 16, 32
    depth = torch.from_numpy(1.0 + np.random.default_rng(0).random((1, h, w)))
    pts = torch.from_numpy(erp_dirs(h, w, dtype=np.float64)).reshape(1, -1, 3) * depth.reshape(1, -1, 1) * 2.0
    r, d = sample_range(depth, pts)
    assert torch.allclose(r, 2.0 * depth.reshape(1, -1), atol=1e-9)
    assert torch.allclose(d, depth.reshape(1, -1), atol=1e-9)
    # exactly on the seam (lon = +-pi): the mean of the first and last columns, not the border value
    seam = torch.tensor([[[0.0, 0.0, -1.0]]], dtype=torch.float64)
    row = (h - 1) // 2, h // 2
    expect = depth[0, list(row)][:, [0, -1]].mean()
    assert torch.allclose(sample_range(depth, seam)[1], expect.reshape(1, 1), atol=1e-9)


def test_refine_recovers_perturbed_poses_from_exact_depth(track):
    depth, gt = track
    noisy = gt.clone()
    rng = np.random.default_rng(1)
    for i in range(1, len(gt)):
        noisy[i] = torch.from_numpy(yaw(rng.uniform(-6, 6))) @ noisy[i]
        noisy[i, :3, 3] += torch.from_numpy(rng.uniform(-0.2, 0.2, 3))
    before = errors(noisy[1:], gt[1:])
    assert before[0] > 0.1
    out = refine_sequence(noisy, depth, edge=0.1, sweeps=4)  # coordinate descent: more sweeps, tighter
    assert torch.equal(out[0], noisy[0])
    dt, dr = errors(out[1:], gt[1:])
    assert dt < 0.005 and dr < 0.3, (before, (dt, dr))
    dt, dr = errors(refine_sequence(gt, depth, edge=0.1, sweeps=4)[1:], gt[1:])
    assert dt < 0.005 and dr < 0.3, "the ground truth should be (nearly) a fixed point"
    # without the edge mask, bilinear lookups across depth edges bias the optimum (by centimetres at 32x64)
    dt_blend, _ = errors(refine_sequence(noisy, depth, sweeps=4)[1:], gt[1:])
    assert dt < dt_blend < 0.06


def test_refine_absorbs_a_depth_scale_error_of_the_other_frame(track):
    depth, gt = track
    start = gt[1:].clone()
    start[:, :3, 3] *= 0.6  # a head that shrinks the translations
    out = refine_relative_poses(start, depth[:1].expand(3, -1, -1), depth[1:] * 1.25, edge=0.1)
    dt, dr = errors(out, gt[1:])
    assert dt < 0.005 and dr < 0.3, (dt, dr)


def test_invalid_depth_pixels_are_ignored_at_any_resolution(track):
    depth, gt = track
    holes = depth.clone()
    holes[1:, :4] = float("inf")  # nothing hit (a renderer's sky), a sensor's zero band, NaN
    holes[1:, -3:] = 0.0
    holes[2, 10:12, 20:30] = float("nan")
    start = gt[1:].clone()
    start[:, :3, 3] += 0.1
    for d in (holes, torch.nn.functional.interpolate(holes[:, None], scale_factor=4, mode="nearest")[:, 0]):
        out = refine_relative_poses(start, d[:1].expand(3, -1, -1), d[1:], edge=0.1, max_height=32)
        assert torch.isfinite(out).all()
        dt, dr = errors(out, gt[1:])
        assert dt < 0.01 and dr < 0.3, (d.shape, dt, dr)


def test_depth_edges_flag_discontinuities_and_wrap_across_the_seam():
    d = torch.full((1, 8, 16), 2.0, dtype=torch.float64)
    d[..., 0] = 4.0  # a step between column 0 and its neighbours 1 and 15 (across the seam)
    e = depth_edges(d)
    np.testing.assert_allclose(e[0, :, [15, 0, 1]].numpy(), np.log(2.0), atol=1e-12)
    assert torch.all(e[0, :, 2:15] == 0)


def test_refine_checks_shapes():
    eye = torch.eye(4, dtype=torch.float64)[None].repeat(2, 1, 1)
    d = torch.ones(2, 8, 16)
    with pytest.raises(ValueError, match=r"ref_from_cam.shape\)=\(2, 4\) but expected \(B, 4, 4\)"):
        refine_relative_poses(eye[:, 0], d, d)
    with pytest.raises(ValueError, match="expected both"):
        refine_relative_poses(eye, d, d[:1])
    with pytest.raises(ValueError, match=r"expected \(S, 4, 4\), \(S, H, W\)"):
        refine_sequence(eye, d[:1])
