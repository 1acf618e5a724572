"""Floor-plane registration of upright panoramas: each panorama's floor as a metric top-down image (camera height from
its depth), SIFT on those images and a 1-point rigid RANSAC over (x, z, yaw) whose inliers agree in position, keypoint
orientation and keypoint scale."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from panoworld.core.conventions import erp_dirs, erp_pixel_from_lonlat
from panoworld.core.shapes import check_shape
from panoworld.register.upright import wrap_angle, yaw_matrix, yaw_matrix_xz, yaw_of


@dataclass(kw_only=True)
class FloorView:
    """SIFT features of one panorama's floor seen from above."""

    height_m: float
    """Camera height above the floor (metres)."""
    xz: np.ndarray
    """(N, 2) keypoint positions on the floor in the camera frame (x right, z forward), metres."""
    descriptors: np.ndarray
    """(N, 128) float32 SIFT descriptors."""
    angles: np.ndarray
    """(N,) SIFT keypoint orientations (radians, OpenCV's angle): a yaw of the camera by psi turns them by psi."""
    sizes: np.ndarray
    """(N,) SIFT keypoint diameters (floor image pixels): the same floor patch has the same metric size in every
    floor image."""


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
    (column = x, row 0 = far +z), resampled from the ERP panorama rgb (H, 2H, 3) (or (n, n) from an (H, 2H) image)."""
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
               rig_deg: float = 32.0, max_features: int = 4000, exclude: np.ndarray | None = None) -> FloorView | None:
    """SIFT keypoints of the floor image of an upright panorama rgb (H, 2H, 3) with ray depth (h, 2h) (camera height;
    0 = invalid). The whole lower hemisphere is projected onto the floor plane, walls included (they smear radially
    and find no consistent partner), so floor seen through a doorway that a layout depth closes is kept; the disc
    within rig_deg of the nadir (the tripod) is masked, and so is what exclude (an ERP mask (H', 2H') bool, e.g. a
    detected rig) covers. None without a camera height."""
    check_shape("panorama", rgb, "H W 3")
    h = camera_height(depth)
    if h is None or not np.isfinite(h) or h <= 0:
        return None
    img = floor_image(rgb, h, radius_m=radius_m, cell_m=cell_m)
    gray = cv2.createCLAHE(2.0, (8, 8)).apply(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
    n = gray.shape[0]
    c = (np.arange(n) + 0.5) * cell_m - radius_m
    r = np.hypot(*np.meshgrid(c, c))
    keep = (r > h * np.tan(np.radians(rig_deg))) & (r < radius_m - 2 * cell_m)
    if exclude is not None:
        keep &= floor_image(exclude.astype(np.uint8) * 255, h, radius_m=radius_m, cell_m=cell_m) < 128
    mask = keep.astype(np.uint8) * 255
    kps, desc = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=0.01).detectAndCompute(gray, mask)
    if desc is None or not kps:
        return FloorView(height_m=h, xz=np.zeros((0, 2)), descriptors=np.zeros((0, 128), np.float32),
                         angles=np.zeros(0), sizes=np.zeros(0))
    pts = np.array([k.pt for k in kps], np.float64)  # OpenCV pixel centres are integers
    xz = np.stack([(pts[:, 0] + 0.5) * cell_m - radius_m, radius_m - (pts[:, 1] + 0.5) * cell_m], 1)
    return FloorView(height_m=h, xz=xz, descriptors=desc.astype(np.float32),
                     angles=np.radians([k.angle for k in kps]), sizes=np.array([k.size for k in kps], np.float64))


def oriented_rigid2d_ransac(p: np.ndarray, q: np.ndarray, dtheta: np.ndarray, dlog2: np.ndarray, *, threshold: float,
                            angle_tol: float = np.radians(15.0), scale_tol: float = 0.6, hypotheses: int = 2000,
                            seed: int = 0) -> tuple[float, np.ndarray, np.ndarray] | None:
    """2D rigid p ~ yaw_matrix_xz(yaw) q + t (no scale) over matched keypoints p, q (N, 2) whose orientations differ by dtheta
    (N,) (a_angle - b_angle, radians) and whose sizes differ by dlog2 (N,) octaves. Each match is a hypothesis by itself
    (yaw = its orientation difference); a match is an inlier when it lands within threshold, its orientation difference
    is within angle_tol of the yaw and its sizes within scale_tol octaves: three independent tests, so chance
    agreement stays at a few matches even without a ratio test. The best is refined by least squares on its inliers.
    -> (yaw, t (2,), inliers (N,) bool), None without a hypothesis."""
    check_shape("p", p, "N 2")
    check_shape("q", q, "N 2")
    same = np.abs(dlog2) < scale_tol
    cand = np.flatnonzero(same)
    if len(cand) < 1:
        return None
    if len(cand) > hypotheses:
        cand = np.sort(np.random.default_rng(seed).choice(cand, hypotheses, replace=False))
    # A hypothesis can only gather matches whose orientation difference is within angle_tol of its own: bins of
    # angle_tol, each hypothesis tested against its own bin and the two beside it.
    nb = max(1, int(2 * np.pi // angle_tol))
    bins = np.floor((dtheta % (2 * np.pi)) / (2 * np.pi) * nb).astype(int) % nb
    best, best_n = -1, -1
    for b in range(nb):
        k = cand[bins[cand] == b]
        near = np.flatnonzero(same & np.isin(bins, [(b - 1) % nb, b, (b + 1) % nb]))
        for k0 in range(0, len(k), 256):
            kk = k[k0:k0 + 256]
            c, s = np.cos(dtheta[kk])[:, None], np.sin(dtheta[kk])[:, None]  # yaw_matrix_xz, written out
            qx, qz, px, pz = q[near, 0], q[near, 1], p[near, 0], p[near, 1]
            ex = c * (qx - q[kk, :1]) + s * (qz - q[kk, 1:]) - (px - p[kk, :1])
            ez = c * (qz - q[kk, 1:]) - s * (qx - q[kk, :1]) - (pz - p[kk, 1:])
            n = ((ex**2 + ez**2 < threshold**2)
                 & (np.abs(wrap_angle(dtheta[near][None] - dtheta[kk, None])) < angle_tol)).sum(1)
            if n.max() > best_n:
                best_n, best = int(n.max()), int(kk[int(np.argmax(n))])
    yaw = float(dtheta[best])
    t = p[best] - yaw_matrix_xz(yaw) @ q[best]
    inl = np.zeros(len(p), bool)
    inl[best] = True
    for _ in range(3):
        inl = inl | ((np.linalg.norm(q @ yaw_matrix_xz(yaw).T + t - p, axis=1) < threshold)
                     & (np.abs(wrap_angle(dtheta - yaw)) < angle_tol) & same)
        if inl.sum() >= 2:
            pc, qc = p[inl].mean(0), q[inl].mean(0)
            U, _, Vt = np.linalg.svd((q[inl] - qc).T @ (p[inl] - pc))
            Rr = Vt.T @ np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
            yaw, t = float(np.arctan2(Rr[0, 1], Rr[0, 0])), pc - Rr @ qc
        inl = ((np.linalg.norm(q @ yaw_matrix_xz(yaw).T + t - p, axis=1) < threshold)
               & (np.abs(wrap_angle(dtheta - yaw)) < angle_tol) & same)
    return yaw, t, inl


def fixed_yaw_translation(p: np.ndarray, q: np.ndarray, dtheta: np.ndarray, dlog2: np.ndarray, yaws: np.ndarray, *,
                          threshold: float, angle_tol: float = np.radians(15.0), scale_tol: float = 0.6
                          ) -> tuple[float, np.ndarray, np.ndarray] | None:
    """oriented_rigid2d_ransac with the yaw one of the candidates yaws (K,) (radians): per candidate, every match
    whose orientation difference is within angle_tol of it and whose sizes agree gives one translation p - R q; the
    translation most of them agree with (within threshold) is refined as their mean. The candidate with the most
    inliers wins. -> (yaw, t (2,), inliers (N,) bool), None without a hypothesis."""
    check_shape("p", p, "N 2")
    check_shape("q", q, "N 2")
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for yaw in np.asarray(yaws, np.float64).ravel():
        ok = (np.abs(dlog2) < scale_tol) & (np.abs(wrap_angle(dtheta - yaw)) < angle_tol)
        idx = np.flatnonzero(ok)
        if not len(idx):
            continue
        d = p[idx] - q[idx] @ yaw_matrix_xz(yaw).T
        counts = np.zeros(len(d), np.int64)
        for k0 in range(0, len(d), 1024):
            counts[k0:k0 + 1024] = (((d[k0:k0 + 1024, None] - d[None]) ** 2).sum(-1) < threshold**2).sum(1)
        t = d[int(np.argmax(counts))]
        for _ in range(3):
            near = np.linalg.norm(d - t, axis=1) < threshold
            t = d[near].mean(0)
        inl = np.zeros(len(p), bool)
        inl[idx[np.linalg.norm(d - t, axis=1) < threshold]] = True
        if best is None or inl.sum() > best[2].sum():
            best = (float(yaw), t, inl)
    return best


def floor_matches(a: FloorView, b: FloorView, *, ratio: float = 1.0) -> np.ndarray:
    """(M, 2) int64 (index in a, index in b): each keypoint of a with its nearest neighbour in b (of two or more),
    kept by Lowe's ratio test when ratio < 1."""
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
    return np.array([(k[0].queryIdx, k[0].trainIdx) for k in knn
                     if len(k) == 2 and (ratio >= 1 or k[0].distance < ratio * k[1].distance)], np.int64).reshape(-1, 2)


def floor_pair(a: FloorView, b: FloorView, *, threshold_m: float = 0.05, ratio: float = 1.0, seed: int = 0,
               yaws: np.ndarray | None = None) -> FloorPose | None:
    """a_from_b of two floor views: each keypoint of a with its nearest neighbour in b (Lowe's ratio test below 1),
    oriented_rigid2d_ransac (threshold_m on the floor), or fixed_yaw_translation when the yaw is known to be one of
    yaws (radians); the vertical offset from the camera heights (one floor). None without a model."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return None
    m = floor_matches(a, b, ratio=ratio)
    if len(m) < 2:
        return None
    args = (a.xz[m[:, 0]], b.xz[m[:, 1]], a.angles[m[:, 0]] - b.angles[m[:, 1]],
            np.log2(a.sizes[m[:, 0]] / b.sizes[m[:, 1]]))
    fit = (oriented_rigid2d_ransac(*args, threshold=threshold_m, seed=seed) if yaws is None
           else fixed_yaw_translation(*args, yaws, threshold=threshold_m))
    if fit is None:
        return None
    yaw, t, inl = fit
    T = np.eye(4)
    T[:3, :3] = yaw_matrix(yaw)
    T[:3, 3] = [t[0], a.height_m - b.height_m, t[1]]
    res = np.linalg.norm(b.xz[m[inl, 1]] @ yaw_matrix_xz(yaw).T + t - a.xz[m[inl, 0]], axis=1)
    return FloorPose(a_from_b=T, inliers=int(inl.sum()), matches=len(m),
                     residual_m=float(np.sqrt(np.mean(res**2))) if len(res) else float("nan"))


def floor_support(a: FloorView, b: FloorView, a_from_b: np.ndarray, *, threshold_m: float = 0.08,
                  angle_tol: float = np.radians(15.0), scale_tol: float = 0.6, matches: np.ndarray | None = None) -> int:
    """How many of floor_matches(a, b) (or `matches`, (M, 2)) agree with a given pose a_from_b (4, 4): land within
    threshold_m of their partner on the floor, turn by the pose's yaw within angle_tol and keep their size within
    scale_tol octaves (the tests of floor_pair's inliers)."""
    m = floor_matches(a, b) if matches is None else matches
    if len(m) == 0:
        return 0
    yaw = yaw_of(a_from_b[:3, :3])
    on_floor = np.linalg.norm(b.xz[m[:, 1]] @ yaw_matrix_xz(yaw).T + a_from_b[[0, 2], 3] - a.xz[m[:, 0]], axis=1)
    turn = np.abs(wrap_angle(a.angles[m[:, 0]] - b.angles[m[:, 1]] - yaw))
    octaves = np.abs(np.log2(a.sizes[m[:, 0]] / b.sizes[m[:, 1]]))
    return int(((on_floor < threshold_m) & (turn < angle_tol) & (octaves < scale_tol)).sum())
