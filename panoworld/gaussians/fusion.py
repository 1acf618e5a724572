"""Voxel-aligned 3D Gaussians: the container, the paper's confidence-weighted voxel fusion and the `voxel-fusion` backend."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from panoworld.core.conventions import check_pose, erp_dirs64
from panoworld.core.parallel import cpu_threads, map_ahead
from panoworld.core.shapes import check_shape
from panoworld.gaussians.eig3 import eigh3
from panoworld.gaussians.fusion_params import Confidence, FusionParams
from panoworld.geometry.resize import resize_depth
from panoworld.geometry.voxels import (
    VoxelSums,
    bbox_extent,
    merge_voxel_sums,
    voxel_coords_from_keys,
    voxel_keys,
    voxel_sums,
)
from panoworld.io.gaussian_set import ContextFrames, FusionResult, Gaussians, rgb_to_sh_dc

# ---------------------------------------------------------------- fusion core (shared with the Gaussian head)


# ---------------------------------------------------------------- per-pixel observations


@dataclass
class Observations:
    """Per-pixel observations of one ERP frame, in the world frame (float64)."""

    points: torch.Tensor
    """(M, 3) back-projected pixel centres."""
    colors: torch.Tensor
    """(M, 3) RGB in [0, 1]."""
    steps: torch.Tensor
    """(M, 2, 3) steps a, b to the pixel's neighbours on its surface; its footprint, uniform over the parallelogram
    they span, has covariance (a a^T + b b^T) / 12."""
    weights: torch.Tensor
    """(M,) confidence w."""
    pixels: torch.Tensor | None = None
    """(M,) flat ERP pixel index (row * W + col) of each observation in its frame."""

    def subset(self, keep: torch.Tensor) -> Observations:
        """The observations selected by a boolean mask (M,)."""
        return Observations(self.points[keep], self.colors[keep], self.steps[keep], self.weights[keep],
                            None if self.pixels is None else self.pixels[keep])


def _min_step(fwd: np.ndarray, bwd: np.ndarray) -> np.ndarray:
    """Pick per pixel the shorter of the forward/backward neighbour steps (..., 3): the side on the same surface."""
    nf = np.linalg.norm(fwd, axis=-1)
    nb = np.linalg.norm(bwd, axis=-1)
    nf = np.where(np.isfinite(nf), nf, np.inf)
    nb = np.where(np.isfinite(nb), nb, np.inf)
    return np.where((nf <= nb)[..., None], fwd, bwd)


def _neighbour_steps(pts: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Steps a (along the row) and b (across rows) of the flat pixels px (M,) of an ERP grid of points pts (H, W, 3):
    the shorter of the forward/backward step on each axis (_min_step); longitude wraps around the seam, latitude
    steps are one-sided at the poles."""
    h, w = pts.shape[:2]
    flat = pts.reshape(-1, 3)
    i, j = np.divmod(px, w)
    p = flat[px]
    row = i * w
    a = _min_step(flat[row + (j + 1) % w] - p, p - flat[row + (j - 1) % w])
    nan = np.full(3, np.nan)
    down = np.where((i < h - 1)[:, None], flat[np.minimum(i + 1, h - 1) * w + j] - p, nan)
    up = np.where((i > 0)[:, None], p - flat[np.maximum(i - 1, 0) * w + j], nan)
    return a, _min_step(down, up)


def frame_observations(
    rgb: np.ndarray, depth: np.ndarray, world_from_cam: np.ndarray, params: FusionParams, *,
    keep_points: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Observations:
    """One ERP frame rgb (H, W, 3) uint8 or float in [0, 1], depth (H, W) metres (0/inf/nan = none), pose (4, 4).

    Each valid pixel becomes a world point with a footprint covariance from its neighbour steps (the shorter step on
    each axis, so pixels on a depth edge borrow the geometry of their own surface) and a confidence (params.confidence).
    Pixels at grazing angles (|cos| < params.min_cos) are dropped. keep_points, when given, maps the world points
    (M, 3) of the valid pixels to a bool mask (M,) of those to keep; the others are dropped before their footprints
    are computed (the same observations as subsetting afterwards, for a fraction of the work when few are kept).
    """
    from panoworld.gaussians.fusion_kernels import frame_footprints, frame_points

    depth = np.asarray(depth)
    check_shape("rgb", rgb, "H W 3", dims=check_shape("depth", depth, "H W"))
    h, w = depth.shape
    check_pose(world_from_cam, "world_from_cam")
    dirs = erp_dirs64(h, w)
    # the camera points (NaN where invalid), the valid pixels and their world points, in one numba pass
    pts, px, pts_w = frame_points(depth, dirs, world_from_cam, params.max_depth)
    if keep_points is not None:
        sel = np.asarray(keep_points(pts_w), bool)
        px, pts_w = px[sel], pts_w[sel]
    a, b, area, cos = frame_footprints(pts, px, dirs)  # _neighbour_steps, |a x b| and its cos to the ray, in numba
    keep = np.isfinite(area) & (area > 0) & (cos >= params.min_cos)
    px, a, b, cos, area, pts_w = px[keep], a[keep], b[keep], cos[keep], area[keep], pts_w[keep]
    d = depth.reshape(-1)[px].astype(np.float64)
    # einsum, not @: these (M, 3) x (3, 3) products run far slower through a multithreaded BLAS on a busy CPU.
    steps = np.einsum("mki,ji->mkj", np.stack([a, b], 1), world_from_cam[:3, :3])
    if params.confidence == Confidence.UNIFORM:
        wts = np.ones(len(px))
    elif params.confidence == Confidence.AREA:
        wts = area
    else:
        wts = cos / d**2
    colors = rgb.reshape(-1, 3)[px]
    colors = colors.astype(np.float32) / 255.0 if rgb.dtype == np.uint8 else colors.astype(np.float32)
    return Observations(
        torch.from_numpy(pts_w), torch.from_numpy(colors.astype(np.float64)), torch.from_numpy(steps),
        torch.from_numpy(wts), torch.from_numpy(px),
    )


_TRIU = (torch.tensor([0, 0, 0, 1, 1, 2]), torch.tensor([0, 1, 2, 1, 2, 2]))
_TRIU_FLAT = _TRIU[0] * 3 + _TRIU[1]


def _sym_from6(v: torch.Tensor) -> torch.Tensor:
    m = torch.zeros(v.shape[0], 3, 3, dtype=v.dtype)
    m[:, _TRIU[0], _TRIU[1]] = v
    m[:, _TRIU[1], _TRIU[0]] = v
    return m


def _moment_values(obs: Observations, centre: torch.Tensor) -> torch.Tensor:
    """(M, 12) values fused per voxel: x - c, rgb, and the 6 unique entries of (x - c)(x - c)^T + footprint."""
    rel = obs.points - centre
    x = torch.cat([rel[:, None, :], obs.steps / 12.0**0.5], 1)  # rows whose Gram matrix is the second moment
    second = torch.bmm(x.transpose(1, 2), x).reshape(-1, 9)[:, _TRIU_FLAT]
    return torch.cat([rel, obs.colors, second], 1)


MERGE_EVERY = 8
"""voxel_fusion reduces its per-frame voxel sums into the running total every this many frames (bounds memory)."""


def _nonempty(obs: Observations, fn: Callable):
    """fn(obs), or None when obs holds no observation."""
    return fn(obs) if len(obs.points) else None


def _reduce(parts: list, part, merge: Callable | None = None) -> list:
    """parts with part appended, merged into one (merge, default merge_voxel_sums) once more than MERGE_EVERY."""
    parts.append(part)
    return [(merge or merge_voxel_sums)(parts)] if len(parts) > MERGE_EVERY else parts


def voxel_fusion(
    frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], params: FusionParams, *, progress: bool = False,
    keep_points: Callable[[np.ndarray], np.ndarray] | None = None, empty_ok: bool = False,
) -> FusionResult:
    """Fuse ERP frames (rgb (H, W, 3), depth (H, W) metres, world_from_cam (4, 4)) into voxel-aligned Gaussians.

    Per voxel j: p_j = sum(w x) / (sum(w) + eps) and colour c_j = sum(w rgb) / (sum(w) + eps) (the paper's fusion,
    computed relative to the voxel's grid centre for float precision); the covariance is the fused second moment of
    the pixel footprints minus p p^T (a moment-matched mixture of the pixels' surface patches). Its eigenvectors give
    the rotation and scale_factor * sqrt(eigenvalues), clamped to [min_scale, max_scale] * voxel_size, the scales.
    Frames are consumed one at a time and their voxel sums reduced into a running total every MERGE_EVERY frames, so
    memory is bounded by one frame's observations plus the occupied voxels, whatever the number of frames (pass a
    re-iterable such as ContextSource that reads frames lazily; per_voxel > 1 iterates twice). keep_points, when
    given (frame_observations'), keeps a subset of each frame's valid pixels by their world points (e.g. those the
    source panorama's own Gaussians do not explain), before their footprints are computed. empty_ok: nothing to fuse
    (no pixel kept, or every voxel pruned) gives an empty result instead of a ValueError (what is left once the
    sources explain everything).
    """
    from panoworld.core.progress import bar as progress_bar
    from panoworld.gaussians.fusion_kernels import frame_moment_sums, merge_sums

    params.check()
    if params.per_voxel > 1 and iter(frames) is frames:
        frames = list(frames)  # a one-shot iterator cannot feed the second pass
    total = len(frames) if hasattr(frames, "__len__") else None
    eps_v = params.voxel_size

    def observations(fn=lambda obs: obs):
        """fn(each frame's non-empty observations), in frame order, two frames at once on worker threads (numpy and
        the numba kernels release the GIL)."""
        bar = progress_bar(frames, total=total, desc="voxel fusion", unit="frame", on=progress, leave=False)
        for out in map_ahead(lambda f: _nonempty(frame_observations(*f, params, keep_points=keep_points), fn), bar,
                             workers=cpu_threads(2)):
            if out is not None:
                yield out

    def frame_sums(obs):  # voxel_sums(voxel_keys, _moment_values)'s sums, bit for bit, by a numba kernel
        return len(obs.points), frame_moment_sums(obs.points.numpy(), obs.colors.numpy(), obs.steps.numpy(),
                                                  obs.weights.numpy(), eps_v)

    parts: list[tuple] = []
    n_obs = 0
    for n, part in observations(frame_sums):
        parts = _reduce(parts, part, merge_sums)
        n_obs += n
    if not parts and empty_ok:
        return FusionResult(empty_gaussians(), 0, 0, 0, [0.0, 0.0, 0.0], eps_v)
    if not parts:
        raise ValueError("no valid depth pixel in any frame: every depth is 0, inf or NaN (or beyond max_depth)")
    sums = VoxelSums(*(torch.from_numpy(a) for a in merge_sums(parts)))
    centres = (voxel_coords_from_keys(sums.keys).double() + 0.5) * eps_v
    num_voxels = int(sums.keys.shape[0])

    if params.per_voxel > 1:
        # Second pass: split each voxel's samples by the sign along its top log2(K) principal axes.
        mean, _, axes = _mean_cov_axes(sums, centres)
        n_split = int(np.log2(params.per_voxel))
        child_parts: list[VoxelSums] = []
        for obs in observations():
            keys, _ = voxel_keys(obs.points, eps_v)
            vid = torch.searchsorted(sums.keys, keys)
            rel = obs.points - mean[vid]
            top = axes[vid][:, :, 3 - n_split :]  # eigenvectors sorted ascending: the last are the principal ones
            bits = (torch.einsum("mc,mck->mk", rel, top) >= 0).long()
            child = (bits * (1 << torch.arange(n_split))).sum(1)
            child_parts = _reduce(
                child_parts,
                voxel_sums(vid * params.per_voxel + child, obs.weights, _moment_values(obs, centres[vid]))[0],
            )
        sums = merge_voxel_sums(child_parts)
        centres = centres[sums.keys // params.per_voxel]

    mean, evals, axes = _mean_cov_axes(sums, centres)
    evals = evals.clamp(min=0.0)
    colors = sums.fused()[:, 3:6]
    keep = (sums.count >= params.min_points) & (sums.weight > 0) & torch.isfinite(evals).all(1)
    keep &= torch.isfinite(mean).all(1)
    num_pruned = int((~keep).sum())
    if not bool(keep.any()) and empty_ok:
        return FusionResult(empty_gaussians(), n_obs, num_voxels, num_pruned, [0.0, 0.0, 0.0], eps_v)
    if not bool(keep.any()):
        raise ValueError(
            f"all {num_voxels} voxels were pruned (fewer than min_points={params.min_points} observations or "
            "degenerate); lower min_points or voxel_size"
        )
    g = _gaussians_from_eig(mean[keep], evals[keep], axes[keep], colors[keep], params, params.max_scale * eps_v)
    return FusionResult(g, n_obs, num_voxels, num_pruned, bbox_extent(g.means), eps_v)


def _gaussians_from_eig(mean: torch.Tensor, evals: torch.Tensor, axes: torch.Tensor, colors: torch.Tensor,
                        params: FusionParams, max_scale_m: float) -> Gaussians:
    """Gaussians at mean (N, 3) with axes (N, 3, 3) and std scale_factor * sqrt(evals) (N, 3), clamped to
    [min_scale * voxel_size, max_scale_m]; colours (N, 3) in [0, 1]."""
    scales = (params.scale_factor * evals.clamp(min=0.0).sqrt()).clamp(params.min_scale * params.voxel_size, max_scale_m)
    axes = axes * torch.where(torch.det(axes) < 0, -1.0, 1.0).to(axes.dtype)[:, None, None]
    quat = np.roll(Rotation.from_matrix(axes.numpy()).as_quat(), 1, axis=-1)  # scipy is xyzw
    n = len(mean)
    return Gaussians(
        means=mean.float().numpy(), scales=scales.float().numpy(), quats=quat.astype(np.float32),
        opacities=np.full(n, params.opacity, np.float32),
        sh_dc=rgb_to_sh_dc(colors.clamp(0.0, 1.0).numpy()).astype(np.float32),
    )


def gaussians_from_cov(mean: torch.Tensor, cov: torch.Tensor, colors: torch.Tensor, params: FusionParams,
                       max_scale_m: float) -> Gaussians:
    """Gaussians of covariance cov (N, 3, 3) (scaled by scale_factor as in voxel fusion) at mean (N, 3)."""
    evals, axes = eigh3(cov)
    return _gaussians_from_eig(mean, evals, axes, colors, params, max_scale_m)


def empty_gaussians() -> Gaussians:
    """A set of no Gaussians (degree 0)."""
    z = np.zeros
    return Gaussians(z((0, 3), np.float32), z((0, 3), np.float32), z((0, 4), np.float32), z(0, np.float32),
                     z((0, 3), np.float32))


def _mean_cov_axes(sums: VoxelSums, centres: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Fused (V, 12) moments -> world means (V, 3), covariance eigenvalues (V, 3) ascending, eigenvectors (V, 3, 3)."""
    fused = sums.fused()
    rel = fused[:, :3]
    cov = _sym_from6(fused[:, 6:12]) - rel[:, :, None] * rel[:, None, :]
    evals, axes = eigh3(torch.nan_to_num(cov))
    return centres + rel, evals, axes


# ---------------------------------------------------------------- stage I/O


def uniform_subset(candidates: Sequence[int], k: int) -> list[int]:
    """k entries of candidates, uniformly spaced and including both ends (all of them when k <= 0 or k >= len)."""
    candidates = list(candidates)
    if k <= 0 or k >= len(candidates):
        return candidates
    pick = np.unique(np.round(np.linspace(0, len(candidates) - 1, k)).astype(int))
    return [candidates[i] for i in pick]


@dataclass
class ContextSource:
    """The frames a gaussians run fuses, read from disk one at a time when iterated (re-iterable; memory: two frames,
    the one being used and the next, whatever their number and size). Yields (rgb (H, W, 3) uint8, depth (H, W) float32 metres NaN = unknown,
    world_from_cam (4, 4)) at ERP height `height`."""

    rgb_paths: list[Path]
    depth_paths: list[Path]
    depth_scale: float
    world_from_cam: np.ndarray
    """(V, 4, 4) float64 poses."""
    indices: list[int]
    """Frame numbers in the video."""
    depth_source: str
    """'poses' or 'video': which artifact's depth/NNNNNN.png is used."""
    height: int
    """ERP height the frames are delivered at (frames: area resize, depth: resize_depth)."""
    stored_height: int
    """ERP height of the frames on disk."""

    def __len__(self) -> int:
        return len(self.indices)

    def frame(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        from panoworld.core.errors import InputError
        from panoworld.io.depth_png import read_depth_png

        rgb = self.rgb_at(k)
        d = read_depth_png(self.depth_paths[k], self.depth_scale)
        if d.shape != (self.stored_height, 2 * self.stored_height):
            raise InputError(f"{self.depth_paths[k]}: depth is {d.shape[1]}x{d.shape[0]} but frames are "
                                  f"{2 * self.stored_height}x{self.stored_height}; rerun the stage that wrote it")
        if d.shape[0] != self.height:
            d = resize_depth(d, self.height, 2 * self.height)
        return rgb, d, self.world_from_cam[k]

    def __iter__(self):
        """The frames in order, the next one read on a second thread while the caller works on this one (decoding
        and resizing release the GIL; memory: two frames)."""
        return map_ahead(self.frame, range(len(self)), workers=1)

    def rgb_at(self, k: int) -> np.ndarray:
        """Frame k's colour alone (frame()'s, without reading its depth)."""
        from panoworld.io.video import load_frames

        return load_frames([self.rgb_paths[k]], self.height)[0]

    def load(self) -> ContextFrames:
        """All frames in memory (for the learned decoder)."""
        rgb, depth = [], []
        for r, d, _ in self:
            rgb.append(r)
            depth.append(d)
        return ContextFrames(np.stack(rgb), np.stack(depth), self.world_from_cam, self.indices, self.depth_source)


def context_source(video_dir: Path, poses_dir: Path, *, context_views: int = 0, height: int = 0,
                   max_height: int = 0) -> ContextSource:
    """The registered frames (uniformly subsampled to context_views when > 0), their depth and poses, read lazily.

    Depth comes from the poses artifact when it has some (its estimator's, or the video's copied), else from the
    video artifact; without either it is a InputError. Frames are delivered at ERP height `height` when > 0,
    else at the stored height capped at max_height when > 0.
    """
    import json

    from panoworld.core.errors import InputError
    from panoworld.io.video import read_video_frames

    video = read_video_frames(Path(video_dir))
    poses_path = Path(poses_dir) / "poses.json"
    try:
        doc = json.loads(poses_path.read_text())
        poses = np.asarray(doc["poses"], np.float64)
        registered = np.asarray(doc.get("registered", [True] * len(poses)), bool)
        pose_depth = [f.get("depth") for f in doc.get("frames", [])]
        pose_scale = float(doc.get("depth_scale", 0.001))
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise InputError(f"{poses_path}: cannot read poses ({e}); rerun the poses stage") from None
    if poses.shape != (video.num_frames, 4, 4) or registered.shape != (video.num_frames,):
        raise InputError(
            f"{poses_path}: {poses.shape} poses / {registered.shape} registered flags but video.json lists "
            f"{video.num_frames} frames; rerun the poses stage on this video"
        )
    if len(pose_depth) == video.num_frames and all(pose_depth):
        depth_paths, scale, source = [Path(poses_dir) / d for d in pose_depth], pose_scale, "poses"
    elif video.has_depth:
        depth_paths, scale, source = video.depth, video.depth_scale, "video"
    else:
        raise InputError(
            "voxel-fusion needs per-frame depth: use video backend warp-inpaint or poses backend vggt "
            f"(neither {poses_path} nor {Path(video_dir) / 'video.json'} lists depth maps)"
        )
    idx = uniform_subset(np.flatnonzero(registered).tolist(), context_views)
    if not idx:
        raise InputError(f"{poses_path}: no registered frame; rerun the poses stage")
    out_h = height or (min(video.height, max_height) if max_height > 0 else video.height)
    return ContextSource([video.rgb[i] for i in idx], [depth_paths[i] for i in idx], scale, poses[idx], idx, source,
                         out_h, video.height)


def read_context_frames(video_dir: Path, poses_dir: Path, *, context_views: int = 0, height: int = 0) -> ContextFrames:
    """Frames, depth and poses of the registered frames (uniformly subsampled to context_views when > 0), in memory.

    Depth comes from the poses artifact when it has some (its estimator's, or the video's copied), else from the
    video artifact; without either it is a InputError. height > 0 resizes frames (area) and depth (nearest).
    """
    return context_source(video_dir, poses_dir, context_views=context_views, height=height).load()
