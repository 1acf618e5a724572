"""The training loop of both stages: batches, optimisation, validation, checkpoints with exact resume, export."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from panoworld.tools.train import common
from panoworld.tools.train.recon.config import Geometry, ReconConfig, head_config, model_config
from panoworld.tools.train.recon.data import Batch, SceneFrames, list_scenes, split_scenes
from panoworld.tools.train.recon.losses import camera_loss, depth_loss, render_loss, render_views

VAL_SEED_OFFSET = 1_000_003
WEIGHTS = "weights"


def build_model(cfg: ReconConfig, init: Path | None):
    """A fresh model (seeded), or the one in `init` (a previous export); stage 2 adds a fresh Gaussian head to a
    stage-1 model that has none."""
    from panoworld.models.panovggt import PanoVGGT
    from panoworld.models.panovggt_config import PanoVGGTConfig
    from panoworld.models.weights import CONFIG_FILE, WEIGHTS_FILE, require_weights_dir

    common.seed_everything(cfg.seed)
    if init is None:
        if cfg.stage == 2:
            raise common.TrainConfigError(
                "stage 2 trains the Gaussian head on a trained backbone: pass --init RUN_DIR/export/weights of a "
                "stage-1 run")
        return PanoVGGT(model_config(cfg, with_head=False))
    root = require_weights_dir(init, [CONFIG_FILE, WEIGHTS_FILE], model="PanoVGGT", flag="--init")
    mcfg = PanoVGGTConfig.from_json(json.loads((root / CONFIG_FILE).read_text()))
    if cfg.stage == 1 or mcfg.gaussian_head is not None:
        return PanoVGGT.from_pretrained(root, flag="--init").train()
    from safetensors.torch import load_file

    mcfg.gaussian_head = head_config(cfg)
    model = PanoVGGT(mcfg)
    missing, unexpected = model.load_state_dict(load_file(str(root / WEIGHTS_FILE)), strict=False)
    if unexpected or any(not k.startswith("gaussian_head.") for k in missing):
        raise common.TrainConfigError(f"--init {root}: {WEIGHTS_FILE} does not match its {CONFIG_FILE}")
    return model


def lr_factor(cfg: ReconConfig, step: int) -> float:
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    t = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    return cfg.lr_min_ratio + (1 - cfg.lr_min_ratio) * 0.5 * (1 + math.cos(math.pi * min(1.0, t)))


def _tensors(batch: Batch, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """-> images (S, 3, H, W) in [0, 1], depth (S, H, W), world_from_cam (S, 4, 4) float64."""
    img = torch.from_numpy(batch.rgb).to(device).permute(0, 3, 1, 2).float().div(255.0)
    return img, torch.from_numpy(batch.depth).to(device), torch.from_numpy(batch.world_from_cam).to(device)


def _resize(img: torch.Tensor, height: int) -> torch.Tensor:
    if img.shape[-2] == height:
        return img
    return F.interpolate(img, size=(height, 2 * height), mode="bilinear", antialias=True, align_corners=False)


class Trainer:
    """One run of one stage; `run()` trains from step 0 or from the latest checkpoint and exports the weights."""

    def __init__(self, cfg: ReconConfig, data_dir: Path, out: Path, *, init: Path | None = None,
                 resume: bool = False, progress: bool = True):
        try:
            cfg.check()
        except ValueError as e:
            raise common.TrainConfigError(f"{e} (--set KEY=VALUE)") from None
        if cfg.num_threads > 0:
            torch.set_num_threads(cfg.num_threads)
        self.cfg, self.resume, self.show = cfg, resume, progress
        self.run_dir = common.RunDir(out)
        train, val = split_scenes(list_scenes(data_dir), cfg.val_scenes)
        self.train_data = SceneFrames(train, cfg.image_height)
        self.val_data = SceneFrames(val, cfg.image_height)
        self.rt = common.Runtime.create(cfg.device, cfg.mixed_precision, cfg.use_accelerate)
        self.model = build_model(cfg, init).to(self.rt.device)
        self.model.gradient_checkpointing = cfg.grad_checkpointing
        if cfg.image_height != self.model.cfg.image_height or cfg.image_height % self.model.cfg.patch_size:
            raise common.TrainConfigError(f"image_height={cfg.image_height} but the --init model takes "
                                          f"{self.model.cfg.image_height}; --set image_height=...")
        groups = self.model.heads()
        train_keys = ("backbone", "camera", "depth") if cfg.stage == 1 else ("gaussian",)
        for k, params in groups.items():
            for p in params:
                p.requires_grad_(k in train_keys)
        params = [p for k in train_keys for p in groups[k]]
        self.optim = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.sched = torch.optim.lr_scheduler.LambdaLR(self.optim, lambda s: lr_factor(cfg, s))
        if cfg.stage == 1:
            self.net, self.optim = self.rt.prepare(self.model, self.optim)
        else:
            self.net, self.optim = self.rt.prepare(self.model.gaussian_head, self.optim)
        self.run_dir.start(cfg, resume)
        self.ckpt = common.Checkpointer(self.run_dir, keep=cfg.keep_checkpoints)
        self.val_batches = [self._val_batch(i) for i in range(cfg.val_batches if len(self.val_data) else 0)]

    # ------------------------------------------------------------ batches

    def _frames(self, rng: np.random.Generator) -> tuple[int, int]:
        c = self.cfg
        if c.stage == 1:
            return c.min_frames, c.max_frames
        lo = min(c.min_frames, c.context_views)
        return lo + c.target_views, c.context_views + c.target_views

    def _val_batch(self, i: int) -> Batch:
        rng = np.random.default_rng([self.cfg.seed, VAL_SEED_OFFSET, i])
        hi = self._frames(rng)[1]
        return self.val_data.sample(rng, hi, hi, scene=i % len(self.val_data))

    def _split(self, batch: Batch, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Stage 2: (context, target) positions in the batch; frame 0 (the canonical frame) is always context."""
        s = len(batch.frames)
        t = min(self.cfg.target_views, s - 1)
        target = np.sort(rng.choice(np.arange(1, s), size=t, replace=False)) if t > 0 else np.zeros(0, int)
        return np.setdiff1d(np.arange(s), target), target

    # ------------------------------------------------------------ steps

    def stage1_losses(self, batch: Batch) -> dict[str, torch.Tensor]:
        c = self.cfg
        img, depth, poses = _tensors(batch, self.rt.device)
        with self.rt.autocast():
            out = self.net(img[None])
        cam = camera_loss(out["world_from_cam"], poses[None], rot_weight=c.rot_weight)
        dep = depth_loss(out["depth"].float(), out["depth_conf"].float(), depth[None], lam=c.silog_lambda,
                         alpha=c.conf_alpha)
        loss = c.camera_weight * cam["loss"] + c.depth_weight * dep["loss"]
        return {"loss": loss, "camera": cam["loss"].detach(), "trans": cam["trans"].detach(),
                "rot": cam["rot"].detach(), "depth": dep["loss"].detach(), "silog": dep["silog"]}, out

    def gaussians(self, img: torch.Tensor, depth: torch.Tensor, poses: torch.Tensor) -> dict:
        """Context views (S, 3, H, W) -> the Gaussian head's output on this run's geometry (predicted or given)."""
        with torch.no_grad(), self.rt.autocast():
            out = self.model(img[None], with_tokens=True)
        if self.cfg.geometry == Geometry.PREDICTED:
            depth, poses = out["depth"][0].float(), out["world_from_cam"][0]
        return self.net(img, depth, poses, out["tokens"][0].float())

    def stage2_losses(self, batch: Batch, ctx: np.ndarray, tgt: np.ndarray, n_ctx_render: int):
        img, depth, poses = _tensors(batch, self.rt.device)
        res = self.gaussians(img[ctx], depth[ctx], poses[ctx])
        views = np.concatenate([ctx[:n_ctx_render], tgt])
        target = _resize(img[views], self.cfg.render_height).permute(0, 2, 3, 1)
        rendered = render_views(res["gaussians"], batch.world_from_cam[views], self.cfg.render_height)
        loss = render_loss(rendered, target)
        return {"loss": loss, "num_gaussians": torch.tensor(float(len(res["gaussians"])))}, rendered, target, views

    def train_step(self, step: int) -> dict[str, float]:
        c = self.cfg
        rng = np.random.default_rng([c.seed, step, self.rt.rank])
        lo, hi = self._frames(rng)
        batch = self.train_data.sample(rng, lo, hi, yaw_augment=c.yaw_augment)
        self.net.train()
        if c.stage == 1:
            losses, _ = self.stage1_losses(batch)
        else:
            ctx, tgt = self._split(batch, rng)
            ctx = np.concatenate([ctx[:1], rng.permutation(ctx[1:])])  # which context views get rendered
            losses = self.stage2_losses(batch, ctx, tgt, min(c.render_context, len(ctx)))[0]
        self.optim.zero_grad(set_to_none=True)
        self.rt.backward(losses["loss"])
        params = [p for g in self.optim.param_groups for p in g["params"]]
        gnorm = torch.nn.utils.clip_grad_norm_(params, c.grad_clip if c.grad_clip > 0 else float("inf"))
        self.optim.step()
        self.sched.step()
        out = {k: float(v.detach()) for k, v in losses.items()}
        out["grad_norm"], out["lr"], out["frames"] = float(gnorm), self.sched.get_last_lr()[0], len(batch.frames)
        return out

    # ------------------------------------------------------------ validation

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        from panoworld.geometry.align import trajectory_metrics
        from panoworld.render.metrics import psnr, ssim
        from panoworld.tools.eval.cli import depth_errors

        self.net.eval()
        rows: dict[str, list[float]] = {}
        for i, batch in enumerate(self.val_batches):
            if self.cfg.stage == 1:
                losses, out = self.stage1_losses(batch)
                est = out["world_from_cam"][0].cpu().numpy()
                tm = trajectory_metrics(est, batch.world_from_cam)
                pred = out["depth"][0].float().cpu().numpy()
                absrel = np.mean([depth_errors(p, g)["abs_rel"] for p, g in zip(pred, batch.depth)])
                vals = {"loss": float(losses["loss"]), "ate": tm["ate"], "rpe_t": tm["rpe_t"], "rpe_r": tm["rpe_r"],
                        "abs_rel": float(absrel)}
            else:
                rng = np.random.default_rng([self.cfg.seed, VAL_SEED_OFFSET, i, 1])
                ctx, tgt = self._split(batch, rng)
                losses, rendered, target, views = self.stage2_losses(batch, ctx, tgt, len(ctx))
                r = (rendered.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
                t = (target.cpu().numpy() * 255).round().astype(np.uint8)
                n = len(ctx)
                vals = {"loss": float(losses["loss"]),
                        "psnr_context": float(np.mean([psnr(a, b) for a, b in zip(r[:n], t[:n])])),
                        "ssim_context": float(np.mean([ssim(a, b) for a, b in zip(r[:n], t[:n])]))}
                if len(tgt):
                    vals["psnr_novel"] = float(np.mean([psnr(a, b) for a, b in zip(r[n:], t[n:])]))
                    vals["ssim_novel"] = float(np.mean([ssim(a, b) for a, b in zip(r[n:], t[n:])]))
            for k, v in vals.items():
                rows.setdefault(k, []).append(v)
        return {k: float(np.mean(v)) for k, v in rows.items()}

    # ------------------------------------------------------------ run

    def objects(self) -> dict:
        return {"model": self.model, "optim": self.optim, "sched": self.sched}

    def run(self, stop_at: int | None = None) -> dict:
        """Train to cfg.steps (from the latest checkpoint with resume) and export; `stop_at` ends the process's work
        after that many steps without exporting (as a kill would, for tests)."""
        c = self.cfg
        start = 0
        if self.resume:
            start, _ = self.ckpt.restore(self.objects())
        log = common.MetricsLog(self.run_dir, resume_step=start if self.resume else None, tensorboard=False)
        bar = common.progress(c.steps, start, f"recon stage {c.stage}", enabled=self.show and self.rt.is_main)
        last_val: dict[str, float] = {}
        t0, cpu0 = time.perf_counter(), time.process_time()
        try:
            for step in range(start, c.steps):
                if stop_at is not None and step >= stop_at:
                    return {"stopped_at": step}
                vals = self.train_step(step)
                done = step + 1
                bar.update(1)
                bar.set_postfix(loss=f"{vals['loss']:.4f}")
                if self.rt.is_main and (done % c.log_every == 0 or done == c.steps):
                    log.log(done, "train", **vals)
                if self.val_batches and (done % c.val_every == 0 or done == c.steps):
                    last_val = self.validate()
                    if self.rt.is_main:
                        log.log(done, "val", **last_val)
                if self.rt.is_main and (done % c.ckpt_every == 0 or done == c.steps):
                    self.ckpt.save(done, self.objects())
        finally:
            bar.close()
            log.close()
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        export = self.export() if self.rt.is_main else None
        return {"steps": c.steps, "val": last_val, "wall_s": wall, "cpu_s": cpu, "export": str(export)}

    def export(self) -> Path:
        """RUN_DIR/export/weights (config.json + model.safetensors) and RUN_DIR/export/scene.yaml."""
        weights = self.run_dir.export / WEIGHTS
        model = self.rt.unwrap(self.model)
        model.cfg.pose_refine_iters = self.cfg.pose_refine_iters  # inference-only: the run decides, --init or not
        model.save_pretrained(weights)
        # The model is trained in metres: keep its scale (se3) rather than fitting one to the plan (sim3).
        params = {"poses": {"backend": "vggt", "weights": str(weights.resolve()), "align": "se3"}}
        if self.cfg.stage == 2:
            params["gaussians"] = {"backend": "decoder", "decoder": {"weights": str(weights.resolve())}}
        common.write_export_scene_yaml(
            self.run_dir, params, note=f"PanoVGGT trained by `runner.py train recon --stage {self.cfg.stage}`")
        return weights
