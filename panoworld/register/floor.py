"""Floor-plane registration of upright panoramas: each panorama's floor as a metric top-down image (camera height from
its depth), SIFT on those images and a 2-point rigid RANSAC over (x, z, yaw)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from panoworld.core.conventions import erp_dirs, erp_pixel_from_lonlat
from panoworld.core.shapes import check_shape
from panoworld.register.upright import yaw_matrix


@dataclass(kw_only=True)
class FloorView:
    """SIFT features of one panorama's floor seen from above."""

    height_m: float
    """Camera height above the floor (metres)."""
    xz: np.ndarray
    """(N, 2) keypoint positions on the floor in the camera frame (x right, z forward), metres."""
    descriptors: np.ndarray
    """(N, 128) float32 SIFT descriptors."""


@dataclass(kw_only=True)
class FloorPose:
    """a_from_b of two panoramas from their floor images."""

    a_from_b: np.ndarray
    """(4, 4) rigid: yaw about gravity, horizontal translation, camera height difference."""
    inliers: int
    matches: int
    residual_m: float
    """RMS floor distance of the inliers (metres)."""


def camera_height(depth: np.ndarray, *, min_depression_deg: float = 40.0) -> float | None:
    """Camera height above the floor from the ray depth (H, W) below min_depression_deg under the horizon (median of
    depth * down component); None when no valid depth is there."""
    check_shape("depth", depth, "H W")
    h, w = depth.shape
    dirs = erp_dirs(h, w, np.float64)
    down = dirs[..., 1]
    sel = (down > np.sin(np.radians(min_depression_deg))) & np.isfinite(depth) & (depth > 0)
    if sel.sum() < 0.01 * sel.size:
        return None
    return float(np.median(depth[sel] * down[sel]))


def floor_image(rgb: np.ndarray, height_m: float, *, radius_m: float, cell_m: float) -> np.ndarray:
    """(n, n, 3) uint8 top-down image of the plane height_m below the camera over x, z in [-radius_m, radius_m]
    (column = x, row 0 = far +z), resampled from the ERP panorama rgb (H, 2H, 3)."""
    n = int(round(2 * radius_m / cell_m))
    c = (np.arange(n) + 0.5) * cell_m - radius_m
    x, z = np.meshgrid(c, c[::-1])
    lon, lat = np.arctan2(x, z), np.arctan2(-height_m, np.hypot(x, z))
    hi, wi = rgb.shape[:2]
    pad = 4
    padded = np.concatenate([rgb[:, -pad:], rgb, rgb[:, :pad]], 1)  # the seam wraps
    u, v = erp_pixel_from_lonlat(lon, lat, hi, wi)  # pixel centres at +0.5; OpenCV's remap at integers
    return cv2.remap(padded, (u - 0.5 + pad).astype(np.float32), (v - 0.5).astype(np.float32), cv2.INTER_LINEAR)


def floor_view(rgb: np.ndarray, depth: np.ndarray, *, radius_m: float = 6.0, cell_m: float = 0.015,
               rig_deg: float = 32.0, max_features: int = 4000) -> FloorView | None:
    """SIFT keypoints of the floor image of an upright panorama rgb (H, 2H, 3) with ray depth (h, 2h) (camera height;
    0 = invalid). The whole lower hemisphere is projected onto the floor plane, walls included (they smear radially
    and find no consistent partner), so floor seen through a doorway that a layout depth closes is kept; the disc
    within rig_deg of the nadir (the tripod) is masked. None without a camera height."""
    check_shape("panorama", rgb, "H W 3")
    h = camera_height(depth)
    if h is None or not np.isfinite(h) or h <= 0:
        return None
    img = floor_image(rgb, h, radius_m=radius_m, cell_m=cell_m)
    gray = cv2.createCLAHE(2.0, (8, 8)).apply(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
    n = gray.shape[0]
    c = (np.arange(n) + 0.5) * cell_m - radius_m
    r = np.hypot(*np.meshgrid(c, c))
    mask = ((r > h * np.tan(np.radians(rig_deg))) & (r < radius_m - 2 * cell_m)).astype(np.uint8) * 255
    kps, desc = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=0.01).detectAndCompute(gray, mask)
    if desc is None or not kps:
        return FloorView(height_m=h, xz=np.zeros((0, 2)), descriptors=np.zeros((0, 128), np.float32))
    pts = np.array([k.pt for k in kps], np.float64)  # OpenCV pixel centres are integers
    xz = np.stack([(pts[:, 0] + 0.5) * cell_m - radius_m, radius_m - (pts[:, 1] + 0.5) * cell_m], 1)
    return FloorView(height_m=h, xz=xz, descriptors=desc.astype(np.float32))


def rigid2d_ransac(p: np.ndarray, q: np.ndarray, *, threshold: float, iterations: int = 2000, seed: int = 0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """2D rigid p ~ R q + t (no scale) over matched points p, q (N, 2): 2-point hypotheses (pairs whose lengths differ
    by more than 2 threshold are skipped), the best refined by least squares on its inliers -> (R (2, 2), t (2,),
    inliers (N,) bool), None with fewer than 2 matches."""
    n = len(p)
    if n < 2:
        return None
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, n, iterations), rng.integers(0, n, iterations)
    dp, dq = p[j] - p[i], q[j] - q[i]
    lq = np.linalg.norm(dq, axis=1)
    ok = (i != j) & (np.abs(np.linalg.norm(dp, axis=1) - lq) < 2 * threshold) & (lq > 10 * threshold)
    if not ok.any():
        return None
    i, dp, dq = i[ok], dp[ok], dq[ok]
    th = np.arctan2(dp[:, 1], dp[:, 0]) - np.arctan2(dq[:, 1], dq[:, 0])
    cs, sn = np.cos(th), np.sin(th)
    R = np.stack([np.stack([cs, -sn], -1), np.stack([sn, cs], -1)], -2)  # (K, 2, 2)
    t = p[i] - np.einsum("kab,kb->ka", R, q[i])
    err = np.linalg.norm(np.einsum("kab,nb->kna", R, q) + t[:, None] - p[None], axis=2)
    inl = err[int(np.argmax((err < threshold).sum(1)))] < threshold
    for _ in range(2):
        if inl.sum() < 2:
            return None
        pc, qc = p[inl].mean(0), q[inl].mean(0)
        U, _, Vt = np.linalg.svd((q[inl] - qc).T @ (p[inl] - pc))
        Rr = Vt.T @ np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
        tr = pc - Rr @ qc
        inl = np.linalg.norm(q @ Rr.T + tr - p, axis=1) < threshold
    return Rr, tr, inl


def floor_pair(a: FloorView, b: FloorView, *, threshold_m: float = 0.05, ratio: float = 0.9, seed: int = 0
               ) -> FloorPose | None:
    """a_from_b of two floor views: ratio-test matches, 2D rigid RANSAC (threshold_m on the floor), yaw and
    horizontal translation from the fit, the vertical offset from the camera heights (one floor). None without a
    model."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
    m = np.array([(k[0].queryIdx, k[0].trainIdx) for k in knn
                  if len(k) == 2 and k[0].distance < ratio * k[1].distance], np.int64).reshape(-1, 2)
    fit = rigid2d_ransac(a.xz[m[:, 0]], b.xz[m[:, 1]], threshold=threshold_m, seed=seed)
    if fit is None:
        return None
    R, t, inl = fit
    # yaw_matrix(yaw) acts on (x, z) as [[c, s], [-s, c]]
    T = np.eye(4)
    T[:3, :3] = yaw_matrix(float(np.arctan2(R[0, 1], R[0, 0])))
    T[:3, 3] = [t[0], a.height_m - b.height_m, t[1]]
    res = np.linalg.norm(b.xz[m[inl, 1]] @ R.T + t - a.xz[m[inl, 0]], axis=1)
    return FloorPose(a_from_b=T, inliers=int(inl.sum()), matches=len(m),
                     residual_m=float(np.sqrt(np.mean(res**2))) if len(res) else float("nan"))
