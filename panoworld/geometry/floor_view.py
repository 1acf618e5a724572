"""An upright panorama's floor seen from above at metric scale (camera height from its depth), its SIFT keypoints, and
the matches of two such views that agree with a pose."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from panoworld.core.conventions import erp_dirs64, erp_pixel_from_lonlat
from panoworld.core.shapes import check_shape
from panoworld.geometry.upright import wrap_angle, yaw_matrix_xz, yaw_of


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


def camera_height(depth: np.ndarray, *, min_depression_deg: float = 40.0) -> float | None:
    """Camera height above the floor from the ray depth (H, W) below min_depression_deg under the horizon
    (plane_distance). None when no valid depth is there."""
    return plane_distance(depth, below=True, min_angle_deg=min_depression_deg)


def plane_distance(depth: np.ndarray, *, below: bool, min_angle_deg: float = 40.0) -> float | None:
    """Distance of the floor (below) or the ceiling (above) from the camera, from the ray depth (H, W) more than
    min_angle_deg under (over) the horizon: the most common vertical distance there (a histogram of depth times the
    ray's vertical component in bins of 1 % of its median, the median of the distances within two bins of the peak),
    so walls within that cone (a closet, a hallway, a doorway) do not shorten it. None when no valid depth is there."""
    check_shape("depth", depth, "H W")
    h, w = depth.shape
    vertical = erp_dirs64(h, w)[..., 1] * (1.0 if below else -1.0)
    sel = (vertical > np.sin(np.radians(min_angle_deg))) & np.isfinite(depth) & (depth > 0)
    if sel.sum() < 0.01 * sel.size:
        return None
    y = depth[sel] * vertical[sel]
    step = 0.01 * float(np.median(y))
    if not step > 0:
        return float(np.median(y))
    top = min(float(y.max()), 1000 * step)  # at most 1,000 bins: a far outlier (a hole, a stairwell) widens nothing
    hist, edges = np.histogram(y, bins=max(1, int(np.ceil((top - y.min()) / step))), range=(y.min(), top))
    k = int(np.argmax(np.convolve(np.pad(hist, 1), [1, 2, 1], "valid")))
    peak = 0.5 * (edges[k] + edges[k + 1])
    return float(np.median(y[np.abs(y - peak) <= 2 * step]))


def floor_image(rgb: np.ndarray, height_m: float, *, radius_m: float, cell_m: float, turn: float = 0.0,
                supersample: int = 1) -> np.ndarray:
    """(n, n, 3) uint8 top-down image of the plane height_m below the camera over x, z in [-radius_m, radius_m]
    (column = x, row 0 = far +z) of the camera turned by `turn` (radians, about gravity: image point (x, z) lies at
    yaw_matrix_xz(turn) @ (x, z) in the camera frame), resampled from the ERP panorama rgb (H, 2H, 3) (or (n, n) from an
    (H, 2H) image): bilinear at supersample x supersample points per cell, averaged (near the camera a cell spans
    several panorama pixels, and one bilinear sample per cell aliases the floor's texture)."""
    n = int(round(2 * radius_m / cell_m))
    k = int(supersample)
    dt = np.float64 if k == 1 else np.float32  # the supersampled grid is large; float32 is 1e-4 pixel here
    c = ((np.arange(n * k) + 0.5) * (cell_m / k) - radius_m).astype(dt)
    x, z = np.meshgrid(c, c[::-1])
    lon, lat = np.arctan2(x, z) + dt(turn), np.arctan2(dt(-height_m), np.hypot(x, z))
    hi, wi = rgb.shape[:2]
    pad = 4
    padded = np.concatenate([rgb[:, -pad:], rgb, rgb[:, :pad]], 1)  # the seam wraps
    u, v = erp_pixel_from_lonlat(lon, lat, hi, wi)  # pixel centres at +0.5; OpenCV's remap at integers
    img = cv2.remap(padded, (u - 0.5 + pad).astype(np.float32), (v - 0.5).astype(np.float32), cv2.INTER_LINEAR)
    return img if k == 1 else cv2.resize(img, (n, n), interpolation=cv2.INTER_AREA)


def floor_view(rgb: np.ndarray, depth: np.ndarray, *, radius_m: float = 6.0, cell_m: float = 0.015,
               rig_deg: float = 32.0, max_features: int = 4000, exclude: np.ndarray | None = None,
               turn: float = 0.0, supersample: int = 1) -> FloorView | None:
    """SIFT keypoints of the floor image of an upright panorama rgb (H, 2H, 3) with ray depth (h, 2h) (camera height;
    0 = invalid). The whole lower hemisphere is projected onto the floor plane, walls included (they smear radially
    and find no consistent partner), so floor seen through a doorway that a layout depth closes is kept; the disc
    within rig_deg of the nadir (the tripod) is masked, and so is what exclude (an ERP mask (H', 2H') bool, e.g. a
    detected rig) covers. The image's axes are the camera's turned by `turn` (radians; the keypoints are returned in
    the camera's frame): SIFT finds the same keypoints again under quarter turns of an image far more often than under
    other turns, so floor images whose axes follow their rooms' walls match better than ones that follow where each
    panorama's seam fell. supersample: floor_image's samples per cell side. None without a camera height."""
    check_shape("panorama", rgb, "H W 3")
    h = camera_height(depth)
    if h is None or not np.isfinite(h) or h <= 0:
        return None
    img = floor_image(rgb, h, radius_m=radius_m, cell_m=cell_m, turn=turn, supersample=supersample)
    gray = cv2.createCLAHE(2.0, (8, 8)).apply(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
    n = gray.shape[0]
    c = (np.arange(n) + 0.5) * cell_m - radius_m
    r = np.hypot(*np.meshgrid(c, c))
    keep = (r > h * np.tan(np.radians(rig_deg))) & (r < radius_m - 2 * cell_m)
    if exclude is not None:
        keep &= floor_image(exclude.astype(np.uint8) * 255, h, radius_m=radius_m, cell_m=cell_m, turn=turn) < 128
    mask = keep.astype(np.uint8) * 255
    kps, desc = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=0.01).detectAndCompute(gray, mask)
    if desc is None or not kps:
        return FloorView(height_m=h, xz=np.zeros((0, 2)), descriptors=np.zeros((0, 128), np.float32),
                         angles=np.zeros(0), sizes=np.zeros(0))
    pts = np.array([k.pt for k in kps], np.float64)  # OpenCV pixel centres are integers
    xz = np.stack([(pts[:, 0] + 0.5) * cell_m - radius_m, radius_m - (pts[:, 1] + 0.5) * cell_m], 1)
    angles = np.radians([k.angle for k in kps])
    if turn:
        xz, angles = xz @ yaw_matrix_xz(turn).T, angles + turn
    return FloorView(height_m=h, xz=xz, descriptors=desc.astype(np.float32),
                     angles=angles, sizes=np.array([k.size for k in kps], np.float64))


def squared_distances(da: np.ndarray, db: np.ndarray) -> np.ndarray:
    """(N, M) float32 squared L2 distances of the descriptors da (N, D) and db (M, D) float32, clipped at 0."""
    g = da @ db.T
    g *= 2.0
    d2 = np.add.outer((da * da).sum(1), (db * db).sum(1))
    np.subtract(d2, g, out=d2)
    return np.maximum(d2, 0.0, out=d2)


@numba.njit(cache=True, nogil=True)
def nearest_both_ways(d2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d2.argmin(1), d2.argmin(0)) of a distance matrix d2 (N, M), N, M >= 1, in one pass over its rows (numpy's
    argmin along the columns strides through memory); ties go to the first index, as numpy's."""
    n, m = d2.shape
    ab = np.zeros(n, np.int64)
    ba = np.zeros(m, np.int64)
    best = d2[0].copy()
    for i in range(n):
        k, v = 0, d2[i, 0]
        for j in range(m):
            x = d2[i, j]
            if x < v:
                v, k = x, j
            if x < best[j]:
                best[j], ba[j] = x, i
        ab[i] = k
    return ab, ba


def floor_matches(a: FloorView, b: FloorView, *, ratio: float = 1.0, both_ways: bool = False) -> np.ndarray:
    """(M, 2) int64 (index in a, index in b): each keypoint of a with its nearest neighbour in b (of two or more),
    kept by Lowe's ratio test when ratio < 1. both_ways adds each keypoint of b with its nearest neighbour in a, once
    per pair of keypoints, best descriptor distance first: the same matches whichever view is a."""
    if not both_ways:
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
        return np.array([(k[0].queryIdx, k[0].trainIdx) for k in knn
                         if len(k) == 2 and (ratio >= 1 or k[0].distance < ratio * k[1].distance)],
                        np.int64).reshape(-1, 2)
    da, db = a.descriptors.astype(np.float32), b.descriptors.astype(np.float32)
    if len(da) < 2 or len(db) < 2:
        return np.zeros((0, 2), np.int64)
    d2 = squared_distances(da, db)
    rows, cols = np.arange(len(da)), np.arange(len(db))
    ab, ba = nearest_both_ways(d2)
    keep_ab, keep_ba = np.ones(len(da), bool), np.ones(len(db), bool)
    if ratio < 1:
        second_ab = np.partition(d2, 1, axis=1)[:, 1]
        second_ba = np.partition(d2, 1, axis=0)[1]
        keep_ab = d2[rows, ab] < ratio**2 * second_ab
        keep_ba = d2[ba, cols] < ratio**2 * second_ba
    i = np.concatenate([rows[keep_ab], ba[keep_ba]])
    j = np.concatenate([ab[keep_ab], cols[keep_ba]])
    key = np.unique(i * len(db) + j)
    i, j = key // len(db), key % len(db)
    order = np.lexsort((np.minimum(i, j), d2[i, j]))
    return np.stack([i[order], j[order]], 1).astype(np.int64)


def agrees_with_pose(a: FloorView, b: FloorView, a_from_b: np.ndarray, matches: np.ndarray, *, threshold_m: float = 0.08,
                     angle_tol: float = np.radians(15.0), scale_tol: float = 0.6) -> np.ndarray:
    """(M,) bool: which matches (M, 2) of the floor views a, b agree with the pose a_from_b (4, 4) (floor_support)."""
    m = matches
    if len(m) == 0:
        return np.zeros(0, bool)
    yaw = yaw_of(a_from_b[:3, :3])
    on_floor = np.linalg.norm(b.xz[m[:, 1]] @ yaw_matrix_xz(yaw).T + a_from_b[[0, 2], 3] - a.xz[m[:, 0]], axis=1)
    turn = np.abs(wrap_angle(a.angles[m[:, 0]] - b.angles[m[:, 1]] - yaw))
    octaves = np.abs(np.log2(a.sizes[m[:, 0]] / b.sizes[m[:, 1]]))
    return (on_floor < threshold_m) & (turn < angle_tol) & (octaves < scale_tol)
