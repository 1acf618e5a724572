"""Image and video metrics on CPU: PSNR, SSIM, WS-PSNR of ERP images, loop closure of ERP videos, Frechet distance."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from panoworld.core.conventions import erp_pixel_solid_angle
from panoworld.core.shapes import check_shape


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a)
    b = np.asarray(b)
    dims = check_shape("a", a, "H W" if a.ndim == 2 else "H W C")
    check_shape("b", b, "H W" if a.ndim == 2 else "H W C", dims=dims)
    return a, b


def default_data_range(a: np.ndarray) -> float:
    """255 for uint8 images, 65535 for uint16, 1.0 for float images."""
    if a.dtype == np.uint8:
        return 255.0
    if a.dtype == np.uint16:
        return 65535.0
    return 1.0


def _weighted_psnr(err2: np.ndarray, weight: np.ndarray, data_range: float) -> float:
    """err2 (H, W, C) squared error, weight (H, W) >= 0 -> PSNR of the weighted mean squared error."""
    wsum = float(weight.sum()) * err2.shape[2]
    if wsum <= 0:
        return float("nan")
    mse = float((err2 * weight[..., None]).sum()) / wsum
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range**2 / mse))


def _sq_err(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    err2 = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    return err2 if err2.ndim == 3 else err2[..., None]


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, *, data_range: float | None = None) -> float:
    """PSNR in dB of images a, b (H, W[, C]) over all pixels or those where mask (H, W) is True.

    inf for identical images, nan for an empty mask. data_range defaults to 255 for uint8 and 1.0 for floats.
    """
    a, b = _pair(a, b)
    weight = np.ones(a.shape[:2]) if mask is None else _mask(mask, a.shape[:2]).astype(np.float64)
    return _weighted_psnr(_sq_err(a, b), weight, data_range or default_data_range(a))


def ws_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, *, data_range: float | None = None) -> float:
    """Weighted-to-spherically-uniform PSNR of ERP images (H, W[, C]) with W = 2H: each pixel weighs its solid angle
    (proportional to cos(latitude)), optionally restricted to mask (H, W)."""
    a, b = _pair(a, b)
    H, W = a.shape[:2]
    weight = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W)).astype(np.float64)
    if mask is not None:
        weight = weight * _mask(mask, (H, W))
    return _weighted_psnr(_sq_err(a, b), weight, data_range or default_data_range(a))


def video_psnr(
    a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, *, spherical: bool = False,
    data_range: float | None = None,
) -> float:
    """PSNR of the mean squared error pooled over all frames of videos a, b (T, H, W, C) (frames with no masked
    pixel simply contribute nothing), optionally where mask (T, H, W) is True; spherical weighs ERP pixels by solid
    angle as ws_psnr does."""
    a, b = np.asarray(a), np.asarray(b)
    check_shape("b", b, "T H W C", dims=check_shape("a", a, "T H W C"))
    T, H, W, C = a.shape
    weight = np.ones((T, H, W))
    if spherical:
        weight = weight * erp_pixel_solid_angle(H, W)[None]
    if mask is not None:
        weight = weight * _mask(mask, (T, H, W))
    err2 = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    return _weighted_psnr(err2.reshape(T * H, W, C), weight.reshape(T * H, W), data_range or default_data_range(a))


def _mask(mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    mask = np.asarray(mask)
    check_shape("mask", mask, " ".join(map(str, shape)))
    return mask.astype(bool)


def ssim_map(
    a: np.ndarray, b: np.ndarray, *, data_range: float | None = None, sigma: float = 1.5, k1: float = 0.01,
    k2: float = 0.03,
) -> np.ndarray:
    """Per-pixel SSIM (H, W) of Wang et al. 2004 (11x11 Gaussian window, sigma 1.5), averaged over channels.

    Local statistics use the Gaussian-weighted (population) moments with reflected borders.
    """
    a, b = _pair(a, b)
    L = data_range or default_data_range(a)
    c1, c2 = (k1 * L) ** 2, (k2 * L) ** 2
    x = a.astype(np.float64)
    y = b.astype(np.float64)
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    out = np.zeros(x.shape[:2])
    for c in range(x.shape[2]):

        def blur(img):
            return gaussian_filter(img, sigma, truncate=3.5, mode="reflect")

        xc, yc = x[..., c], y[..., c]
        mx, my = blur(xc), blur(yc)
        vx = blur(xc * xc) - mx * mx
        vy = blur(yc * yc) - my * my
        cxy = blur(xc * yc) - mx * my
        out += ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return out / x.shape[2]


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, *, data_range: float | None = None) -> float:
    """Mean SSIM of images a, b (H, W[, C]) (see ssim_map); over pixels where mask (H, W) is True if given,
    otherwise over all pixels at least 5 pixels (the window radius) from the border, like scikit-image."""
    m = ssim_map(a, b, data_range=data_range)
    if mask is not None:
        sel = _mask(mask, m.shape)
        return float(m[sel].mean()) if sel.any() else float("nan")
    r = 5
    inner = m[r:-r, r:-r] if min(m.shape) > 2 * r else m
    return float(inner.mean())


def reprojection_error(
    img_t: np.ndarray,
    img_t1: np.ndarray,
    depth_t: np.ndarray,
    depth_t1: np.ndarray,
    world_from_cam_t: np.ndarray,
    world_from_cam_t1: np.ndarray,
    *,
    mask_t: np.ndarray | None = None,
    occlusion_tol: float = 0.03,
) -> tuple[np.ndarray, np.ndarray]:
    """Temporal consistency of ERP frames t and t+1 through known geometry (e.g. ground-truth depth).

    Every pixel of frame t+1 is lifted with depth_t1 (H, W), moved into camera t and sampled bilinearly (columns
    wrapped) from img_t (H, W, C). Returns (err (H, W) float64 RMS over channels of img_t1 - sampled img_t,
    valid (H, W) bool): valid where the depth is finite and the point is visible in frame t (its distance agrees
    within occlusion_tol relative with depth_t at all four pixels the bilinear sample reads) and, if mask_t (H, W)
    is given, all four of those pixels are True in mask_t (e.g. only pixels that were filled in frame t).
    """
    from panoworld.core.conventions import erp_pixel_from_dir, invert_pose, points_from_depth, transform_points

    img_t, img_t1 = _pair(img_t, img_t1)
    H, W = img_t.shape[:2]
    dims = {"H": H, "W": W}
    check_shape("depth_t", depth_t, "H W", dims=dims)
    check_shape("depth_t1", depth_t1, "H W", dims=dims)
    if mask_t is not None:
        mask_t = _mask(mask_t, (H, W))
    ok = np.isfinite(depth_t1) & (depth_t1 > 0)
    d1 = np.where(ok, depth_t1, 1.0).astype(np.float64)
    pts = transform_points(invert_pose(world_from_cam_t) @ world_from_cam_t1, points_from_depth(d1))
    u, v = erp_pixel_from_dir(pts, H, W)
    map_x = (u - 0.5).astype(np.float32)
    map_y = np.clip(v - 0.5, 0, H - 1).astype(np.float32)
    sampled = cv2_remap(img_t.astype(np.float32), map_x, map_y)
    # Visible only if all four bilinear taps see the point: no colour is mixed across an occlusion edge.
    dist = np.linalg.norm(pts, axis=-1)
    d_t = np.where(np.isfinite(depth_t), depth_t, 0.0)
    i0 = np.floor(map_y).astype(np.int64)
    j0 = np.floor(map_x).astype(np.int64)
    for di in (0, 1):
        for dj in (0, 1):
            ti, tj = np.clip(i0 + di, 0, H - 1), (j0 + dj) % W
            ok &= np.abs(d_t[ti, tj] - dist) <= occlusion_tol * dist
            if mask_t is not None:
                ok &= mask_t[ti, tj]
    diff = img_t1.astype(np.float64) - sampled
    err = np.sqrt((diff**2).mean(axis=-1)) if diff.ndim == 3 else np.abs(diff)
    return err, ok


def cv2_remap(img: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, *, nearest: bool = False) -> np.ndarray:
    """cv2.remap with columns wrapped around (ERP seam); bilinear unless nearest."""
    import cv2

    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(img, map_x, map_y, interp, borderMode=cv2.BORDER_WRAP)


def loop_closure_flow_deg(first: np.ndarray, last: np.ndarray) -> float:
    """Loop-closure error of a closed path: how far the last ERP frame's content lies from the first's, in degrees.

    Dense optical flow (OpenCV DIS, medium preset) from first to last on grey ERP frames (H, W[, 3]) with W = 2H,
    columns wrapped by W/8 at the seam; the solid-angle-weighted median of the flow magnitude, times 360 / W.
    0 for identical frames (DIS returns exactly zero flow there); a yaw of k columns reads k * 360 / W degrees.
    Lower is better.
    """
    import cv2

    a, b = _pair(first, last)
    H, W = a.shape[:2]
    if W != 2 * H:
        raise ValueError(f"{a.shape=} but expected an ERP frame (H, 2H[, C])")

    def grey(x: np.ndarray) -> np.ndarray:
        x = x if x.dtype == np.uint8 else np.clip(np.rint(x.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
        return cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) if x.ndim == 3 else x

    pad = max(W // 8, 1)
    ga, gb = (np.ascontiguousarray(np.concatenate([g[:, -pad:], g, g[:, :pad]], 1)) for g in (grey(a), grey(b)))
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(ga, gb, None)[:, pad:-pad]
    mag = np.hypot(flow[..., 0], flow[..., 1]).astype(np.float64).ravel()
    w = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W)).ravel()
    order = np.argsort(mag, kind="stable")
    cum = np.cumsum(w[order])
    return float(mag[order][np.searchsorted(cum, 0.5 * cum[-1])] * 360.0 / W)


def feature_statistics(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean (D,), covariance (D, D)) of features (N, D), N >= 2 (unbiased covariance, as pytorch-fid)."""
    f = np.asarray(features, dtype=np.float64)
    check_shape("features", f, "N D")
    if len(f) < 2:
        raise ValueError(f"{f.shape=} but expected (N, D) with N >= 2")
    return f.mean(0), np.cov(f, rowvar=False)


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray, eps: float = 1e-6) -> float:
    """Frechet distance of two Gaussians: |mu1 - mu2|^2 + tr(S1 + S2 - 2 (S1 S2)^(1/2)) (Heusel et al. 2017, FID;
    Unterthiner et al. 2018, FVD). tr (S1 S2)^(1/2) is the sum of the square roots of the eigenvalues of S1^(1/2) S2
    S1^(1/2) (symmetric, positive semi-definite, the same eigenvalues as S1 S2), so a singular covariance (fewer
    samples than dimensions) needs no eps; eps is the round-off below which an eigenvalue counts as 0."""
    mu1, mu2 = np.atleast_1d(mu1).astype(np.float64), np.atleast_1d(mu2).astype(np.float64)
    s1, s2 = np.atleast_2d(sigma1).astype(np.float64), np.atleast_2d(sigma2).astype(np.float64)
    dims = check_shape("mu1", mu1, "D")
    for name, arr, spec in (("mu2", mu2, "D"), ("sigma1", s1, "D D"), ("sigma2", s2, "D D")):
        check_shape(name, arr, spec, dims=dims)
    w, v = np.linalg.eigh((s1 + s1.T) / 2)
    root1 = (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T
    inner = root1 @ s2 @ root1
    lam = np.linalg.eigvalsh((inner + inner.T) / 2)
    tr_covmean = float(np.sqrt(np.clip(lam, 0.0, None) * (lam > eps * max(lam.max(initial=0.0), 1.0))).sum())
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * tr_covmean)


def frechet_feature_distance(feats_a: np.ndarray, feats_b: np.ndarray) -> float:
    """Frechet distance between the Gaussian fits of two feature sets (N, D) and (M, D)."""
    return frechet_distance(*feature_statistics(feats_a), *feature_statistics(feats_b))
