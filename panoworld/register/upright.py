"""Two-view geometry of upright (gravity-aligned) panoramas from bearing vectors alone: yaw and translation by RANSAC on
the upright essential matrix, least-squares refinement, metric scale from the depths that agree, and the longest
baseline the floor allows."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from panoworld.geometry.upright import yaw_matrix


@dataclass(kw_only=True)
class UprightPose:
    """i_from_j of two upright panoramas up to scale, and the matches that support it."""

    yaw: float
    """Rotation of camera j in camera i about the camera y axis (gravity), radians."""
    t: np.ndarray
    """(3,) unit direction from camera i to camera j in camera i's frame."""
    inliers: np.ndarray
    """(M,) bool over the matches: epipolar angle below the threshold and in front of both cameras."""
    max_baseline_m: float = math.inf
    """The longest baseline that keeps the matched points above the floor (max_baseline; inf: not bounded)."""

    def i_from_j(self, scale: float = 1.0) -> np.ndarray:
        """(4, 4) rigid transform with the translation scaled to `scale` metres."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = yaw_matrix(self.yaw), scale * self.t
        return T


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def epipolar_angles(E: np.ndarray, xi: np.ndarray, xj: np.ndarray) -> np.ndarray:
    """(N,) radians: for unit bearings xi, xj (N, 3) the larger angle of either ray to its epipolar plane under E
    (xi^T E xj = 0 for a perfect match). E (3, 3) or a stack (K, 3, 3) -> (K, N)."""
    nj = xj @ np.swapaxes(E, -1, -2)  # E xj: normal of the epipolar plane in view i
    ni = xi @ E  # E^T xi: normal in view j
    dot = np.abs(np.einsum("...nk,nk->...n", nj, xi))
    ai = dot / np.maximum(np.linalg.norm(nj, axis=-1), 1e-12)
    aj = dot / np.maximum(np.linalg.norm(ni, axis=-1), 1e-12)
    return np.arcsin(np.clip(np.maximum(ai, aj), 0.0, 1.0))


def _hypotheses(xi: np.ndarray, xj: np.ndarray, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upright essential matrices with a horizontal baseline from 3-match samples (K, 3) -> (yaw (K,), t (K, 3)).
    With t = (tx, 0, tz): xi^T E xj is linear in (E01, E10, E12, E21) = (-tz, tz c + tx s, tz s - tx c, tx)."""
    a, b = xi[samples], xj[samples]  # (K, 3, 3)
    rows = np.stack([a[..., 0] * b[..., 1], a[..., 1] * b[..., 0], a[..., 1] * b[..., 2], a[..., 2] * b[..., 1]], -1)
    p = np.linalg.svd(rows, full_matrices=True)[2][:, -1]  # (K, 4) null vectors
    tx, tz = p[:, 3], -p[:, 0]
    n2 = np.maximum(tx**2 + tz**2, 1e-12)
    c = (tz * p[:, 1] - tx * p[:, 2]) / n2
    s = (tx * p[:, 1] + tz * p[:, 2]) / n2
    t = np.stack([tx, np.zeros_like(tx), tz], 1)
    return np.arctan2(s, c), t / np.sqrt(n2)[:, None]


def _hypotheses_tilted(xi: np.ndarray, xj: np.ndarray, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upright essential matrices with any baseline from 5-match samples (K, 5) -> (yaw (K,), t (K, 3)). xi^T E xj is
    linear in (E00 = E22, E02 = -E20, E01, E10, E12, E21) = (-ty s, ty c, -tz, tz c + tx s, tz s - tx c, tx)."""
    a, b = xi[samples], xj[samples]
    rows = np.stack([a[..., 0] * b[..., 0] + a[..., 2] * b[..., 2], a[..., 0] * b[..., 2] - a[..., 2] * b[..., 0],
                     a[..., 0] * b[..., 1], a[..., 1] * b[..., 0], a[..., 1] * b[..., 2], a[..., 2] * b[..., 1]], -1)
    p = np.linalg.svd(rows, full_matrices=True)[2][:, -1]  # (K, 6)
    tx, tz = p[:, 5], -p[:, 2]
    n2 = np.maximum(tx**2 + tz**2, 1e-12)
    c = (tz * p[:, 3] - tx * p[:, 4]) / n2
    s = (tx * p[:, 3] + tz * p[:, 4]) / n2
    norm = np.maximum(np.hypot(c, s), 1e-12)
    c, s = c / norm, s / norm
    t = np.stack([tx, p[:, 1] * c - p[:, 0] * s, tz], 1)
    return np.arctan2(s, c), t / np.maximum(np.linalg.norm(t, axis=1), 1e-12)[:, None]


def _essentials(yaw: np.ndarray, t: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    S = np.zeros((len(yaw), 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 0], S[:, 1, 2], S[:, 2, 0], S[:, 2, 1] = -t[:, 2], t[:, 1], t[:, 2], -t[:, 0], \
        -t[:, 1], t[:, 0]
    return S @ R


def triangulate(yaw: float, t: np.ndarray, xi: np.ndarray, xj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ranges (lambda_i, lambda_j) (N,) along xi and xj of the midpoint triangulation with camera j at t (camera i's
    frame) rotated by yaw; negative = behind that camera."""
    rj = xj @ yaw_matrix(yaw).T
    d = np.einsum("nk,nk->n", xi, rj)
    ti, tj = xi @ t, rj @ t
    den = np.maximum(1.0 - d**2, 1e-12)
    return (ti - d * tj) / den, (d * ti - tj) / den


def _oriented(yaw: float, t: np.ndarray, xi: np.ndarray, xj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sign of t (the essential matrix fixes it only up to sign) that puts most points in front -> (t, front)."""
    li, lj = triangulate(yaw, t, xi, xj)
    front = (li > 0) & (lj > 0)
    back = (li < 0) & (lj < 0)
    return (t, front) if front.sum() >= back.sum() else (-t, back)


def _refine(yaw: float, t: np.ndarray, xi: np.ndarray, xj: np.ndarray, f_scale: float) -> tuple[float, np.ndarray]:
    """Yaw and unit t minimising the robust (soft-L1) epipolar angles of the matches; t may leave the horizontal."""

    def res(x):
        tt = x[1:] / max(np.linalg.norm(x[1:]), 1e-12)
        return epipolar_angles(_essentials(x[:1], tt[None])[0], xi, xj)

    sol = least_squares(res, np.concatenate([[yaw], t]), loss="soft_l1", f_scale=f_scale, max_nfev=60)
    return float(sol.x[0]), sol.x[1:] / np.linalg.norm(sol.x[1:])


def upright_relative_pose(xi: np.ndarray, xj: np.ndarray, *, threshold_deg: float = 0.4, iterations: int = 2000,
                          min_inliers: int = 12, seed: int = 0) -> UprightPose | None:
    """RANSAC over matched unit bearings xi, xj (N, 3) of two upright panoramas (camera y = gravity in both):
    3-match hypotheses with a horizontal baseline (cameras at one height) and half as many 5-match ones with any
    baseline, the best refined on the inliers of a
    shrinking band (4, 2, 1.5 thresholds) with the baseline free to tilt, inliers re-counted. None when fewer than min_inliers support the best model."""
    n = len(xi)
    if n < max(min_inliers, 3):
        return None
    rng = np.random.default_rng(seed)
    thr = np.radians(threshold_deg)
    best, best_count = None, -1
    chunks = [(_hypotheses, np.argsort(rng.random((500, n)), 1)[:, :3]) for _ in range(max(1, iterations // 500))]
    if n >= 5:
        chunks += [(_hypotheses_tilted, np.argsort(rng.random((500, n)), 1)[:, :5])
                   for _ in range(max(1, iterations // 1000))]
    for solver, chunk in chunks:
        yaw, t = solver(xi, xj, chunk)
        ok = np.isfinite(yaw) & np.isfinite(t).all(1)
        if not ok.any():
            continue
        err = epipolar_angles(_essentials(yaw[ok], t[ok]), xi, xj)  # (K, N)
        count = (err < thr).sum(1)
        k = int(np.argmax(count))
        if count[k] > best_count:
            best_count, best = int(count[k]), (float(yaw[ok][k]), t[ok][k])
    if best is None or best_count < min_inliers:
        return None
    yaw, t = best
    for widen in (4.0, 2.0, 1.5):  # local optimisation: refine on the inliers of a shrinking band, re-count
        E = _essentials(np.array([yaw]), t[None])[0]
        inl = epipolar_angles(E, xi, xj) < widen * thr
        if inl.sum() < min_inliers:
            return None
        yaw, t = _refine(yaw, t, xi[inl], xj[inl], thr)
    t, front = _oriented(yaw, t, xi, xj)
    E = _essentials(np.array([yaw]), t[None])[0]
    inliers = (epipolar_angles(E, xi, xj) < thr) & front
    if inliers.sum() < min_inliers:
        return None
    return UprightPose(yaw=yaw, t=t, inliers=inliers)


def _triangulated(pose: UprightPose, xi: np.ndarray, xj: np.ndarray, min_parallax_deg: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit-baseline ranges (li, lj) (N,) of the matches xi, xj (N, 3) and which are in front of both cameras with a
    parallax above min_parallax_deg."""
    li, lj = triangulate(pose.yaw, pose.t, xi, xj)
    rj = xj @ yaw_matrix(pose.yaw).T
    parallax = np.degrees(np.arccos(np.clip(np.einsum("nk,nk->n", xi, rj), -1, 1)))
    return li, lj, (li > 0) & (lj > 0) & (parallax > min_parallax_deg)


def metric_scale(pose: UprightPose, xi: np.ndarray, xj: np.ndarray, di: np.ndarray, dj: np.ndarray, *,
                 tol: float = 0.05, min_parallax_deg: float = 2.0) -> tuple[float, int]:
    """Metres per unit baseline of pose from the ray depths di, dj (N,) (0 = unknown) of the inlier matches: each
    triangulated point gives one scale per view (depth / unit-baseline range); points whose two scales agree within
    tol (log) lie on a surface both depths hold, and their median is the scale. -> (scale, support); nan, 0 when none
    agree (a door opening held as a wall, furniture missing from a layout depth: their two scales differ)."""
    m = pose.inliers & (di > 0) & (dj > 0)
    li, lj, ok = _triangulated(pose, xi[m], xj[m], min_parallax_deg)
    si, sj = np.log(di[m][ok] / li[ok]), np.log(dj[m][ok] / lj[ok])
    agree = np.abs(si - sj) < tol
    if not agree.any():
        return float("nan"), 0
    return float(np.exp(np.median(0.5 * (si + sj)[agree]))), int(agree.sum())


def max_baseline(pose: UprightPose, xi: np.ndarray, xj: np.ndarray, height_m: float, *, below: float = 0.3,
                 count: int = 3, min_parallax_deg: float = 2.0) -> float:
    """The longest baseline (metres) of pose that leaves fewer than `count` of its triangulated inlier matches
    (xi, xj (N, 3), parallax above min_parallax_deg) more than `below` times camera i's height above the floor
    (height_m) under that floor: every length scales the points with it, and a floor seen in both views would be
    pushed under the floor by a baseline too long (a floor pattern matched at the wrong repeat). inf when fewer than
    `count` points lie below camera i."""
    m = pose.inliers
    li, _, ok = _triangulated(pose, xi[m], xj[m], min_parallax_deg)
    down = li[ok] * xi[m][ok, 1]  # unit-baseline depth below camera i (camera y points down)
    lengths = np.sort((1.0 + below) * height_m / down[down > 0])
    return float(lengths[count - 1]) if len(lengths) >= count else math.inf
