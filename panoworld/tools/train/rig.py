"""Training the rig U-Net on synthetic scenes: tripod (with and without shadow) vs no rig, rug and stool."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from panoworld.geometry.cube_views import render_view


@dataclass
class RigSample:
    face: np.ndarray
    """(S, S, 3) uint8 downward face."""
    target: np.ndarray
    """(S, S) bool: rig geometry on the face (empty for scenes without a rig)."""
    case: str
    seed: int


def rig_samples(seed: int, height: int = 256) -> list[RigSample]:
    """The five cases of one synthetic scene on its downward face: tripod, tripod-shadow (targets: the rig's own
    pixels, not its shadow), none, rug, stool (empty targets)."""
    from panoworld.depth.rig.face import erp_mask_to_face, nadir_view
    from panoworld.tools.synth import generate_scene
    from panoworld.tools.synth.rig import FloorObject, RigKind, render_with_rig, with_floor_object

    scene = generate_scene(seed, "ci-tiny")
    view = nadir_view(height)
    clean, cdepth = scene.render(scene.world_from_canonical, height, 2 * height)
    out = [RigSample(render_view(clean, view), np.zeros((view.size,) * 2, bool), "none", seed)]
    for kind in (RigKind.TRIPOD, RigKind.TRIPOD_SHADOW):
        rgb, depth, _ = render_with_rig(scene, kind, height)
        geom = depth < cdepth - 1e-3
        out.append(RigSample(render_view(rgb, view), erp_mask_to_face(geom, view), str(kind), seed))
    for kind in (FloorObject.RUG, FloorObject.STOOL):
        s = with_floor_object(scene, kind)
        rgb, _ = s.render(s.world_from_canonical, height, 2 * height)
        out.append(RigSample(render_view(rgb, view), np.zeros((view.size,) * 2, bool), str(kind), seed))
    return out


def _augment(face: np.ndarray, target: np.ndarray, size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Resize to size, rotate about the nadir by a random angle, flip, jitter brightness (the rig's yaw and the
    room's light are arbitrary)."""
    f = cv2.resize(face, (size, size), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    t = cv2.resize(target.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    M = cv2.getRotationMatrix2D((size / 2 - 0.5, size / 2 - 0.5), float(rng.uniform(0, 360)), 1.0)
    f = cv2.warpAffine(f, M, (size, size), borderMode=cv2.BORDER_REFLECT)
    t = cv2.warpAffine(t, M, (size, size), borderMode=cv2.BORDER_REFLECT)
    if rng.random() < 0.5:
        f, t = f[:, ::-1], t[:, ::-1]
    f = np.clip(f * rng.uniform(0.7, 1.3) + rng.normal(0, 0.01, f.shape), 0, 1).astype(np.float32)
    return np.ascontiguousarray(f), np.ascontiguousarray(t > 0.5)


def train_rig_unet(samples: list[RigSample], cfg, *, steps: int, batch: int = 8, lr: float = 2e-3, seed: int = 0,
                   log=None):
    """A RigUNet(cfg) trained on samples with BCE + soft Dice (Adam, cosine decay); returns the network (eval)."""
    import torch

    from panoworld.models.rig_unet import RigUNet

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = RigUNet(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    net.train()
    for step in range(steps):
        pick = rng.integers(0, len(samples), batch)
        pairs = [_augment(samples[i].face, samples[i].target, cfg.size, rng) for i in pick]
        x = torch.from_numpy(np.stack([p[0] for p in pairs])).permute(0, 3, 1, 2)
        y = torch.from_numpy(np.stack([p[1] for p in pairs])).float()[:, None]
        logit = net(x)
        p = torch.sigmoid(logit)
        dice = 1 - (2 * (p * y).sum() + 1) / (p.sum() + y.sum() + 1)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logit, y, pos_weight=torch.tensor(3.0)) + dice
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if log and (step % 50 == 0 or step == steps - 1):
            log(f"step {step} loss {loss.item():.4f}")
    return net.eval()
