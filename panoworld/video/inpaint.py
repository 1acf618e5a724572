"""Weight-free disocclusion filling: a 3D background layer behind depth edges (warp-inpaint) and a per-frame 2D baseline."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from panoworld.core.conventions import (
    check_pose,
    dir_from_lonlat,
    erp_dirs,
    erp_lonlat_from_pixel,
    erp_pixel_from_dir,
    invert_pose,
)
from panoworld.core.progress import bar
from panoworld.core.shapes import check_shape
from panoworld.geometry.erp_mesh import ErpMesh
from panoworld.geometry.raycast import Hits
from panoworld.video.background_layer import BackgroundLayer, build_background_layer
from panoworld.video.erp_fill import erp_gaussian_blur, erp_inpaint

# ---------------------------------------------------------------- per-frame filling


@dataclass
class FilledFrame:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres, 0 where unknown
    filled_3d: np.ndarray  # (H, W) bool: hole pixels filled from the fill mesh (or reused from earlier frames)
    filled_2d: np.ndarray  # (H, W) bool: hole pixels filled by the 2D last resort
    source: np.ndarray | None = None  # (H, W, 3) uint8: the condition RGB it was filled from (the caller's array)


FOREGROUND_RATIO = 0.85
"""background_fill: a pixel nearer than this fraction of the background depth around a hole is foreground."""


def background_fill(rgb: np.ndarray, depth: np.ndarray, hole: np.ndarray, *, radius: float = 3.0, max_window: int = 129
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Depth-aware 2D fill of hole (H, W) in an ERP frame rgb (H, W, 3) uint8 with depth (H, W) metres (0 = unknown):
    the hidden surface continues the farther side of the hole, never its occluder. The hole's rim pixels within
    FOREGROUND_RATIO of the farthest rim depth around them (a window twice as wide as the holes, at most max_window)
    are its background; each hole pixel
    takes the depth and colour of the nearest background rim pixel (seam wrapped), the colour smoothed (Gaussian
    of sigma radius, seam-aware) over the hole and that rim only. Returns (rgb, depth) with only the hole changed;
    depth stays 0 where no rim has depth."""
    from scipy import ndimage

    hole = np.ascontiguousarray(hole, bool)
    H, W = hole.shape
    rows = np.flatnonzero(hole.any(axis=1))
    if not len(rows):
        return rgb.copy(), np.asarray(depth, np.float32).copy()
    # Only rows near the holes matter: the rim lies within a row of them and every filter below reaches a bounded
    # number of rows, so away from the poles the work runs on that band of full-width rows (the same result).
    r0, r1 = max(int(rows[0]) - 1, 0), min(int(rows[-1]) + 1, H - 1)
    thick = _max_distance(hole[r0:r1 + 1])  # half the widest hole's width
    window = int(min(4 * thick + 3, max_window))
    sigma = max(radius, 1.0)
    pad_y = int(np.ceil(3 * sigma)) + 1  # erp_gaussian_blur's padding across the poles
    reach = max(window // 2, int(np.ceil(4 * sigma))) + 2  # the maximum filter's and the blur kernel's half-widths
    a, b = r0 - reach - pad_y, r1 + reach + pad_y
    polar = a < 0 or b > H - 1 or W % 2  # near a pole: the whole frame, padded across the poles
    a, b = (0, H - 1) if polar else (a + pad_y, b - pad_y)
    band_hole = hole[a:b + 1]
    ring = (cv2.dilate(band_hole.view(np.uint8), np.ones((3, 3), np.uint8)) > 0) & ~band_hole & (depth[a:b + 1] > 0)
    if not ring.any():
        return erp_inpaint(rgb, hole, radius=radius), np.where(hole, 0.0, depth).astype(np.float32)
    out_rgb, out_d = rgb.copy(), np.asarray(depth, np.float32).copy()
    rgb, depth, hole = rgb[a:b + 1], depth[a:b + 1], band_hole
    far = ndimage.maximum_filter(np.where(ring, depth, 0.0), size=window, mode="wrap")
    bg_rim = ring & (depth >= FOREGROUND_RATIO * far)
    pad = W // 4
    padded = np.concatenate([~bg_rim[:, -pad:], ~bg_rim, ~bg_rim[:, :pad]], axis=1)
    ii, jj = ndimage.distance_transform_edt(padded, return_distances=False, return_indices=True)
    # Only the hole pixels read their nearest background rim pixel (hi, hj) -> (ii, jj).
    hi, hj = np.divmod(np.flatnonzero(hole), W)  # np.nonzero(hole), ~4x faster
    ii, jj = ii[hi, hj + pad], (jj[hi, hj + pad] - pad) % W
    fill_d = np.asarray(depth, np.float32).copy()
    fill_d[hi, hj] = depth[ii, jj]
    # colour: the nearest background rim pixel's, smoothed over the hole and that rim only (never the occluder)
    known = (hole | bg_rim).astype(np.float32)
    col = rgb.astype(np.float32)
    col[hi, hj] = rgb[ii, jj]
    col *= known[..., None]
    num, den = (erp_gaussian_blur(x, sigma, across_poles=polar) for x in (col, known))
    smooth = num[hi, hj] / np.maximum(den[hi, hj], 1e-6)[..., None]
    out_rgb[a + hi, hj] = np.clip(np.rint(smooth), 0, 255).astype(np.uint8)
    out_d[a:b + 1] = fill_d
    return out_rgb, out_d


def _max_distance(mask: np.ndarray) -> float:
    """The largest Euclidean distance (pixels) of a True pixel of mask (h, w) bool from the nearest False one, as
    scipy.ndimage.distance_transform_edt(mask).max() gives it (OpenCV's exact transform, ~10x faster, is off by up
    to ~1e-5 px: its squared distance is rounded back to the integer it is)."""
    if mask.all() or not mask.any():
        from scipy import ndimage

        return float(ndimage.distance_transform_edt(mask).max())
    d = cv2.distanceTransform(mask.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return float(np.sqrt(np.rint(np.float64(d.max()) ** 2)))


class CommittedPoints:
    """World points (colour) that 2D fills committed: later frames reuse them before filling anew, so content
    invented once keeps its place and colour along the path (temporal reuse of what the video already showed)."""

    def __init__(self) -> None:
        self._xyz: list[np.ndarray] = []
        self._rgb: list[np.ndarray] = []

    def add(self, world_from_cam: np.ndarray, pixels: np.ndarray, depth: np.ndarray, rgb: np.ndarray, H: int, W: int
            ) -> None:
        """Commit the flat pixel indices `pixels` of an ERP frame (H, W) at pose world_from_cam with their depth (M,)
        metres and colours (M, 3); pixels without depth are skipped."""
        ok = depth > 0
        if not ok.any():
            return
        dirs = erp_dirs(H, W, np.float64).reshape(-1, 3)[pixels[ok]]
        T = np.asarray(world_from_cam, np.float64)
        self._xyz.append((dirs * depth[ok, None]) @ T[:3, :3].T + T[:3, 3])
        self._rgb.append(rgb[ok])

    def project(self, world_from_cam: np.ndarray, H: int, W: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The nearest committed point of each ERP pixel at pose world_from_cam: (flat pixel indices, depth, rgb)."""
        if not self._xyz:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3), np.uint8)
        xyz, rgb = np.concatenate(self._xyz), np.concatenate(self._rgb)
        self._xyz, self._rgb = [xyz], [rgb]
        T = invert_pose(np.asarray(world_from_cam, np.float64))
        p = xyz @ T[:3, :3].T + T[:3, 3]
        dist = np.linalg.norm(p, axis=1)
        u, v = erp_pixel_from_dir(p / np.maximum(dist, 1e-12)[:, None], H, W)
        pix = np.clip(np.floor(v).astype(np.int64), 0, H - 1) * W + np.mod(np.floor(u).astype(np.int64), W)
        order = np.lexsort((dist, pix))
        first = np.unique(pix[order], return_index=True)[1]
        k = order[first]
        return pix[k], dist[k], rgb[k]


def _check_frame(rgb: np.ndarray, mask: np.ndarray, depth: np.ndarray | None) -> None:
    dims = check_shape("rgb", rgb, "H W 3", dtype=np.uint8)
    check_shape("mask", mask, "H W", dims=dims)
    if depth is not None:
        check_shape("depth", depth, "H W", dims=dims)


def erp_dir_at(u: np.ndarray, v: np.ndarray, height: int, width: int) -> np.ndarray:
    """Camera-frame unit directions (N, 3) of continuous ERP pixel coordinates u, v (N,)."""
    return dir_from_lonlat(*erp_lonlat_from_pixel(u, v, height, width))


class WarpInpainter:
    """Fills the holes of conditions frames by casting their rays against a BackgroundLayer (same surface, same
    colour in every frame); rays that hit nothing get the depth-aware 2D fill (background_fill: the far side's depth
    and colour) when the frame has depth and depth_fill, else the colour-only seam-aware 2D fill."""

    def __init__(self, layer: BackgroundLayer, *, inpaint_radius: float = 3.0, reuse: bool = False, depth_fill: bool = True):
        self.layer = layer
        self.depth_fill = depth_fill
        self.inpaint_radius = inpaint_radius
        self._rc = layer.raycaster().build() if len(layer.faces) else None  # built: fill may run on threads
        self._colors = layer.colors.astype(np.float32)
        self.committed = CommittedPoints() if reuse else None
        self._trig: dict[tuple, tuple[np.ndarray, ...]] = {}  # (H, W, du, dv) -> per-row and per-column sines/cosines

    def _dirs_at(self, ti: np.ndarray, tj: np.ndarray, H: int, W: int, du: float = 0.0, dv: float = 0.0) -> np.ndarray:
        """erp_dir_at(tj + 0.5 + du, ti + 0.5 + dv, H, W), the same numbers, from per-row and per-column tables."""
        key = (H, W, du, dv)
        if key not in self._trig:
            lon, lat = erp_lonlat_from_pixel(np.arange(W) + 0.5 + du, np.arange(H) + 0.5 + dv, H, W)
            self._trig[key] = (np.cos(lat), np.sin(lat), np.sin(lon), np.cos(lon))
        cos_lat, sin_lat, sin_lon, cos_lon = self._trig[key]
        cl = cos_lat[ti]
        return np.stack([cl * sin_lon[tj], -sin_lat[ti], cl * cos_lon[tj]], axis=-1)

    def fill(self, rgb: np.ndarray, mask: np.ndarray, depth: np.ndarray | None, world_from_cam: np.ndarray) -> FilledFrame:
        """rgb (H, W, 3) uint8, mask (H, W) bool (True = valid condition), depth (H, W) metres or None, pose 4x4."""
        _check_frame(rgb, mask, depth)
        check_pose(world_from_cam, "world_from_cam")
        H, W = mask.shape
        hole = ~mask.astype(bool)
        out = rgb.copy()
        out_d = np.where(mask, depth, 0.0).astype(np.float32) if depth is not None else np.zeros((H, W), np.float32)
        filled = np.zeros((H, W), bool)
        if hole.any() and self._rc is not None:
            ti, tj = np.divmod(np.flatnonzero(hole), W)  # the hole pixels not filled yet (np.nonzero's order)
            origin = np.asarray(world_from_cam)[:3, 3][None]
            R = np.asarray(world_from_cam)[:3, :3]
            # Rays through a vertex or edge can slip between triangles: retry those at sub-pixel offsets.
            # einsum, not @: the (M, 3) x (3, 3) product through the multithreaded BLAS leaves its threads spinning
            # beside the other fill thread and the encoders (~10 % of the stage's CPU).
            for du, dv in ((0.0, 0.0), (0.25, 0.25), (-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25)):
                if not len(ti):
                    break
                dirs = np.einsum("mi,ji->mj", self._dirs_at(ti, tj, H, W, du, dv), R)
                hits = self._rc.cast(origin, dirs)
                ok = hits.face >= 0
                px = ti[ok] * W + tj[ok]
                col = self._rc.interpolate(Hits(hits.distance[ok], hits.face[ok], hits.bary[ok]), self._colors)
                out.reshape(-1, 3)[px] = np.clip(np.rint(col), 0, 255).astype(np.uint8)
                out_d.reshape(-1)[px] = hits.distance[ok]
                filled.reshape(-1)[px] = True
                ti, tj = ti[~ok], tj[~ok]
        rest = hole & ~filled
        if self.committed is not None and rest.any() and not rest.all():
            pix, dist, col = self.committed.project(world_from_cam, H, W)
            use = rest.reshape(-1)[pix]
            out.reshape(-1, 3)[pix[use]] = col[use]
            out_d.reshape(-1)[pix[use]] = dist[use]
            filled.reshape(-1)[pix[use]] = True
            rest = hole & ~filled
            if rest.any() and not rest.all():
                out, out_d = background_fill(out, out_d, rest, radius=self.inpaint_radius)
                px = np.flatnonzero(rest)
                self.committed.add(world_from_cam, px, out_d.reshape(-1)[px], out.reshape(-1, 3)[px], H, W)
        elif rest.any() and not rest.all() and self.depth_fill and depth is not None:
            out, out_d = background_fill(out, out_d, rest, radius=self.inpaint_radius)
            if self.layer.floor_map is not None:
                self._paint_planes(out, out_d, rest, world_from_cam)
        elif rest.any() and not rest.all():
            out = erp_inpaint(out, rest, radius=self.inpaint_radius)
        return FilledFrame(out, out_d, filled, rest, rgb)


    def _paint_planes(self, out: np.ndarray, out_d: np.ndarray, rest: np.ndarray, world_from_cam: np.ndarray) -> None:
        """The 2D-filled pixels rest (H, W) of out (H, W, 3) whose depth out_d puts them on the floor beyond the
        room's shell take the floor map's colour (in place)."""
        H, W = rest.shape
        ti, tj = np.divmod(np.flatnonzero(rest & (out_d > 0)), W)
        pose = np.asarray(world_from_cam, np.float64)
        pts = pose[:3, 3] + np.einsum("mi,ji->mj", self._dirs_at(ti, tj, H, W), pose[:3, :3]) * out_d[ti, tj, None]
        out[ti, tj] = self.layer.floor_map.paint(pts, out[ti, tj])[0]


def frame_inpaint(
    rgb: np.ndarray, mask: np.ndarray, depth: np.ndarray | None = None, *, radius: float = 3.0
) -> FilledFrame:
    """Per-frame baseline: seam-aware Telea inpainting of the holes (mask False) of one frame, colour and depth."""
    _check_frame(rgb, mask, depth)
    hole = ~mask.astype(bool)
    if hole.all():
        raise ValueError("frame_inpaint: the frame has no valid pixel to fill from")
    out = erp_inpaint(rgb, hole, radius=radius)
    if depth is not None:
        d = np.where(hole, 0.0, depth).astype(np.float32)
        out_d = erp_inpaint(d, hole, radius=radius)
    else:
        out_d = np.zeros(mask.shape, np.float32)
    return FilledFrame(out, out_d.astype(np.float32), np.zeros(mask.shape, bool), hole, rgb)


def max_translation(poses: np.ndarray) -> float:
    """Largest distance (metres) of any camera centre of poses (N, 4, 4) from the source camera (the origin)."""
    poses = np.asarray(poses)
    check_shape("poses", poses, "N 4 4")
    return float(np.linalg.norm(poses[:, :3, 3], axis=1).max()) if len(poses) else 0.0


def warp_inpaint_video(
    rgb: np.ndarray,
    mask: np.ndarray,
    depth: np.ndarray | None,
    poses: np.ndarray,
    mesh: ErpMesh,
    *,
    max_band_deg: float = 45.0,
    inpaint_radius: float = 3.0,
    progress: bool = True,
) -> tuple[list[FilledFrame], BackgroundLayer]:
    """Fill conditions rgb (T, H, W, 3) uint8 / mask (T, H, W) bool / depth (T, H, W) at poses (T, 4, 4) from
    one background layer built from the source mesh (see build_background_layer)."""
    dims = check_shape("rgb", rgb, "T H W 3")
    check_shape("mask", mask, "T H W", dims=dims)
    check_shape("poses", poses, "T 4 4", dims=dims)
    layer = build_background_layer(
        mesh, max_translation(poses), max_band_deg=max_band_deg, inpaint_radius=inpaint_radius
    )
    filler = WarpInpainter(layer, inpaint_radius=inpaint_radius)
    frames = [
        filler.fill(rgb[t], mask[t], None if depth is None else depth[t], poses[t])
        for t in bar(range(len(rgb)), desc="warp-inpaint", leave=False, on=progress)
    ]
    return frames, layer
