import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from panoworld.core.conventions import pose_from_rt
from panoworld.geometry.align import (
    align_trajectory,
    apply_sim3,
    path_length,
    relative_pose_errors,
    trajectory_metrics,
    umeyama,
)


def random_trajectory(n: int, seed: int, planar: bool = False) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = np.cumsum(rng.normal(scale=0.2, size=(n, 3)), axis=0)
    if planar:
        centres[:, 1] = 0.0
    rots = Rotation.from_rotvec(rng.normal(scale=0.5, size=(n, 3))).as_matrix()
    return np.stack([pose_from_rt(r, c) for r, c in zip(rots, centres)])


def straight_line(n: int) -> np.ndarray:
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 2, 3] = np.linspace(0.0, 2.0, n)
    yaw = Rotation.from_euler("y", np.linspace(0, 40, n)[:, None], degrees=True).as_matrix()
    poses[:, :3, :3] = yaw
    return poses


def test_umeyama_recovers_known_sim3():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = Rotation.random(random_state=1).as_matrix()
    s, t = 2.7, np.array([1.0, -2.0, 0.5])
    dst = s * src @ R.T + t
    s2, R2, t2 = umeyama(src, dst)
    assert s2 == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)


def test_umeyama_without_scale_is_rigid_and_handles_reflection_case():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    R = Rotation.random(random_state=3).as_matrix()
    dst = 3.0 * src @ R.T  # scaled: the rigid fit must still return a proper rotation and s = 1
    s, R2, _ = umeyama(src, dst, with_scale=False)
    assert s == 1.0
    assert np.linalg.det(R2) == pytest.approx(1.0)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    mirrored = src * np.array([1.0, 1.0, -1.0])
    _, Rm, _ = umeyama(src, mirrored)
    assert np.linalg.det(Rm) == pytest.approx(1.0)


def test_umeyama_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"src.shape=\(4, 2\) but expected \(N, 3\)"):
        umeyama(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"dst.shape=\(5, 3\) but expected \(4, 3\)"):
        umeyama(np.zeros((4, 3)), np.zeros((5, 3)))


@pytest.mark.parametrize("make", [lambda: random_trajectory(30, 4), lambda: straight_line(12)])
def test_align_trajectory_recovers_sim3_of_poses(make):
    gt = make()
    R = Rotation.random(random_state=5).as_matrix()
    s, t = 0.37, np.array([3.0, 1.0, -4.0])
    est = apply_sim3(s, R, t, gt)  # est = gt expressed in a scaled, rotated, shifted world
    aligned, (s2, R2, t2) = align_trajectory(est, gt)
    np.testing.assert_allclose(aligned, gt, atol=1e-9)
    assert s2 == pytest.approx(1 / s, rel=1e-9)
    np.testing.assert_allclose(R2, R.T, atol=1e-9)


def test_straight_line_rotation_about_the_line_comes_from_orientations():
    gt = straight_line(10)
    roll = Rotation.from_euler("z", 70, degrees=True).as_matrix()  # about the line of motion (z)
    est = apply_sim3(2.0, roll, np.zeros(3), gt)
    aligned, _ = align_trajectory(est, gt)
    np.testing.assert_allclose(aligned[:, :3, :3], gt[:, :3, :3], atol=1e-9)


def test_rotation_weighted_alignment_is_exact_on_exact_data():
    gt = random_trajectory(15, 6)
    R = Rotation.random(random_state=7).as_matrix()
    est = apply_sim3(4.0, R, np.array([0.1, 0.2, 0.3]), gt)
    aligned, (s, _, _) = align_trajectory(est, gt, rotation_weight=1.0)
    np.testing.assert_allclose(aligned, gt, atol=1e-9)
    assert s == pytest.approx(0.25)


def test_rotation_weighted_alignment_never_gives_a_negative_scale():
    # Orientations agree exactly while the centres run the other way (a pose model that got the path backwards):
    # the joint fit's rotation would need a negative scale; the fit falls back to Umeyama on the centres.
    gt = random_trajectory(12, 3)
    est = gt.copy()
    est[:, :3, 3] = 2.0 * gt[:, :3, 3].mean(0) - gt[:, :3, 3]
    _, (s, R, t) = align_trajectory(est, gt, rotation_weight=1.0)
    assert s > 0
    s_u, R_u, t_u = umeyama(est[:, :3, 3], gt[:, :3, 3])
    assert s == pytest.approx(s_u) and np.allclose(R, R_u) and np.allclose(t, t_u)


def test_metrics_zero_on_identical_and_similar_trajectories():
    gt = random_trajectory(25, 8)
    m = trajectory_metrics(gt, gt)
    for k in ("ate", "ate_rmse", "rpe_t", "rpe_r", "rre", "rte"):
        assert m[k] == pytest.approx(0.0, abs=1e-6), k
    est = apply_sim3(3.0, Rotation.random(random_state=9).as_matrix(), np.ones(3), gt)
    m = trajectory_metrics(est, gt)
    assert m["ate"] < 1e-9 and m["rpe_r"] < 1e-5 and m["scale"] == pytest.approx(1 / 3)
    assert m["path_length"] == pytest.approx(path_length(gt))


def test_metrics_known_values_for_a_translation_perturbation():
    # gt: 5 frames along x at 1 m spacing. est: frame 2 displaced by d along y (perpendicular, inside the plane
    # z=0 spanned by the path and the offset). SE(3) alignment of this symmetric set: the centroid moves by d/5 in y.
    n, d = 5, 0.1
    gt = np.repeat(np.eye(4)[None], n, axis=0)
    gt[:, 0, 3] = np.arange(n)
    gt[:, 1, 3] = [0.0, 0.5, 0.0, 0.5, 0.0]  # zig-zag so the centres span a plane
    est = gt.copy()
    est[2, 1, 3] += d
    m = trajectory_metrics(est, gt, sim3=False)
    aligned, _ = align_trajectory(est, gt, sim3=False)
    e = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert m["ate"] == pytest.approx(e.mean())
    assert m["ate_rmse"] == pytest.approx(np.sqrt((e**2).mean()))
    assert m["ate"] < d  # alignment spreads the error
    # Unaligned RPE: only pairs (1,2) and (2,3) see the displacement, each by exactly d.
    rpe_t, rpe_r = relative_pose_errors(est, gt)
    np.testing.assert_allclose(rpe_t, [0.0, d, d, 0.0], atol=1e-12)
    np.testing.assert_allclose(rpe_r, 0.0, atol=1e-6)
    assert m["ate_over_path"] == pytest.approx(m["ate"] / path_length(gt))


def test_metrics_known_values_for_a_rotation_perturbation():
    n = 6
    gt = straight_line(n)
    est = gt.copy()
    est[3, :3, :3] = est[3, :3, :3] @ Rotation.from_euler("y", 2.0, degrees=True).as_matrix()
    rpe_t, rpe_r = relative_pose_errors(est, gt)
    np.testing.assert_allclose(rpe_r, [0, 0, 2.0, 2.0, 0], atol=1e-9)
    # Camera 3 turned in place about its vertical axis, which is perpendicular to the step 3 -> 4: the relative
    # translation seen from camera 3 turns by 2 degrees, an error of 2 sin(1 deg) * step.
    step = 2.0 / (n - 1)
    assert rpe_t[3] == pytest.approx(2 * np.sin(np.radians(1.0)) * step, rel=1e-9)
    # Centres that span a plane: Umeyama ignores orientations, so only RRE sees the rotated camera.
    gt = random_trajectory(n, 10)
    est = gt.copy()
    est[3, :3, :3] = est[3, :3, :3] @ Rotation.from_euler("x", 2.0, degrees=True).as_matrix()
    m = trajectory_metrics(est, gt)
    assert m["ate"] == pytest.approx(0.0, abs=1e-12)
    assert m["rot_error_abs"] == pytest.approx(2.0 / n, rel=1e-9)
    assert m["rre"] == pytest.approx(2 * 2.0 / (n - 1), rel=1e-9)  # pairs (2, 3) and (3, 4) each see 2 degrees


@pytest.mark.parametrize("scale", [1.0, 2.5])
def test_rre_rte_match_hand_computed_values(scale):
    # gt: 7 upright cameras on a zig-zag (centres span a plane, so Umeyama on centres is exact), steps d_i.
    # est: the same centres (times `scale`, moved and turned by a similarity) with camera k yawed by theta in place.
    # Relative errors of consecutive pairs, by hand: pair (k-1, k) rotation theta, translation 0 (the step is seen
    # from the unrotated camera k-1); pair (k, k+1) rotation theta, translation |R_y(theta)^T d_k - d_k| =
    # 2 |d_k| sin(theta / 2) (d_k horizontal, perpendicular to the yaw axis); every other pair 0.
    n, k, theta = 7, 3, 5.0
    gt = np.repeat(np.eye(4)[None], n, axis=0)
    gt[:, 0, 3] = np.arange(n) * 0.3
    gt[:, 2, 3] = [0.0, 0.1, 0.0, 0.2, 0.0, 0.1, 0.0]
    est = gt.copy()
    est[k, :3, :3] = Rotation.from_euler("y", theta, degrees=True).as_matrix()
    est = apply_sim3(scale, Rotation.from_euler("xyz", [10, 40, -20], degrees=True).as_matrix(), np.array([1, 2, 3.0]), est)
    m = trajectory_metrics(est, gt)
    d_k = np.linalg.norm(gt[k + 1, :3, 3] - gt[k, :3, 3])
    assert m["ate"] == pytest.approx(0.0, abs=1e-12)
    assert m["rre"] == pytest.approx(2 * theta / (n - 1), rel=1e-9)
    assert m["rte"] == pytest.approx(2 * d_k * np.sin(np.radians(theta / 2)) / (n - 1), rel=1e-9)
    assert m["scale"] == pytest.approx(1 / scale, rel=1e-12)
    # The same local error on every step scaled 4x (stride 4): RRE is unchanged and RTE scales with the step
    # (metres), so it stays comparable with ATE across strides, unlike ATE / path length.
    long_gt, long_est = gt.copy(), est.copy()
    long_gt[:, :3, 3] *= 4
    long_est[:, :3, 3] *= 4
    m4 = trajectory_metrics(long_est, long_gt)
    assert m4["rre"] == pytest.approx(m["rre"], rel=1e-9)
    assert m4["rte"] == pytest.approx(4 * m["rte"], rel=1e-9)  # metres: the steps are 4x longer


def test_trajectory_shape_errors_are_self_describing():
    with pytest.raises(ValueError, match=r"est.shape=\(3, 3, 4\) but expected \(N, 4, 4\)"):
        trajectory_metrics(np.zeros((3, 3, 4)), np.zeros((3, 4, 4)))
    with pytest.raises(ValueError, match="NaN"):
        align_trajectory(np.full((3, 4, 4), np.nan), np.zeros((3, 4, 4)))


def test_one_pose_checker_for_metrics_and_trajectory_files(tmp_path):
    """align (metrics) and trajectory files share conventions.check_poses: same rigidity rule and tolerance."""
    from panoworld.core.conventions import POSE_RIGID_TOL, check_poses
    from panoworld.io.trajectory import TrajectoryFileError, read_trajectory_file

    good = np.tile(np.eye(4), (3, 1, 1))
    good[1, :3, :3] = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix()
    near = good.copy()
    near[2, :3, :3] *= 1 + 0.4 * POSE_RIGID_TOL  # inside the tolerance: float32 / rounded storage
    scaled = good.copy()
    scaled[2, :3, :3] *= 1 + 3 * POSE_RIGID_TOL
    np.testing.assert_array_equal(check_poses(near), near)
    path = tmp_path / "t.json"
    path.write_text(json.dumps(near.tolist()))
    assert trajectory_metrics(read_trajectory_file(path), good)["ate"] < 1e-3
    with pytest.raises(ValueError, match="est: pose 2 is not a rigid"):
        trajectory_metrics(scaled, good)
    path.write_text(json.dumps(scaled.tolist()))
    with pytest.raises(TrajectoryFileError, match="t.json: pose 2 is not a rigid"):
        read_trajectory_file(path)
    reflected = good.copy()
    reflected[0, 0, 0] = -1
    with pytest.raises(ValueError, match="gt: pose 0 is not a rigid"):
        trajectory_metrics(good, reflected)
