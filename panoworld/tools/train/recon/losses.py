"""Reconstruction losses: relative-pose camera loss, confidence-weighted scale-invariant log-depth loss, render L2."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def camera_loss(pred: torch.Tensor, gt: torch.Tensor, *, rot_weight: float = 1.0, huber_beta: float = 0.05) -> dict:
    """Relative poses between every frame pair (i < j): pred, gt world_from_cam (B, S, 4, 4).

    With Q_ij = P_i^-1 P_j: translation term = Huber(t(Q_pred) - t(Q_gt)) in metres (summed over xyz), rotation
    term = Frobenius norm |R(Q_pred) - R(Q_gt)| (the chordal distance, 2 sqrt(2) sin(angle / 2)); both averaged over
    pairs. VGGT supervises the pose of every frame relative to the first; the pairs here include those (i = 0) and
    every other pair, as the paper's "relative camera poses between frame pairs".
    """
    if pred.shape != gt.shape or pred.shape[-2:] != (4, 4):
        raise ValueError(f"{tuple(pred.shape)=} {tuple(gt.shape)=} but expected both (B, S, 4, 4)")
    s = pred.shape[1]
    if s < 2:
        zero = pred.sum() * 0.0
        return {"loss": zero, "trans": zero, "rot": zero}
    i, j = torch.triu_indices(s, s, 1, device=pred.device)
    gt = gt.to(pred.dtype)
    q_pred = torch.linalg.inv(pred[:, i]) @ pred[:, j]
    q_gt = torch.linalg.inv(gt[:, i]) @ gt[:, j]
    trans = F.smooth_l1_loss(q_pred[..., :3, 3], q_gt[..., :3, 3], beta=huber_beta, reduction="none").sum(-1).mean()
    rot = (q_pred[..., :3, :3] - q_gt[..., :3, :3]).flatten(-2).norm(dim=-1).mean()
    return {"loss": (trans + rot_weight * rot).float(), "trans": trans.float(), "rot": rot.float()}


def depth_loss(pred: torch.Tensor, conf: torch.Tensor, gt: torch.Tensor, *, lam: float = 0.85,
               alpha: float = 0.05) -> dict:
    """Scale-invariant log-depth regression with VGGT-style confidence weighting, per frame then averaged.

    d = log(pred) - log(gt) on pixels with gt > 0; per frame L = mean(c d^2) - lam (mean d)^2 - alpha mean(log c)
    (Eigen et al.'s scale-invariant loss, lam = 1 fully scale invariant, lam < 1 keeps some metric scale; c >= 1 the
    predicted confidence, the -alpha log c term of VGGT keeps it from growing without bound).
    pred, conf, gt: (B, S, H, W).
    """
    if pred.shape != gt.shape or conf.shape != gt.shape:
        raise ValueError(f"{tuple(pred.shape)=} {tuple(conf.shape)=} {tuple(gt.shape)=} but expected equal shapes")
    valid = (gt > 0).float()
    n = valid.flatten(2).sum(-1).clamp(min=1.0)
    d = (torch.log(pred.float().clamp(min=1e-6)) - torch.log(gt.float().clamp(min=1e-6))) * valid
    c = conf.float()
    weighted = (c * d * d).flatten(2).sum(-1) / n
    mean_d = d.flatten(2).sum(-1) / n
    logc = (torch.log(c) * valid).flatten(2).sum(-1) / n
    has = (valid.flatten(2).sum(-1) > 0).float()
    loss = ((weighted - lam * mean_d**2 - alpha * logc) * has).sum() / has.sum().clamp(min=1.0)
    silog = (((d * d).flatten(2).sum(-1) / n - lam * mean_d**2) * has).sum() / has.sum().clamp(min=1.0)
    return {"loss": loss, "silog": silog.detach()}


def render_views(gaussians, poses: np.ndarray, height: int) -> torch.Tensor:
    """ERP renders (V, H, W, 3) of torch Gaussians at world_from_cam poses (V, 4, 4) with the project's
    differentiable renderer (erp_render.render_erp: pure-torch tile rasteriser on 6 cube faces), without supersampling:
    the loss compares with frames at this resolution and s x s supersampling would cost s^2 per step."""
    from panoworld.render.erp import render_erp

    return torch.stack([render_erp(gaussians, p, height, 2 * height, supersample=1).rgb for p in poses])


def render_loss(rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The paper's stage-2 loss: mean squared error between rendered and ground-truth images, both in [0, 1]."""
    if rendered.shape != target.shape:
        raise ValueError(f"{tuple(rendered.shape)=} but target is {tuple(target.shape)}")
    return F.mse_loss(rendered, target.to(rendered))
