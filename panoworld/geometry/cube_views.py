"""Perspective views of a panorama, and per-view monocular depth merged into one seamless ERP depth."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from panoworld.core.conventions import erp_dirs, erp_pixel_from_dir
from panoworld.io.depth import DepthKind


@dataclass(frozen=True)
class PerspectiveView:
    """A square pinhole view from the panorama's centre: cam_from_view rotation (3, 3), field of view, size."""

    cam_from_view: np.ndarray
    fov_deg: float
    size: int

    @property
    def focal(self) -> float:
        return 0.5 * self.size / np.tan(np.deg2rad(self.fov_deg) / 2.0)

    def rays(self) -> np.ndarray:
        """Unit ray directions of the view's pixel centres in the camera (ERP) frame, shape (size, size, 3)."""
        c = np.arange(self.size) + 0.5 - 0.5 * self.size
        x, y = np.meshgrid(c / self.focal, c / self.focal)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return d @ self.cam_from_view.T

    def project(self, dirs_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame directions (..., 3) -> (px, py) continuous pixel coords (centre of pixel (r, c) at (c, r),
        OpenCV remap convention) and cos of the angle to the optical axis (<= 0 behind the view)."""
        d = dirs_cam @ self.cam_from_view  # view_from_cam applied to row vectors
        z = d[..., 2]
        zs = np.where(z > 1e-6, z, np.nan)
        px = self.focal * d[..., 0] / zs + 0.5 * self.size - 0.5
        py = self.focal * d[..., 1] / zs + 0.5 * self.size - 0.5
        return px, py, z / np.linalg.norm(d, axis=-1)


def cube_views(fov_deg: float = 110.0, size: int = 518) -> list[PerspectiveView]:
    """Six cube-face views (front, right, back, left, up, down) widened to fov_deg (> 90) so neighbours overlap."""
    if not 90.0 < fov_deg < 170.0:
        raise ValueError(f"{fov_deg=} must be in (90, 170) so that neighbouring cube faces overlap")
    rots = [Rotation.from_euler("y", a, degrees=True).as_matrix() for a in (0, 90, 180, 270)]
    rots += [Rotation.from_euler("x", a, degrees=True).as_matrix() for a in (90, -90)]  # up, down
    return [PerspectiveView(r, fov_deg, size) for r in rots]


def render_view(rgb: np.ndarray, view: PerspectiveView) -> np.ndarray:
    """Bilinear resampling of the panorama rgb (H, W, 3) into a perspective view (size, size, 3), seam wrapped."""
    H, W = rgb.shape[:2]
    mx, my = view_maps(view, H, W)
    # One wrapped column each side and one replicated row top/bottom, so remap never reads past the seam.
    padded = np.concatenate([rgb[:, -1:], rgb, rgb[:, :1]], axis=1)
    padded = np.concatenate([padded[:1], padded, padded[-1:]], axis=0)
    return cv2.remap(padded, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def view_maps(view: PerspectiveView, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """render_view's remap coordinates (size, size) float32 of the view into an (H, W) panorama padded by one pixel
    (cached per view and size; read-only)."""
    return _view_maps(np.asarray(view.cam_from_view, np.float64).tobytes(), float(view.fov_deg), int(view.size), H, W)


@lru_cache(maxsize=8)
def _view_maps(rot: bytes, fov_deg: float, size: int, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    view = PerspectiveView(np.frombuffer(rot, np.float64).reshape(3, 3), fov_deg, size)
    u, v = erp_pixel_from_dir(view.rays(), H, W)
    maps = (u + 0.5).astype(np.float32), (v + 0.5).astype(np.float32)
    for m in maps:
        m.flags.writeable = False
    return maps


@dataclass
class MergeResult:
    depth: np.ndarray
    """(H, W) float32 ray distance; relative views: arbitrary global scale, metric views: metric; 0 where invalid."""
    valid: np.ndarray
    """(H, W) bool."""
    scale: np.ndarray
    """(N,) per-view scale of the alignment."""
    shift: np.ndarray
    """(N,) per-view shift (relative views; zeros for metric)."""
    overlap_rel_rmse: float
    """Relative RMS disagreement of the aligned views on their overlaps (0 = perfectly consistent)."""


def merge_view_predictions(
    preds: list[np.ndarray], views: list[PerspectiveView], height: int, width: int, kind: DepthKind,
    *, align_height: int = 128,
) -> MergeResult:
    """Merge per-view predictions (each (h, w), any size, resampled to the view size) into one seamless ERP depth.

    Every view k gets unknowns (scale s_k, shift t_k) for relative (inverse-depth) predictions, or s_k alone for
    metric z-depth, such that the inverse ray distance 1/r = cos(theta) * (s_k * o_k + t_k) (relative) or
    cos(theta) * s_k / o_k (metric) agrees between overlapping views; theta is the angle to the view's axis. The
    least-squares system over overlap samples of an align_height x 2*align_height ERP grid is solved with the
    gauge "mean inverse distance on the overlaps = 1" (two reweighted passes make residuals relative), so the
    result is defined up to one global scale: relative results are normalised to median depth 1, metric ones
    to a geometric-mean view scale of 1. The ERP map blends the aligned views in inverse depth with weights
    falling to 0 at each view's border, so it has no seams.
    """
    if len(preds) != len(views):
        raise ValueError(f"{len(preds)=} predictions but {len(views)=} views")
    kind = DepthKind(kind)
    n = len(views)
    n_unk = 2 if kind == DepthKind.RELATIVE else 1

    def sample(h: int, w: int):
        """Per view: (feature columns (h, w, n_unk) with 1/r = feat . x_k, blend weight (h, w))."""
        dirs = erp_dirs(h, w, dtype=np.float64)
        out = []
        for pred, view in zip(preds, views):
            p = np.asarray(pred, np.float32)
            if p.shape != (view.size, view.size):
                p = cv2.resize(p, (view.size, view.size), interpolation=cv2.INTER_LINEAR)
            px, py, cos = view.project(dirs)
            inside = np.isfinite(px) & (px >= 0) & (px <= view.size - 1) & (py >= 0) & (py <= view.size - 1)
            mx = np.where(inside, px, -10).astype(np.float32)
            my = np.where(inside, py, -10).astype(np.float32)
            o = cv2.remap(p, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
            half = 0.5 * (view.size - 1)
            edge = 1.0 - np.maximum(np.abs(mx - half), np.abs(my - half)) / half
            wgt = np.where(inside & np.isfinite(o), np.clip(edge, 0.0, 1.0), 0.0)
            if kind == DepthKind.RELATIVE:
                feat = np.stack([cos * o, cos], axis=-1)
            else:
                wgt = np.where(o > 0, wgt, 0.0)
                feat = (cos / np.where(o > 0, o, 1.0))[..., None]
            out.append((np.nan_to_num(feat), wgt))
        return out

    # Alignment on a coarse grid.
    ha = min(align_height, height)
    coarse = sample(ha, 2 * ha)
    blocks_i, blocks_j = [], []
    for i in range(n):
        for j in range(i + 1, n):
            both = (coarse[i][1] > 0) & (coarse[j][1] > 0)
            if both.sum() < 4:
                continue
            bi = np.zeros((int(both.sum()), n * n_unk))
            bj = np.zeros_like(bi)
            bi[:, i * n_unk:(i + 1) * n_unk] = coarse[i][0][both]
            bj[:, j * n_unk:(j + 1) * n_unk] = coarse[j][0][both]
            blocks_i.append(bi)
            blocks_j.append(bj)
    if not blocks_i:
        raise ValueError("the perspective views do not overlap; use a wider field of view")
    Ai, Aj = np.concatenate(blocks_i), np.concatenate(blocks_j)
    A = Ai - Aj

    def magnitude(x):  # mean |1/r| of the two views of each overlap sample, to make residuals relative
        return np.maximum(0.5 * (np.abs(Ai @ x) + np.abs(Aj @ x)), 1e-12)

    # Gauge: the mean inverse distance over the overlap samples is 1. A tiny ridge picks the smallest solution
    # where the data cannot tell scale from shift (a view whose overlaps are all one fronto-parallel plane).
    gauge = 0.5 * (Ai + Aj).mean(axis=0)
    x = _constrained_null_vector(A, gauge)
    for _ in range(2):
        x = _constrained_null_vector(A / magnitude(x)[:, None], gauge)
    res = (A @ x) / magnitude(x)
    x = x.reshape(n, n_unk)
    if kind == DepthKind.RELATIVE:
        scale, shift = x[:, 0], x[:, 1]
    else:
        scale, shift = x[:, 0], np.zeros(n)
    # Sign: inverse depths must come out positive where views see things.
    inv_med = np.nanmedian(np.concatenate([(c[0] @ xx)[c[1] > 0] for c, xx in zip(coarse, x)]))
    if inv_med < 0:
        x, scale, shift = -x, -scale, -shift
    rmse = float(np.sqrt(np.mean(res**2)))

    full = sample(height, width)
    num = np.zeros((height, width))
    den = np.zeros((height, width))
    for (feat, wgt), xx in zip(full, x):
        num += wgt * (feat @ xx)
        den += wgt
    inv = num / np.maximum(den, 1e-12)
    valid = (den > 0) & np.isfinite(inv) & (inv > 0)
    depth = np.where(valid, 1.0 / np.where(valid, inv, 1.0), 0.0)
    if kind == DepthKind.RELATIVE:
        g = np.median(depth[valid]) if valid.any() else 1.0
        depth, scale, shift = depth / g, scale * g, shift * g
    else:
        g = float(np.exp(np.mean(np.log(np.abs(scale)))))
        depth, scale = depth * g, scale / g
    return MergeResult(depth.astype(np.float32), valid, scale, shift, rmse)


def _constrained_null_vector(A: np.ndarray, gauge: np.ndarray, ridge: float = 1e-9) -> np.ndarray:
    """argmin |A x|^2 + ridge * tr(A^T A) / n * |x|^2 subject to gauge . x = 1 (a KKT solve)."""
    n = A.shape[1]
    M = A.T @ A
    M = M + ridge * np.trace(M) / n * np.eye(n)
    K = np.block([[2.0 * M, gauge[:, None]], [gauge[None, :], np.zeros((1, 1))]])
    rhs = np.zeros(n + 1)
    rhs[-1] = 1.0
    return np.linalg.solve(K, rhs)[:n]


def erp_depth_from_model(
    rgb: np.ndarray, predict: Callable[[np.ndarray], np.ndarray], kind: DepthKind, *, fov_deg: float = 110.0,
    view_size: int = 518, progress: bool = True,
) -> MergeResult:
    """Run a perspective depth model `predict(image (s, s, 3) uint8) -> (h, w)` on the six cube views of rgb
    (H, W, 3) and merge the results into an ERP depth (see merge_view_predictions)."""
    from panoworld.core.progress import bar

    H, W = rgb.shape[:2]
    views = cube_views(fov_deg, view_size)
    preds = [np.asarray(predict(render_view(rgb, v)), np.float32)
             for v in bar(views, desc="depth views", on=progress)]
    return merge_view_predictions(preds, views, H, W, kind)


