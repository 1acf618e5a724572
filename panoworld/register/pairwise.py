"""One pair of panoramas: SIFT on cube-face views, depth-backed 3D points, rigid LO-RANSAC (pycolmap), point-to-plane
ICP on the dense depth maps and a free-space consistency check."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap
import torch
from scipy import ndimage
from scipy.spatial.transform import Rotation

from panoworld.core.conventions import erp_dirs, erp_dirs64, erp_pixel_from_dir, invert_pose
from panoworld.geometry.cube_views import cube_views, render_view
from panoworld.geometry.floor_view import nearest_both_ways, squared_distances
from panoworld.geometry.panoramas import erp_pixel_index
from panoworld.models.pose_refine import depth_edges, sample_range


@dataclass(kw_only=True)
class Features:
    """Keypoints of one panorama: unit bearings, ray depth where the depth is trustworthy, SIFT descriptors."""

    bearings: np.ndarray
    """(N, 3) float64 unit rays in the camera frame."""
    depth: np.ndarray
    """(N,) float64 ray depth in metres; 0 where the depth is invalid, on a depth edge or nearer than
    MIN_POINT_DEPTH_M."""
    descriptors: np.ndarray
    """(N, 128) float32 SIFT descriptors."""

    @property
    def points(self) -> np.ndarray:
        """(N, 3) camera-frame points (bearing times ray depth; the origin where there is no depth)."""
        return self.bearings * self.depth[:, None]


@dataclass(kw_only=True)
class PairResult:
    """The estimate of i_from_j for panoramas i and j, and how far to trust it."""

    matches: int
    """Descriptor matches passing the ratio test."""
    inliers: int
    """RANSAC inliers of the rigid fit (3D distance below max_error_m)."""
    i_from_j: np.ndarray | None
    """(4, 4) rigid transform after refinement, None when RANSAC failed."""
    overlap: float
    """Fraction of the depth pixels of each view that the other view sees at the estimated pose (mean of both)."""
    consistency: float
    """Of the pixels of each view that land on the other's visible surface or in front of it, the fraction within
    tol of that surface (1 = no free-space violation; a wrong pose puts surfaces in the other's free space)."""
    residual: float
    """Median |log range - log depth| over the consistent pixels."""


MIN_POINT_DEPTH_M = 0.3
"""Keypoints nearer than this have no depth for the depth-backed fit: a 5 cm match tolerance there is an angle of
10 deg and more, so any texture matches on them, and no camera on a tripod photographs a surface that near (a layout
whose wall line passes through the camera puts one there)."""


def grow_exclusion(exclude: np.ndarray | None, degrees: float = 2.0) -> np.ndarray | None:
    """An ERP mask (H, W) bool (a detected capture rig) dilated by about `degrees`, so that no keypoint next to it
    describes the texture inside; None stays None."""
    if exclude is None or not exclude.any():
        return None
    k = 2 * max(1, int(round(exclude.shape[0] * degrees / 180.0))) + 1
    return cv2.dilate(exclude.astype(np.uint8), np.ones((k, k), np.uint8)) > 0


def erp_features(rgb: np.ndarray, depth: np.ndarray, *, max_features: int, max_edge: float = 0.05,
                 contrast: float = 0.01, exclude: np.ndarray | None = None, min_depth: float = MIN_POINT_DEPTH_M
                 ) -> Features:
    """SIFT on six cube-face views of the panorama (less distortion than the ERP image); each keypoint whose ray is
    closest to its own face's axis is kept, with the bilinearly sampled ray depth where the depth is valid, off depth
    edges (log-depth range over 3x3 below max_edge) and at least min_depth metres away. No keypoint is kept whose ray
    falls in exclude (an ERP mask (H', W') bool of any size, e.g. the capture rig, whose inpainted texture is no
    evidence)."""
    h, w = depth.shape
    if rgb.shape[:2] != depth.shape:
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    valid = np.isfinite(depth) & (depth > 0)
    d = np.where(valid, depth, 0).astype(np.float64)
    edges = depth_edges(torch.from_numpy(np.where(valid, d, 1e-6))[None])[0].numpy()
    views = cube_views(fov_deg=100.0, size=int(round(h / 2 * 100 / 90)))
    axes = np.stack([v.cam_from_view[:, 2] for v in views])
    sift = cv2.SIFT_create(nfeatures=max_features // len(views), contrastThreshold=contrast)
    rays, depths, descs = [], [], []
    for k, view in enumerate(views):
        gray = cv2.cvtColor(render_view(rgb, view), cv2.COLOR_RGB2GRAY)
        kps, desc = sift.detectAndCompute(gray, None)
        if desc is None or not kps:
            continue
        xy = np.array([kp.pt for kp in kps], np.float64)
        c = 0.5 * view.size - 0.5  # OpenCV pixel centres are integers
        ray = np.stack([(xy[:, 0] - c) / view.focal, (xy[:, 1] - c) / view.focal, np.ones(len(xy))], 1)
        ray = ray / np.linalg.norm(ray, axis=1, keepdims=True) @ view.cam_from_view.T
        u, v = erp_pixel_from_dir(ray, h, w)
        rc = np.stack([v - 0.5, u - 0.5])
        dk = ndimage.map_coordinates(d, rc, order=1, mode="nearest")
        ok = ndimage.map_coordinates(valid.astype(np.float32), rc, order=1, mode="nearest") > 0.999
        ek = ndimage.map_coordinates(edges, rc, order=0, mode="nearest")
        keep = np.argmax(ray @ axes.T, axis=1) == k
        if exclude is not None:
            keep &= ~exclude[erp_pixel_index(ray, *exclude.shape)]
        trusted = ok & (ek < max_edge) & (dk >= min_depth)
        rays.append(ray[keep])
        depths.append(np.where(trusted, dk, 0.0)[keep])
        descs.append(desc[keep])
    if not rays:
        return Features(bearings=np.zeros((0, 3)), depth=np.zeros(0), descriptors=np.zeros((0, 128), np.float32))
    return Features(bearings=np.concatenate(rays), depth=np.concatenate(depths),
                    descriptors=np.concatenate(descs).astype(np.float32))


def match(a: Features, b: Features, *, ratio: float = 0.8) -> np.ndarray:
    """(M, 2) indices (into a, into b) of mutual nearest neighbours passing Lowe's ratio test, in a's order: one
    distance matrix (a matrix product) gives both directions' nearest neighbours and a's second nearest."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return np.zeros((0, 2), np.int64)
    d2 = squared_distances(a.descriptors.astype(np.float32), b.descriptors.astype(np.float32))
    ab, ba = nearest_both_ways(d2)
    rows = np.arange(len(ab))
    second = np.partition(d2, 1, axis=1)[:, 1]
    keep = (d2[rows, ab] < ratio**2 * second) & (ba[ab] == rows)
    return np.stack([rows[keep], ab[keep]], 1).astype(np.int64)


def _small(depth: np.ndarray, height: int) -> np.ndarray:
    """Depth (H, W) -> float64 at most `height` rows, 0 where invalid; downsampled by a valid-weighted area average
    (pixel centres stay where the ERP convention puts them, which nearest-neighbour resizing breaks)."""
    valid = np.isfinite(depth) & (depth > 0)
    d = np.where(valid, depth, 0).astype(np.float64)
    if d.shape[0] > height:
        size = (2 * height, height)
        total = cv2.resize(d, size, interpolation=cv2.INTER_AREA)
        frac = cv2.resize(valid.astype(np.float64), size, interpolation=cv2.INTER_AREA)
        d = np.where(frac > 0.99, total / np.maximum(frac, 1e-12), 0.0)
    return d


def _cross_ranges(i_from_j: np.ndarray, depth_i: np.ndarray, depth_j: np.ndarray, height: int
                  ) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Each view's points seen from the other at the pose i_from_j, on depth maps at `height` rows: for depth_j in
    view i, then depth_i in view j, (source depth (1, N), range r (1, N) of its points from the other camera, the
    other's depth d along the same ray (1, N) and its depth-edge measure e there (sample_range))."""
    di, dj = (torch.from_numpy(_small(x, height))[None] for x in (depth_i, depth_j))
    dirs = torch.from_numpy(erp_dirs(*di.shape[1:], dtype=np.float64)).reshape(1, -1, 3)
    T = torch.from_numpy(np.asarray(i_from_j, np.float64))
    ei, ej = depth_edges(di.clamp(min=1e-6)), depth_edges(dj.clamp(min=1e-6))
    out = []
    for src, dst, e_dst, A in ((dj, di, ei, T), (di, dj, ej, torch.linalg.inv(T))):
        p = dirs * src.reshape(1, -1, 1)
        p = p @ A[:3, :3].T + A[:3, 3]
        out.append((src.reshape(1, -1), *sample_range(dst, p, e_dst)))
    return out


def consistency(i_from_j: np.ndarray, depth_i: np.ndarray, depth_j: np.ndarray, *, height: int = 128,
                tol: float = 0.03, edge: float = 0.1) -> tuple[float, float, float]:
    """(overlap, consistency, residual) of PairResult for the pose i_from_j, on depth maps at `height` rows."""
    stats = []
    for src, r, d, e in _cross_ranges(i_from_j, depth_i, depth_j, height):
        ok = (src > 0) & (d > 0) & (e < edge)
        res = torch.log(r.clamp(min=1e-6)) - torch.log(d.clamp(min=1e-6))
        agree = ok & (res.abs() < tol)
        front = ok & (res < -tol)  # in the other view's free space
        n = max(int((src > 0).sum()), 1)
        stats.append((float(agree.sum() / n), int(agree.sum()), int(front.sum()),
                      res[agree].abs().numpy()))
    overlap = 0.5 * (stats[0][0] + stats[1][0])
    agree = stats[0][1] + stats[1][1]
    front = stats[0][2] + stats[1][2]
    res = np.concatenate([stats[0][3], stats[1][3]])
    return overlap, agree / max(agree + front, 1), float(np.median(res)) if len(res) else float("nan")


def depth_toward(depth: np.ndarray, point: np.ndarray, *, window: int = 2) -> float:
    """Depth (H, W) of a panorama in the direction of `point` (3,) in its camera frame: the median valid depth of the
    (2 window + 1)^2 pixels around that direction (0 when none is valid)."""
    h, w = depth.shape
    u, v = erp_pixel_from_dir(point[None] / max(float(np.linalg.norm(point)), 1e-12), h, w)
    ui, vi = int(u[0]), min(max(int(v[0]), 0), h - 1)
    rows = depth[max(vi - window, 0):vi + window + 1]
    patch = rows[:, [(ui + k) % w for k in range(-window, window + 1)]]
    valid = patch[np.isfinite(patch) & (patch > 0)]
    return float(np.median(valid)) if len(valid) else 0.0


def cameras_in_one_room(i_from_j: np.ndarray, depth_i: np.ndarray, depth_j: np.ndarray, *, margin_m: float = 0.15,
                        margin_frac: float = 0.15) -> list[tuple[float, float]] | None:
    """Whether a pose i_from_j (4, 4) puts each camera in the other's free space (nearer than that panorama's depth
    (H, W) toward it, by margin_m and margin_frac of that depth): both panoramas in one room. -> per camera (i's, then
    j's) its distance from the other and that depth, or None when either stands behind a wall or where the other's
    depth is unknown."""
    toward = []
    for depth, cam in ((depth_i, i_from_j[:3, 3]), (depth_j, invert_pose(i_from_j)[:3, 3])):
        dist, d = float(np.linalg.norm(cam)), depth_toward(depth, cam)
        if not (d > 0 and dist < d - max(margin_m, margin_frac * d)):
            return None
        toward.append((dist, d))
    return toward


def same_room_refusal(i_from_j: np.ndarray, depth_i: np.ndarray, depth_j: np.ndarray, *, min_consistency: float,
                      margin_m: float = 0.15, margin_frac: float = 0.15) -> str:
    """Why a pose i_from_j (4, 4) estimated without the dense depths cannot hold ('' when it can): it puts each camera
    in the other's free space (nearer than that panorama's depth toward it, by margin_m and margin_frac of that depth),
    i.e. both panoramas in one room, where their depth maps (H, W) must then agree as a depth-backed pair's do
    (consistency >= min_consistency), and they do not. Panoramas in two rooms joined through a doorway see each
    other's camera behind a wall (or where their depth is unknown) and pass."""
    t = np.asarray(i_from_j, np.float64)
    toward = cameras_in_one_room(t, depth_i, depth_j, margin_m=margin_m, margin_frac=margin_frac)
    if toward is None:
        return ""
    _, cons, _ = consistency(t, depth_i, depth_j)
    if cons >= min_consistency:
        return ""
    (di, ri), (dj, rj) = toward
    return (f"puts the cameras in one room ({di:.2f} m apart, within {ri:.2f} m and {rj:.2f} m of free space) whose "
            f"depths disagree (consistency {cons:.2f})")


def free_space_violation(i_from_j: np.ndarray, depth_i: np.ndarray, depth_j: np.ndarray, *, height: int = 128,
                         margin_m: float = 0.15, margin_frac: float = 0.05, edge: float = 0.1) -> tuple[float, float]:
    """Shares of depth_j's and of depth_i's valid pixels (H, W each) that the pose i_from_j (4, 4) puts inside the other
    view's free space: nearer to that camera than its depth along the same ray by more than margin_m plus margin_frac
    of that depth (a wall of one room standing inside the other room), where that depth is not at a depth edge (as in
    consistency: the silhouettes of furniture, whose downsampled depth mixes near and far, are no evidence)."""
    out = []
    for src, r, d, e in _cross_ranges(i_from_j, depth_i, depth_j, height):
        ok = (src > 0) & (d > 0) & (e < edge)
        out.append(float((ok & (r < d * (1 - margin_frac) - margin_m)).sum()) / max(int((src > 0).sum()), 1))
    return out[0], out[1]


WHOLE_ROOM = 0.98
"""A depth map holds its whole room when at least this share of its pixels is valid (rooms_overlap_refusal)."""


def rooms_overlap_refusal(i_from_j: np.ndarray, depth_i: np.ndarray, depth_j: np.ndarray, *, max_share: float = 0.05,
                          min_valid: float = WHOLE_ROOM) -> str:
    """Why a pose i_from_j (4, 4) estimated without the dense depths cannot hold ('' when it can): where both depth maps
    (H, W) hold the whole room (at least min_valid of their pixels valid), more than max_share of either view's
    surfaces stand inside the other's free space, so the two rooms overlap. Not tested where a depth is masked (a
    layout seen from outside its own polygon holds wrong surfaces where it holds any)."""
    if min(valid_share(depth_i), valid_share(depth_j)) < min_valid:
        return ""
    vj, vi = free_space_violation(i_from_j, depth_i, depth_j)
    if max(vi, vj) <= max_share:
        return ""
    return f"puts {max(vi, vj):.0%} of one view's surfaces inside the other's free space (the rooms overlap)"


def valid_share(depth: np.ndarray) -> float:
    """Share of a depth map's pixels that are finite and positive."""
    return float((np.isfinite(depth) & (depth > 0)).mean())


def _erp_normals(pts: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of an ERP point grid (H, W, 3) from central differences (columns wrap), facing the
    camera; zero where a neighbour is missing."""
    du = np.roll(pts, -1, axis=1) - np.roll(pts, 1, axis=1)
    dv = np.zeros_like(pts)
    dv[1:-1] = pts[2:] - pts[:-2]
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), 0.0)
    return np.where((np.einsum("hwk,hwk->hw", n, pts) > 0)[..., None], -n, n)


def icp_refine(i_from_j: np.ndarray, depth_i: np.ndarray, depth_j: np.ndarray, *, height: int = 256,
               iterations: int = 15, max_dist: float = 0.1, min_dist: float = 0.01) -> np.ndarray:
    """Rigid point-to-plane ICP of depth_j's points onto depth_i's surface with projective association (each point
    paired with depth_i's point on its ray); pairs farther apart than a threshold shrinking from max_dist to min_dist
    (occluded or unseen surfaces) are dropped. -> refined i_from_j (4, 4)."""
    di, dj = _small(depth_i, height), _small(depth_j, height)
    h, w = di.shape
    dirs = erp_dirs64(h, w)
    pi = dirs * di[..., None]
    ni = _erp_normals(pi)
    edge_i = depth_edges(torch.from_numpy(np.where(di > 0, di, 1e-6))[None])[0].numpy()
    good_i = (di > 0) & (np.abs(ni).sum(-1) > 0) & (edge_i < 0.1)
    pj = (dirs * dj[..., None])[dj > 0]
    R, t = i_from_j[:3, :3].copy(), i_from_j[:3, 3].copy()
    for it in range(iterations):
        thresh = max(min_dist, max_dist * 0.75**it)
        q = pj @ R.T + t
        u, v = erp_pixel_from_dir(q, h, w)
        iu, iv = np.floor(u).astype(int) % w, np.clip(np.floor(v).astype(int), 0, h - 1)
        P, N = pi[iv, iu], ni[iv, iu]
        keep = good_i[iv, iu] & (np.linalg.norm(q - P, axis=1) < thresh)
        if keep.sum() < 100:
            break
        q, P, N = q[keep], P[keep], N[keep]
        e = np.einsum("nk,nk->n", q - P, N)
        A = np.concatenate([np.cross(q, N), N], 1)
        x = np.linalg.lstsq(A, -e, rcond=None)[0]
        dR = Rotation.from_rotvec(x[:3]).as_matrix()
        R, t = dR @ R, dR @ t + x[3:]
        if np.linalg.norm(x) < 1e-7:
            break
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, t
    return out


def register_pair(fi: Features, fj: Features, depth_i: np.ndarray, depth_j: np.ndarray, *, max_error_m: float,
                  min_inliers: int, refine_height: int, refine_iterations: int, seed: int = 0,
                  matches: np.ndarray | None = None) -> PairResult:
    """Estimate i_from_j from the matches (match(fi, fj) when None) that have a depth in both views (LO-RANSAC on
    their 3D points), then refine it on the dense depth maps."""
    m = match(fi, fj) if matches is None else matches
    m = m[(fi.depth[m[:, 0]] > 0) & (fj.depth[m[:, 1]] > 0)]
    if len(m) < max(min_inliers, 3):
        return PairResult(matches=len(m), inliers=0, i_from_j=None, overlap=0.0, consistency=0.0, residual=float("nan"))
    opts = pycolmap.RANSACOptions()
    opts.max_error = max_error_m
    opts.random_seed = seed
    opts.num_threads = 1
    est = pycolmap.estimate_rigid3d_robust(fj.points[m[:, 1]], fi.points[m[:, 0]], opts)
    if est is None or est["num_inliers"] < min_inliers:
        n = 0 if est is None else int(est["num_inliers"])
        return PairResult(matches=len(m), inliers=n, i_from_j=None, overlap=0.0, consistency=0.0, residual=float("nan"))
    T = np.eye(4)
    T[:3] = est["tgt_from_src"].matrix()
    if refine_iterations > 0:
        T = icp_refine(T, depth_i, depth_j, height=refine_height, iterations=refine_iterations, max_dist=2 * max_error_m)
    overlap, cons, res = consistency(T, depth_i, depth_j)
    return PairResult(matches=len(m), inliers=int(est["num_inliers"]), i_from_j=T, overlap=overlap, consistency=cons,
                      residual=res)
