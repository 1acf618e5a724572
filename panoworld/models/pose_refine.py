"""Gauss-Newton refinement of relative ERP camera poses by the consistency of their depth maps (no learned weights)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from panoworld.core.conventions import erp_dirs

PARAMS = 7
"""Per-frame update: rotation vector (3) and translation (3), both in the camera's own frame, log depth scale (1)."""


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation vectors (..., 3) -> rotation matrices (..., 3, 3) (Rodrigues)."""
    theta = w.norm(dim=-1, keepdim=True)
    k = w / theta.clamp(min=1e-12)
    zero = torch.zeros_like(k[..., 0])
    K = torch.stack([zero, -k[..., 2], k[..., 1], k[..., 2], zero, -k[..., 0], -k[..., 1], k[..., 0], zero], -1)
    K = K.reshape(w.shape[:-1] + (3, 3))
    theta = theta[..., None]
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + torch.sin(theta) * K + (1 - torch.cos(theta)) * (K @ K)


def depth_edges(depth: torch.Tensor) -> torch.Tensor:
    """depth (B, H, W) > 0 -> (B, H, W) max - min of log depth over each pixel's 3x3 neighbourhood (columns wrap)."""
    logd = torch.log(depth.clamp(min=1e-6))[:, None]
    padded = torch.cat([logd[..., -1:], logd, logd[..., :1]], dim=-1)
    hi = F.max_pool2d(F.pad(padded, (0, 0, 1, 1), mode="replicate"), 3, stride=1)
    lo = -F.max_pool2d(F.pad(-padded, (0, 0, 1, 1), mode="replicate"), 3, stride=1)
    return (hi - lo)[:, 0]


def sample_range(depth: torch.Tensor, pts: torch.Tensor, *extra: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """depth (B, H, W) ERP ray distances, pts (B, N, 3) in the same cameras -> (|pts|, depth bilinearly sampled in
    the direction of pts, then each of `extra` (B, H, W) maps sampled there too) all (B, N); columns wrap across the
    seam (conventions.md's ERP mapping)."""
    b, h, w = depth.shape
    depth = torch.stack([depth, *extra], 1)
    r = pts.norm(dim=-1).clamp(min=1e-6)
    lon = torch.atan2(pts[..., 0], pts[..., 2])  # conventions.erp_pixel_from_dir, in torch
    lat = torch.atan2(-pts[..., 1], torch.hypot(pts[..., 0], pts[..., 2]))
    u = (lon / (2 * np.pi) + 0.5) * w
    v = (0.5 - lat / np.pi) * h
    padded = torch.cat([depth[..., -1:], depth, depth[..., :1]], dim=-1)
    grid = torch.stack([(u + 1.0) / (w + 2) * 2 - 1, v / h * 2 - 1], dim=-1)[:, None]  # (B, 1, N, 2)
    d = F.grid_sample(padded, grid.to(padded.dtype), mode="bilinear", padding_mode="border", align_corners=False)
    return (r, *d[:, :, 0].unbind(1))


def _pose_residuals(xi: torch.Tensor, R: torch.Tensor, t: torch.Tensor, dirs: torch.Tensor, d_ref: torch.Tensor,
                    d_i: torch.Tensor, near: float,
                    edges: tuple[torch.Tensor, torch.Tensor, float] | None) -> torch.Tensor:
    """xi (B, 7) updates of ref_from_cam_i = [R | t] (B, 3, 3), (B, 3) (right-multiplied: in camera i's frame) and of
    the log scale of its depth; dirs (h, w, 3); depth maps (B, h, w) -> (B, 2 h w) log-range residuals, both
    directions (camera i's points seen from the reference, and back). edges: None, or (depth_edges of d_ref, of d_i,
    threshold): lookups where the looked-up map's exceeds the threshold (bilinear across a depth discontinuity) do not
    count."""
    b = xi.shape[0]
    Rn = R @ so3_exp(xi[:, :3])
    tn = t + (R @ xi[:, 3:6, None])[..., 0]
    di = d_i * torch.exp(xi[:, 6])[:, None, None]
    rays = dirs.reshape(1, -1, 3)
    p_i = rays * di.reshape(b, -1, 1)
    p_ref = rays * d_ref.reshape(b, -1, 1)
    if edges is None:
        r, d = sample_range(d_ref, p_i @ Rn.transpose(1, 2) + tn[:, None])
        rb, db = sample_range(di, (p_ref - tn[:, None]) @ Rn)
        fwd, bwd = d > near, db > near
    else:
        e_ref, e_i, edge = edges
        r, d, e = sample_range(d_ref, p_i @ Rn.transpose(1, 2) + tn[:, None], e_ref)
        rb, db, eb = sample_range(di, (p_ref - tn[:, None]) @ Rn, e_i)
        fwd, bwd = (d > near) & (e < edge), (db > near) & (eb < edge)
    valid = torch.cat([(di.reshape(b, -1) > near) & fwd, (d_ref.reshape(b, -1) > near) & bwd], 1)
    res = torch.cat([torch.log(r) - torch.log(d.clamp(min=near)), torch.log(rb) - torch.log(db.clamp(min=near))], 1)
    return torch.where(valid, res, torch.zeros_like(res))


def _downsample(depth: torch.Tensor, max_height: int) -> torch.Tensor:
    """(B, H, W) -> float64 with invalid pixels (non-finite or <= 0) set to 0, area-downsampled over the valid pixels
    to (max_height, 2 max_height) when taller."""
    depth = depth.to(torch.float64)
    valid = torch.isfinite(depth) & (depth > 0)
    depth = torch.where(valid, depth, torch.zeros_like(depth))
    if depth.shape[-2] > max_height:
        size = (max_height, 2 * max_height)
        total = F.adaptive_avg_pool2d(depth[:, None], size)[:, 0]
        frac = F.adaptive_avg_pool2d(valid[:, None].to(depth.dtype), size)[:, 0]
        depth = torch.where(frac > 0.5, total / frac.clamp(min=1e-12), torch.zeros_like(total))
    return depth


def _gauss_newton(R: torch.Tensor, t: torch.Tensor, d_ref: torch.Tensor, d_i: torch.Tensor, *, shared: bool,
                  iterations: int, huber: float, occlusion: float, damping: float, edge: float | None
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Damped, reweighted Gauss-Newton on _pose_residuals; float64 inputs (B, 3, 3), (B, 3), (B, h, w), (B, h, w).

    shared: the B pairs are one camera against B references and get one update (their normal equations summed).
    edge: None = no depth-edge mask (nothing computed for it). -> R, t, log depth scale (B,) of d_i."""
    b, h, w = d_ref.shape
    dirs = torch.from_numpy(erp_dirs(h, w, dtype=np.float64)).to(d_ref.device)
    eps, near = 1e-5, 1e-3
    basis = torch.eye(PARAMS, dtype=R.dtype, device=R.device) * eps
    eye = torch.eye(PARAMS, dtype=R.dtype, device=R.device)
    log_scale = torch.zeros(b, dtype=R.dtype, device=R.device)
    zero = torch.zeros(b, PARAMS, dtype=R.dtype, device=R.device)
    edges = None if edge is None else (depth_edges(d_ref), depth_edges(d_i), edge)
    for _ in range(iterations):
        d_s = d_i * torch.exp(log_scale)[:, None, None]
        r0 = _pose_residuals(zero, R, t, dirs, d_ref, d_s, near, edges)
        J = torch.stack([(_pose_residuals(zero + e, R, t, dirs, d_ref, d_s, near, edges) - r0) / eps for e in basis],
                        -1)
        a = r0.abs()
        wgt = torch.where(a < huber, torch.ones_like(a), huber / a.clamp(min=1e-12))
        wgt = torch.where(r0 > occlusion, 0.1 * wgt, wgt)
        A = J.transpose(1, 2) @ (wgt[..., None] * J)
        g = J.transpose(1, 2) @ (wgt * r0)[..., None]
        if shared:
            A, g = A.sum(0, keepdim=True), g.sum(0, keepdim=True)
        A = A + damping * (torch.diagonal(A, dim1=1, dim2=2).mean(-1)[:, None, None] + 1e-9) * eye
        step = (-torch.linalg.solve(A, g)[..., 0]).expand(b, PARAMS)
        t = t + (R @ step[:, 3:6, None])[..., 0]
        R = R @ so3_exp(step[:, :3])
        log_scale = log_scale + step[:, 6]
    return R, t, log_scale


@torch.no_grad()
def refine_relative_poses(ref_from_cam: torch.Tensor, depth_ref: torch.Tensor, depth: torch.Tensor, *,
                          iterations: int = 10, huber: float = 0.05, occlusion: float = 0.15, edge: float | None = None,
                          damping: float = 1e-3, max_height: int = 64) -> torch.Tensor:
    """Refine poses of cameras relative to a reference camera so that their ERP depth maps agree.

    ref_from_cam (B, 4, 4), depth_ref and depth (B, H, W) metres (ray distance; <= 0 or non-finite: invalid) ->
    refined (B, 4, 4).
    Minimises, over a rotation, a translation and a per-frame log depth scale (7 parameters per camera), the robust
    log-range residuals log|X| - log D(dir X) of each camera's points seen from the other camera, both directions;
    Huber weights (threshold `huber`), residuals of points farther than the other view's surface by more than
    `occlusion` (in log range: possibly hidden there) down-weighted 10x; with `edge`, lookups across a depth edge
    (depth_edges above it: the bilinear value blends two surfaces) are dropped, which removes the bias of exact
    depth maps (about 0.1 suits rendered or sensor depth; smooth predicted maps do better without: a wider basin);
    damped Gauss-Newton with a forward-difference Jacobian. Depth maps taller than max_height rows are
    area-downsampled first. The depth scale absorbs a scale error of one map against the other; the translation
    keeps the reference map's units.
    """
    if ref_from_cam.ndim != 3 or ref_from_cam.shape[-2:] != (4, 4):
        raise ValueError(f"{tuple(ref_from_cam.shape)=} but expected (B, 4, 4)")
    if depth.shape != depth_ref.shape or depth.ndim != 3 or depth.shape[0] != ref_from_cam.shape[0]:
        raise ValueError(f"{tuple(depth_ref.shape)=} {tuple(depth.shape)=} but expected both (B, H, W) with "
                         f"B = {ref_from_cam.shape[0]}")
    pose = ref_from_cam.to(torch.float64)
    R, t, _ = _gauss_newton(pose[:, :3, :3].clone(), pose[:, :3, 3].clone(), _downsample(depth_ref, max_height),
                            _downsample(depth, max_height), shared=False, iterations=iterations, huber=huber,
                            occlusion=occlusion, damping=damping, edge=edge)
    out = pose.clone()
    out[:, :3, :3], out[:, :3, 3] = R, t
    return out.to(ref_from_cam.dtype)


@torch.no_grad()
def refine_sequence(world_from_cam: torch.Tensor, depth: torch.Tensor, *, iterations: int = 20, sweeps: int = 2,
                    sweep_iterations: int = 5, neighbours: int = 8, huber: float = 0.05, occlusion: float = 0.15,
                    edge: float | None = None, damping: float = 1e-3, max_height: int = 64) -> torch.Tensor:
    """world_from_cam (S, 4, 4), depth (S, H, W) -> poses refined so that the depth maps agree
    (the objective of refine_relative_poses); frame 0 stays as it is.

    First every frame against frame 0 alone (`iterations` steps, independent problems); then `sweeps` rounds of block
    coordinate descent over the pose graph: each frame in turn against the current estimates of frame 0 and of the
    frames at most `neighbours` positions away in the sequence (`sweep_iterations` steps, one shared update and one
    depth scale per frame; frame 0 and its scale fixed). The sweeps fix frames far from frame 0, whose overlap with it
    is small; they cost O(S * neighbours) pairs. `edge` (see refine_relative_poses) applies to the sweeps only: the
    first phase keeps the wide basin of the unmasked objective.
    """
    if world_from_cam.ndim != 3 or depth.ndim != 3 or world_from_cam.shape[0] != depth.shape[0]:
        raise ValueError(f"{tuple(world_from_cam.shape)=} {tuple(depth.shape)=} but expected (S, 4, 4), (S, H, W)")
    s = world_from_cam.shape[0]
    if s < 2:
        return world_from_cam
    kw = dict(huber=huber, occlusion=occlusion, damping=damping)
    d = _downsample(depth, max_height)
    T = world_from_cam.to(torch.float64).clone()
    log_scale = torch.zeros(s, dtype=torch.float64, device=d.device)
    if iterations > 0:
        rel = torch.linalg.inv(T[:1]) @ T[1:]
        R, t, log_scale[1:] = _gauss_newton(rel[:, :3, :3].clone(), rel[:, :3, 3].clone(), d[:1].expand(s - 1, -1, -1),
                                            d[1:], shared=False, iterations=iterations, edge=None, **kw)
        rel[:, :3, :3], rel[:, :3, 3] = R, t
        T[1:] = T[:1] @ rel
    for _ in range(sweeps if sweep_iterations > 0 else 0):
        for k in range(1, s):
            refs = sorted({0} | {j for j in range(max(0, k - neighbours), min(s, k + neighbours + 1)) if j != k})
            rel = torch.linalg.inv(T[refs]) @ T[k]
            d_refs = d[refs] * torch.exp(log_scale[refs])[:, None, None]
            d_k = (d[k] * torch.exp(log_scale[k])).expand(len(refs), -1, -1)
            R, t, dls = _gauss_newton(rel[:, :3, :3].clone(), rel[:, :3, 3].clone(), d_refs, d_k, shared=True,
                                      iterations=sweep_iterations, edge=edge, **kw)
            rel[0, :3, :3], rel[0, :3, 3] = R[0], t[0]  # refs[0] is frame 0
            T[k] = T[0] @ rel[0]
            log_scale[k] += dls[0]
    return T.to(world_from_cam.dtype)
