"""Umeyama Sim(3)/SE(3) alignment of camera trajectories and trajectory error metrics (ATE, RPE, RRE, RTE)."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import check_poses
from panoworld.core.shapes import check_shape


def _check_points(src: np.ndarray, dst: np.ndarray) -> None:
    check_shape("dst", dst, "N 3", dims=check_shape("src", src, "N 3"))
    if len(src) < 1:
        raise ValueError("cannot align empty point sets")


def _rotation_from_correlation(M: np.ndarray) -> np.ndarray:
    """The rotation R maximising trace(R^T M) (closest proper rotation, det = +1)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ D @ Vt


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (Umeyama 1991): (s, R (3, 3), t (3,)) minimising sum |dst - (s R src + t)|^2.

    src, dst: corresponding points (N, 3). with_scale=False fixes s = 1 (SE(3)). For fewer than three
    non-collinear points the rotation about their common line is not determined (SVD picks one).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    _check_points(src, dst)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def sim3_matrix(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 matrix of x -> s R x + t."""
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(R)
    T[:3, 3] = t
    return T


def apply_sim3(s: float, R: np.ndarray, t: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Move world_from_cam poses (N, 4, 4) by the similarity new_from_old = (s, R, t); results stay rigid.

    Rotations become R R_i and camera centres s R c_i + t (the camera frame itself is not scaled).
    """
    poses = check_poses(poses)
    out = np.repeat(np.eye(4)[None], len(poses), axis=0)
    out[:, :3, :3] = np.asarray(R)[None] @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ np.asarray(R).T + t
    return out


def _spans_a_plane(points: np.ndarray, rel_tol: float = 1e-3) -> bool:
    """Whether centred points (N, 3) are far from collinear (their 2nd singular value is not negligible)."""
    if len(points) < 3:
        return False
    sv = np.linalg.svd(points - points.mean(0), compute_uv=False)
    return bool(sv[0] > 0 and sv[1] > rel_tol * sv[0])


def align_trajectory(
    est: np.ndarray, gt: np.ndarray, sim3: bool = True, rotation_weight: float = 0.0
) -> tuple[np.ndarray, tuple[float, np.ndarray, np.ndarray]]:
    """Align estimated world_from_cam poses est (N, 4, 4) to gt (N, 4, 4): -> (aligned (N, 4, 4), (s, R, t)).

    rotation_weight = 0: Umeyama on camera centres (the evaluation protocol of the paper). If the gt centres are
    collinear the rotation about their line is unobservable from positions, so the camera orientations are used
    as well (as with rotation_weight = 1). rotation_weight > 0: R maximises
    trace(R^T (C_pos / (sigma_est sigma_gt) + w mean_i(R_gt_i R_est_i^T))), the normalised Umeyama
    correlation plus w times the orientation correlation, then s and t are Umeyama's given R. Exact data
    is recovered exactly either way. sim3=False fixes s = 1.
    """
    est = check_poses(est, "est")
    gt = check_poses(gt, "gt")
    check_shape("gt", gt, "N 4 4", dims={"N": len(est)})
    c_est, c_gt = est[:, :3, 3], gt[:, :3, 3]
    if rotation_weight <= 0 and _spans_a_plane(c_gt):
        s, R, t = umeyama(c_est, c_gt, with_scale=sim3)
        return apply_sim3(s, R, t, est), (s, R, t)
    w = rotation_weight if rotation_weight > 0 else 1.0
    xs, xd = c_est - c_est.mean(0), c_gt - c_gt.mean(0)
    sig_s, sig_d = np.sqrt((xs**2).sum(1).mean()), np.sqrt((xd**2).sum(1).mean())
    M = w * np.einsum("nij,nkj->ik", gt[:, :3, :3], est[:, :3, :3]) / len(est)
    if sig_s > 0 and sig_d > 0:
        M = M + xd.T @ xs / len(est) / (sig_s * sig_d)
    R = _rotation_from_correlation(M)
    s = 1.0
    if sim3 and sig_s > 0:
        s = float(np.einsum("ni,ni->", xd, xs @ R.T) / (xs**2).sum())
        if s <= 0:
            # The orientations outvoted the centres so far that they point the other way: no similarity with
            # this R maps one path onto the other; fall back to Umeyama on the centres, whose scale is >= 0.
            s, R, t = umeyama(c_est, c_gt)
            return apply_sim3(s, R, t, est), (s, R, t)
    t = c_gt.mean(0) - s * R @ c_est.mean(0)
    return apply_sim3(s, R, t, est), (s, R, t)


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Geodesic angle in degrees of rotation matrices (..., 3, 3).

    atan2(|sin|, cos) from the skew part and the trace: exact near 0 and 180 degrees, where arccos of the trace
    alone loses half the digits (float noise of 1e-16 in the trace reads as 1e-6 degrees).
    """
    R = np.asarray(R, dtype=np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.linalg.norm(skew, axis=-1) / 2.0
    return np.degrees(np.arctan2(sin, cos))


def path_length(poses: np.ndarray) -> float:
    """Sum of distances between consecutive camera centres of poses (N, 4, 4), in the poses' units."""
    c = check_poses(poses)[:, :3, 3]
    return float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())


def relative_pose_errors(est: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per consecutive pair i -> i+1: E_i = (gt_i^-1 gt_{i+1})^-1 (est_i^-1 est_{i+1}) -> (|t(E_i)| (N-1,), angle(E_i) deg (N-1,)).

    Both inputs are world_from_cam (N, 4, 4) in the same units (align est first for metric RPE_t).
    """
    est, gt = check_poses(est, "est"), check_poses(gt, "gt")
    if len(est) < 2:
        return np.zeros(0), np.zeros(0)
    rel_e = np.linalg.inv(est[:-1]) @ est[1:]
    rel_g = np.linalg.inv(gt[:-1]) @ gt[1:]
    err = np.linalg.inv(rel_g) @ rel_e
    return np.linalg.norm(err[:, :3, 3], axis=1), rotation_angle_deg(err[:, :3, :3])


def trajectory_metrics(est: np.ndarray, gt: np.ndarray, sim3: bool = True) -> dict[str, float]:
    """Pose-error metrics of est against gt (both world_from_cam (N, 4, 4), gt in metres) after Umeyama alignment.

    est is first aligned to gt with align_trajectory (Sim(3) Umeyama on camera centres, or SE(3) when
    sim3=False). With e_i = |c_i(aligned est) - c_i(gt)| the camera-centre errors in metres and
    E_i = (gt_i^-1 gt_{i+1})^-1 (aligned_i^-1 aligned_{i+1}) the relative-pose error of consecutive frames:
      ate            mean_i e_i                                  (Absolute Trajectory Error, metres)
      ate_rmse       sqrt(mean_i e_i^2)                          (metres)
      rpe_t, rte     mean_i |t(E_i)|                             (Relative Translation Error, metres)
      rpe_r, rre     mean_i angle(R(E_i))                        (Relative Rotation Error, degrees)
      ate_over_path  ate / path_length(gt)                       (dimensionless; nan when gt does not move)
      rot_error_abs  mean_i angle(R_gt_i^T R_aligned_i)          (absolute orientation error, degrees)
    plus scale (the Sim(3) scale s), path_length (metres) and num_frames. The paper's RRE/RTE (video tables) are
    the relative errors between frames, the same quantities as its RPE_r/RPE_t (reconstruction tables): they do not
    grow with the path length the way an absolute error does (docs/evaluation.md).
    """
    est, gt = check_poses(est, "est"), check_poses(gt, "gt")
    check_shape("gt", gt, "N 4 4", dims={"N": len(est)})
    aligned, (s, _, _) = align_trajectory(est, gt, sim3=sim3)
    e = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    rpe_t, rpe_r = relative_pose_errors(aligned, gt)
    rot_abs = rotation_angle_deg(np.swapaxes(gt[:, :3, :3], 1, 2) @ aligned[:, :3, :3])
    length = path_length(gt)
    ate = float(e.mean())
    rte = float(rpe_t.mean()) if len(rpe_t) else 0.0
    rre = float(rpe_r.mean()) if len(rpe_r) else 0.0
    return {
        "ate": ate,
        "ate_rmse": float(np.sqrt((e**2).mean())),
        "rpe_t": rte,
        "rpe_r": rre,
        "rre": rre,
        "rte": rte,
        "ate_over_path": ate / length if length > 0 else float("nan"),
        "rot_error_abs": float(rot_abs.mean()),
        "scale": float(s),
        "path_length": length,
        "num_frames": int(len(est)),
    }
