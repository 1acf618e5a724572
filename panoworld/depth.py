"""ERP metric depth: reading provided depth, hole filling, perspective-view merging of monocular depth, floor-based metric scale."""

from __future__ import annotations

import enum
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from scipy.sparse import linalg as sparse_linalg
from scipy.spatial.transform import Rotation

from panoworld.choices import Rescale
from panoworld.conventions import erp_dirs, erp_pixel_from_dir, erp_pixel_solid_angle, points_from_depth
from panoworld.errors import InputError
from panoworld.image_io import read_image
from panoworld.limits import depth_plane, load_npy


class DepthKind(enum.StrEnum):
    """What a monocular depth model predicts for a perspective view."""

    RELATIVE = "relative"
    """Affine-invariant inverse depth (disparity up to an unknown scale and shift), e.g. Depth Anything V2."""
    METRIC = "metric"
    """Metric z-depth along the optical axis, up to a small per-view scale error."""


# ---------------------------------------------------------------- files


def read_panorama(path: Path, notes: list[str] | None = None) -> np.ndarray:
    """Read an ERP panorama -> RGB uint8 (H, W, 3); InputError if unreadable or not 2:1.

    Grayscale, RGBA (alpha dropped), 16-bit (scaled to 8 bit) and EXIF-rotated JPEGs (orientation applied) are
    accepted; what was converted is appended to notes.
    """
    path = Path(path)
    notes = [] if notes is None else notes
    img = read_image(path, cv2.IMREAD_UNCHANGED, what="panorama")
    gray = img.ndim == 2 or img.shape[2] == 1
    if path.suffix.lower() in (".jpg", ".jpeg") and img.dtype == np.uint8:
        # IMREAD_UNCHANGED ignores the EXIF orientation; IMREAD_COLOR applies it (same decoder otherwise).
        oriented = cv2.imread(str(path), cv2.IMREAD_COLOR)
        plain = img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        if oriented is not None and (oriented.shape != plain.shape or not np.array_equal(oriented, plain)):
            img = oriented
            notes.append("EXIF orientation applied")
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
        notes.append("16-bit panorama scaled to 8 bit")
    if img.dtype != np.uint8:
        raise InputError(f"{path}: panorama has dtype {img.dtype}; give an 8- or 16-bit PNG/JPEG")
    if gray:
        notes.append("grayscale panorama expanded to RGB")
    if img.ndim == 2 or img.shape[2] == 1:
        img = cv2.cvtColor(img.reshape(img.shape[:2]), cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        notes.append("alpha channel dropped")
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    H, W = img.shape[:2]
    if W != 2 * H:
        raise InputError(
            f"{path}: panorama is {W}x{H} (WxH) but an equirectangular panorama must be 2:1; give a full 360x180 ERP image"
        )
    return img


def working_size(height: int, max_height: int) -> tuple[int, int]:
    """(H, W) the pipeline works at: the panorama's, or max_height x 2 max_height when it is taller (0 = no limit)."""
    if max_height <= 0 or height <= max_height:
        return height, 2 * height
    return max_height, 2 * max_height


def resize_panorama(rgb: np.ndarray, height: int) -> np.ndarray:
    """Area-average an ERP panorama (H, W, 3) down to (height, 2 height, 3)."""
    if rgb.shape[0] == height:
        return rgb
    return cv2.resize(rgb, (2 * height, height), interpolation=cv2.INTER_AREA)


def read_depth(path: Path, *, png_scale: float = 0.001) -> np.ndarray:
    """Read a depth map (H, W) as float32 in file units times scale; NaN/inf/<=0 are kept (they mark invalid pixels).

    `.npy`: float array, metres. `.exr`: first channel, metres (OpenCV with OpenEXR, else the `OpenEXR` package).
    `.png`: 16-bit, metres = value * png_scale (0.001 for millimetres; Matterport-style 1/4000 m per unit is
    png_scale=0.00025; Realsee-style PNGs store value / depth_scale with a per-view scale). Extra channels are dropped.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise InputError(f"{path}: depth file not found")
    if suffix == ".npy":
        depth = load_npy(path, "depth array", kinds="fiu")
    elif suffix == ".exr":
        depth = _read_exr(path)
    elif suffix == ".png":
        depth = read_image(path, cv2.IMREAD_UNCHANGED, what="depth PNG")
        if depth.dtype != np.uint16:
            raise InputError(
                f"{path}: depth PNG is {depth.dtype}; an 8-bit PNG cannot hold depth, save 16-bit (value * png_scale = metres)"
            )
        depth = depth.astype(np.float32) * np.float32(png_scale)
    else:
        raise InputError(f"{path}: unsupported depth format {suffix!r}; give depth.npy, depth.exr or a 16-bit depth.png")
    depth = depth_plane(depth, path)
    return np.asarray(depth, dtype=np.float32)


def _read_exr(path: Path) -> np.ndarray:
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    try:
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    except cv2.error:
        depth = None
    if depth is not None:
        return depth
    try:
        import OpenEXR
    except ImportError:
        raise InputError(
            f"{path}: cannot read EXR (this OpenCV has no OpenEXR and the OpenEXR package is missing); "
            "pip install OpenEXR, or save depth.npy"
        ) from None
    try:
        with OpenEXR.File(str(path)) as f:
            channels = f.channels()
            name = next(c for c in ("Z", "Y", "R", "depth") if c in channels) if channels else None
            if name is None:
                name = next(iter(channels))
            return np.asarray(channels[name].pixels, dtype=np.float32)
    except Exception as e:  # OpenEXR raises plain exceptions for corrupt files
        raise InputError(f"{path}: cannot read the EXR depth ({e})") from None


def load_depth_artifact(artifact_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a depth artifact dir -> (depth (H, W) float32 metres, valid (H, W) bool, rgb (H, W, 3) uint8)."""
    artifact_dir = Path(artifact_dir)
    depth = np.load(artifact_dir / "depth.npy")
    valid = cv2.imread(str(artifact_dir / "valid.png"), cv2.IMREAD_GRAYSCALE) > 127
    rgb = cv2.cvtColor(cv2.imread(str(artifact_dir / "panorama.png"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return depth, valid, rgb


def valid_depth_mask(depth: np.ndarray) -> np.ndarray:
    """Valid = finite and > 0, shape (H, W) bool."""
    return np.isfinite(depth) & (depth > 0)


def conform_depth(depth: np.ndarray, height: int, width: int, what: str = "depth") -> tuple[np.ndarray, str | None]:
    """Resize depth (h, w) to the panorama's (height, width) with nearest sampling (invalid pixels never blend into
    valid ones); the aspect must match. Returns (depth, note) where note describes the resize (None if none)."""
    h, w = depth.shape
    if (h, w) == (height, width):
        return depth, None
    if w * height != h * width:
        raise InputError(
            f"{what}: depth is {w}x{h} but the panorama is {width}x{height} (WxH), a different aspect; "
            "give a 2:1 ERP depth map aligned with the panorama"
        )
    out = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST_EXACT)
    return out, f"depth resized from {w}x{h} to {width}x{height} (nearest)"


def fill_small_holes(
    depth: np.ndarray, valid: np.ndarray, max_hole_px: int, max_gap_px: int = 0
) -> tuple[np.ndarray, np.ndarray, int]:
    """Fill small holes harmonically in inverse depth; larger invalid regions stay invalid.

    Filled: invalid components of at most max_hole_px pixels (found with the seam wrapped), and invalid pixels in
    a run of at most max_gap_px pixels between valid ones along a row or a column (the gaps between the scan lines
    of sparse LiDAR; interpolation only, never extrapolation past the rim of a dropout).
    depth (H, W), valid (H, W) bool -> (depth with 0 where still invalid, valid, number of pixels filled).
    """
    holes = ~valid
    if not holes.any() or not valid.any() or (max_hole_px <= 0 and max_gap_px <= 0):
        return np.where(valid, depth, 0).astype(np.float32), valid, 0
    fill = np.zeros_like(holes)
    if max_hole_px > 0:
        labels, n = ndimage.label(holes)
        # Merge components that meet across the seam (left and right border pixels of the same row).
        both = (labels[:, 0] > 0) & (labels[:, -1] > 0)
        seam = sparse.coo_matrix((np.ones(int(both.sum())), (labels[both, 0], labels[both, -1])), shape=(n + 1, n + 1))
        _, comp = csgraph.connected_components(seam, directed=False)
        labels = comp[labels]
        sizes = np.bincount(labels[holes], minlength=labels.max() + 1)
        fill |= holes & (sizes[labels] <= max_hole_px)
    if max_gap_px > 0:
        fill |= holes & (wrapped_gap_lengths(valid) <= max_gap_px)
    if not fill.any():
        return np.where(valid, depth, 0).astype(np.float32), valid, 0
    inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    filled = _harmonic_fill(inv, fill, valid)
    out_valid = valid | fill
    out = np.where(valid, depth, np.where(fill, 1.0 / np.maximum(filled, 1e-12), 0.0)).astype(np.float32)
    return out, out_valid, int(fill.sum())


def wrapped_gap_lengths(valid: np.ndarray) -> np.ndarray:
    """Per pixel of valid (H, W): the shorter of the invalid runs it lies in along its row (seam wrapped) and its
    column, each bounded by valid pixels on both sides (see _gap_lengths; huge where unbounded or valid)."""
    W = valid.shape[1]
    row_gap = _gap_lengths(np.concatenate([valid[:, -W // 2:], valid, valid[:, : W // 2]], axis=1))
    return np.minimum(row_gap[:, W // 2: W // 2 + W], _gap_lengths(valid.T).T)


def auto_gap_px(
    valid: np.ndarray, *, max_px: int = 8, min_share: float = 0.3, cover: float = 0.9, min_invalid: float = 0.05
) -> tuple[int, float]:
    """Scan-line gap width to interpolate for depth validity valid (H, W): (max_gap_px, share of short gaps).

    Sparse LiDAR leaves most invalid pixels in short runs between valid ones; dense depth with dropouts or
    blind bands does not. When at least min_share of the invalid pixels lie in runs of <= max_px pixels (along a
    row or a column), returns the smallest width whose runs hold `cover` of those pixels, else 0 (no filling).
    Depth with less than min_invalid of its pixels invalid is dense: 0.
    """
    holes = ~valid
    if holes.mean() < min_invalid or not valid.any():
        return 0, 0.0
    g = wrapped_gap_lengths(valid)[holes]
    short = g <= max_px
    share = float(short.mean())
    if share < min_share:
        return 0, share
    counts = np.bincount(g[short], minlength=max_px + 1)
    width = int(np.searchsorted(np.cumsum(counts), cover * short.sum()))
    return max(width, 1), share


def _gap_lengths(valid: np.ndarray) -> np.ndarray:
    """Length of the run of invalid pixels each pixel lies in along axis 1, bounded by valid pixels on both sides;
    a huge number where a run reaches the array's border or the pixel is valid."""
    n = valid.shape[1]
    j = np.arange(n)
    left = np.maximum.accumulate(np.where(valid, j, -(10 * n)), axis=1)
    right = np.minimum.accumulate(np.where(valid, j, 11 * n)[:, ::-1], axis=1)[:, ::-1]
    return np.where(valid, 10 * n, right - left - 1)


def _harmonic_fill(values: np.ndarray, fill: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Solve Laplace's equation on the pixels fill (H, W) with their known (H, W) 4-neighbours' values (H, W) as
    boundary values; other neighbours are left out (a free boundary). Seam wrapped, rows clamped; each fill
    component must touch a known pixel. Returns values with the fill pixels solved."""
    H, W = values.shape
    n = int(fill.sum())
    idx = np.full((H, W), -1, np.int64)
    idx[fill] = np.arange(n)
    ii, jj = np.nonzero(fill)
    rows, cols, diag = [], [], np.zeros(n)
    rhs = np.zeros(n)
    for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        ni, nj = ii + di, (jj + dj) % W
        inside = (ni >= 0) & (ni < H)
        p, ni, nj = np.nonzero(inside)[0], ni[inside], nj[inside]
        q = idx[ni, nj]
        unknown = q >= 0
        fixed = known[ni, nj]
        np.add.at(diag, p[unknown | fixed], 1.0)
        rows.append(p[unknown])
        cols.append(q[unknown])
        np.add.at(rhs, p[fixed], values[ni[fixed], nj[fixed]])
    r = np.concatenate(rows + [np.arange(n)])
    c = np.concatenate(cols + [np.arange(n)])
    v = np.concatenate([-np.ones(len(r) - n), diag])
    A = sparse.csr_matrix((v, (r, c)), shape=(n, n))
    out = values.astype(np.float64).copy()
    # Every unknown is near known pixels, so Jacobi-preconditioned CG converges in few iterations.
    x, info = sparse_linalg.cg(A, rhs, rtol=1e-9, maxiter=5000, M=sparse.diags(1.0 / diag))
    out[fill] = x if info == 0 else sparse_linalg.spsolve(A.tocsc(), rhs)
    return out


# ---------------------------------------------------------------- metric scale


@dataclass
class FloorFit:
    """Horizontal floor plane below the camera found in an ERP depth map."""

    camera_height: float
    """Distance from the camera centre down to the floor plane, in the depth map's units."""
    support: float
    """Fraction of the downward-looking valid solid angle whose points lie on the fitted floor."""


def estimate_floor(
    depth: np.ndarray, valid: np.ndarray, *, min_below_deg: float = 15.0, max_tilt_deg: float = 15.0, bin_rel: float = 0.01
) -> FloorFit | None:
    """Fit the floor (a horizontal plane y = h > 0, up = -Y) to an ERP depth map (H, W) with validity (H, W).

    Points seen at least min_below_deg below the horizon whose local normal is within max_tilt_deg of vertical
    vote, weighted by surface area, in a histogram of log y (bins of bin_rel relative width); among the peaks
    holding at least half of the strongest bin's weight the lowest wins (furniture tops lie above the floor),
    refined by the weighted median of its inliers. None if no such horizontal surface exists.
    """
    H, W = depth.shape
    pts = points_from_depth(np.where(valid, depth, 0.0))
    dirs = erp_dirs(H, W, dtype=np.float64)
    # Central differences with the seam wrapped; rows clamp at the poles.
    dx = np.roll(pts, -1, axis=1) - np.roll(pts, 1, axis=1)
    up = np.concatenate([pts[:1], pts[:-1]])
    down = np.concatenate([pts[1:], pts[-1:]])
    n = np.cross(dx, down - up)
    nn = np.linalg.norm(n, axis=-1)
    ok = valid & np.roll(valid, 1, 1) & np.roll(valid, -1, 1)
    ok[1:] &= valid[:-1]
    ok[:-1] &= valid[1:]
    ok &= nn > 0
    cos_vert = np.abs(n[..., 1]) / np.maximum(nn, 1e-30)
    below = dirs[..., 1] > np.sin(np.deg2rad(min_below_deg))
    y = pts[..., 1]
    sel = ok & below & (cos_vert >= np.cos(np.deg2rad(max_tilt_deg))) & (y > 0)
    omega = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    down_total = omega[below & valid].sum()
    if sel.sum() < 20 or down_total <= 0:
        return None
    cos_inc = np.clip(np.abs(dirs[..., 1]), 0.05, 1.0)  # ray vs vertical normal
    area = (omega * depth**2 / cos_inc)[sel]
    ly = np.log(y[sel])
    lo, hi = ly.min(), ly.max()
    nb = max(1, int(np.ceil((hi - lo) / bin_rel)) + 1)
    hist, edges = np.histogram(ly, bins=nb, range=(lo, lo + nb * bin_rel), weights=area)
    # Smooth with the ends padded ('same' mode would return 3 bins for a 1- or 2-bin histogram: planar layouts).
    hist = np.convolve(np.pad(hist, 1), [0.25, 0.5, 0.25], mode="valid")
    strong = np.nonzero(hist >= 0.5 * hist.max())[0]
    peak = strong.max()
    ly_peak = 0.5 * (edges[peak] + edges[peak + 1])
    inl = np.abs(ly - ly_peak) <= 2.0 * bin_rel
    order = np.argsort(ly[inl])
    cw = np.cumsum(area[inl][order])
    h = float(np.exp(ly[inl][order][np.searchsorted(cw, 0.5 * cw[-1])]))
    on_floor = np.abs(y - h) <= 0.02 * h
    support = float(omega[on_floor & below & valid].sum() / down_total)
    return FloorFit(camera_height=h, support=support)


# ---------------------------------------------------------------- perspective views


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
    u, v = erp_pixel_from_dir(view.rays(), H, W)
    # One wrapped column each side and one replicated row top/bottom, so remap never reads past the seam.
    padded = np.concatenate([rgb[:, -1:], rgb, rgb[:, :1]], axis=1)
    padded = np.concatenate([padded[:1], padded, padded[-1:]], axis=0)
    return cv2.remap(padded, (u + 0.5).astype(np.float32), (v + 0.5).astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


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
    from tqdm import tqdm

    H, W = rgb.shape[:2]
    views = cube_views(fov_deg, view_size)
    preds = [np.asarray(predict(render_view(rgb, v)), np.float32)
             for v in tqdm(views, desc="depth views", disable=not progress)]
    return merge_view_predictions(preds, views, H, W, kind)


# ---------------------------------------------------------------- metric scale policy


PLAUSIBLE_CAMERA_HEIGHT = (0.2, 5.0)
"""Floor distances (m) accepted for depth taken as metric (rescale relative-only): outside it is an error."""
CAPTURE_CAMERA_HEIGHT = (0.9, 2.4)
"""Floor distances (m) of handheld and tripod indoor captures: rescale auto takes provided depth whose floor lies
outside this range as being in unknown units (raw sensor values, a wrong PNG scale) and rescales it."""


def metric_rescale(
    depth: np.ndarray, valid: np.ndarray, *, relative: bool, rescale: Rescale, camera_height: float
) -> tuple[np.ndarray, dict]:
    """Rescale depth (H, W) by camera_height / estimated floor distance when the policy asks for it.

    auto: relative depth always; provided or metric depth when its floor lies outside CAPTURE_CAMERA_HEIGHT
    (unknown units); depth without a visible floor is kept as given (relative depth then has an arbitrary scale,
    said in info["scale_note"]). Returns (depth, info) with the estimated camera height before and after (None
    when no floor is found), the factor applied and why. InputError if a rescale is required (always,
    relative-only on relative depth) but no floor is visible, or if relative-only takes depth as metric whose
    floor lies outside PLAUSIBLE_CAMERA_HEIGHT (wrong units).
    """
    fit = estimate_floor(depth, valid)
    if not camera_height > 0:
        raise InputError(f"--camera-height {camera_height} must be > 0 metres")
    note = None
    if rescale == Rescale.AUTO:
        if fit is None:
            do = False
            note = "no floor visible: depth kept as given" + (" (relative: arbitrary scale)" if relative else "")
        elif relative:
            do, note = True, "relative depth: floor put at camera_height"
        else:
            lo, hi = CAPTURE_CAMERA_HEIGHT
            do = not lo <= fit.camera_height <= hi
            note = (f"floor {fit.camera_height:.4g} units below the camera, outside {lo}-{hi} m: unknown units, "
                    "floor put at camera_height" if do else f"floor {fit.camera_height:.3f} m below the camera: metric")
    else:
        do = rescale == Rescale.ALWAYS or (rescale == Rescale.RELATIVE_ONLY and relative)
    factor = 1.0
    if do:
        if fit is None:
            raise InputError(
                "no horizontal floor found below the camera, so depth cannot be put to metric scale; "
                "pass --rescale never (and metric depth) or a panorama that shows the floor"
            )
        factor = camera_height / fit.camera_height
    elif rescale == Rescale.RELATIVE_ONLY and fit is not None and not PLAUSIBLE_CAMERA_HEIGHT[0] <= fit.camera_height <= PLAUSIBLE_CAMERA_HEIGHT[1]:
        raise InputError(
            f"depth units look wrong: the floor is {fit.camera_height:.4g} units below the camera, not "
            f"{PLAUSIBLE_CAMERA_HEIGHT[0]}-{PLAUSIBLE_CAMERA_HEIGHT[1]} m; if the depth is not in metres pass "
            "--rescale always --camera-height H (or the right --png-scale), or --rescale never to keep it as is"
        )
    info = {
        "camera_height_estimated_before": fit.camera_height if fit else None,
        "camera_height_estimated_after": fit.camera_height * factor if fit else None,
        "floor_support": fit.support if fit else None,
        "rescaled": do,
        "scale_factor": factor,
    }
    if note:
        info["scale_note"] = note
    return (depth * np.float32(factor)).astype(np.float32), info
