"""The video generator's training run: (tiny: VAE and base pre-training), then the paper's LoRA + shortcut stage.

One global step counter runs through the phases `vae` (tiny), `base` (tiny) and `lora`; each phase checkpoints
its trainable tensors, optimiser, scheduler, data position, loss generator and the RNG states, so a killed run
resumed with `--resume` continues with the same losses as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from panoworld.models import wan_layers as wl
from panoworld.models import wan_training as wt
from panoworld.tools.train import common
from panoworld.tools.train.video import data as vdata
from panoworld.tools.train.video import models as vm
from panoworld.tools.train.video.config import BaseModel, VideoTrainConfig

VAL_SIGMAS = (0.1, 0.3, 0.5, 0.7, 0.9)
VAE_FRAMES = 5  # the tiny VAE trains on the first causal chunk pair (1 + 4 frames)


class StopRequested(Exception):
    """Raised by `stop_at` (tests: a run killed after a given step)."""


@dataclasses.dataclass
class Gen:
    """A torch.Generator with state_dict() (the loss noise stream is part of the exact-resume state)."""

    g: torch.Generator

    def state_dict(self) -> dict:
        return {"state": self.g.get_state()}

    def load_state_dict(self, s: dict) -> None:
        self.g.set_state(s["state"])


def _scheduler(opt, warmup: int):
    return torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / max(1, warmup)))


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of uint8 images a vs b over all pixels or the True pixels of mask (..., H, W)."""
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    if mask is not None:
        if not mask.any():
            return float("nan")
        d = d[mask]
    mse = float(d.mean())
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def _uint8(video: torch.Tensor) -> np.ndarray:
    """(3, T, H, W) in [-1, 1] -> (T, H, W, 3) uint8."""
    return ((video.clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(1, 2, 3, 0).numpy()


@torch.no_grad()
def sample_scores(transformer, vae, embeds: torch.Tensor, items: list[dict], *, sampler: str, steps: int,
                  device, flow_shift: float = 5.0, seed: int = 0) -> dict[str, float]:
    """Generate each held-out item with the video stage's generator and score it against its target frames:
    PSNR over all pixels and over the disoccluded ones (mask 0), frame 0 (the given panorama) excluded."""
    from panoworld.models.wan_shortcut import Sampler, WanShortcutConfig, WanShortcutGenerator

    cfg = WanShortcutConfig(sampler=Sampler(sampler), steps=steps, device=str(device), dtype="float32",
                            vae_tiling=False, shift=flow_shift, seed=seed)
    gen = WanShortcutGenerator(transformer.eval(), vae, cfg, {"prompt_embeds": embeds})
    all_, hole = [], []
    for k, it in enumerate(items):
        gen.cfg = dataclasses.replace(cfg, seed=seed + k)
        cond, mask, target = _uint8(it["cond"]), it["mask"][0].numpy() > 0, _uint8(it["target"])
        video, _ = gen.generate(cond, mask)
        all_.append(psnr(video[1:], target[1:]))
        hole.append(psnr(video[1:], target[1:], ~mask[1:]))
    return {"psnr": float(np.mean(all_)), "psnr_disoccluded": float(np.nanmean(hole) if not np.all(np.isnan(hole)) else np.nan)}


class VideoTrainer:
    """Builds the data, models and phases of one run; `run()` trains (resuming when asked) and exports."""

    def __init__(self, cond_dir: Path, run_dir: Path, cfg: VideoTrainConfig, *, weights: Path | None = None,
                 resume: bool = False, progress: bool = True):
        self.cfg, self.cond_dir, self.weights, self.resume, self.progress = cfg, Path(cond_dir), weights, resume, progress
        if cfg.base == BaseModel.WAN and weights is None:
            raise common.TrainConfigError("base=wan needs --weights WAN_DIR (local Wan2.2-TI2V-5B-Diffusers); "
                                          "or --preset tiny to build a tiny base")
        if (cfg.frames - 1) % 4:
            raise common.TrainConfigError(f"frames={cfg.frames}: the Wan VAE needs 4k + 1 frames (e.g. 13, 17, 81)")
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)
        rows = vdata.read_index(self.cond_dir)  # bad data is an error before anything is written
        self.rd = common.RunDir(run_dir)
        self.rd.start(cfg, resume)
        self.rt = common.Runtime.create(cfg.device, cfg.mixed_precision, cfg.use_accelerate)
        train_s, val_s = vdata.split_scenes([r.scene for r in rows], cfg.val_fraction, cfg.split_seed)
        self.train_ds = vdata.ClipDataset([r for r in rows if r.scene in train_s], cfg.frames, cfg.height)
        self.val_ds = vdata.ClipDataset([r for r in rows if r.scene in val_s], cfg.frames, cfg.height)
        if len(self.train_ds) == 0:
            raise common.TrainConfigError(f"{self.cond_dir}: no training clip with >= {cfg.frames} frames "
                                          f"({len(self.train_ds.skipped)} shorter); precompute with --frames {cfg.frames}")
        self.split = {"train_scenes": train_s, "val_scenes": val_s, "train_clips": len(self.train_ds),
                      "val_clips": len(self.val_ds), "skipped_short": len(self.train_ds.skipped) + len(self.val_ds.skipped)}
        tiny = cfg.base == BaseModel.TINY
        self.phases = [("vae", cfg.vae_steps if tiny else 0), ("base", cfg.base_steps if tiny else 0), ("lora", cfg.steps)]
        self.ckpt = common.Checkpointer(self.rd, cfg.keep_checkpoints)
        self.base_dir = self.rd.path / "base"
        self.device = self.rt.device

    # ------------------------------------------------------------ helpers

    def _range(self, name: str) -> tuple[int, int]:
        first = 0
        for n, k in self.phases:
            if n == name:
                return first, first + k
            first += k
        raise KeyError(name)

    def _bar_postfix(self, bar, loss: float, phase: str) -> None:
        bar.set_postfix(phase=phase, loss=f"{loss:.4f}")

    def _loop(self, name: str, start: int, objects: dict, step_fn, eval_fn=None) -> None:
        first, last = self._range(name)
        cfg = self.cfg
        for step in range(max(start, first), last):
            loss, extra = step_fn(step)
            s = step + 1
            self.bar.update()
            self._bar_postfix(self.bar, loss, name)
            if self.rt.is_main and (s % cfg.log_every == 0 or s == last):
                self.metrics.log(s, "train", phase=self._phase_id(name), loss=loss, **extra)
            if self.rt.is_main and (s % cfg.checkpoint_every == 0 or s == last):
                self.ckpt.save(s, objects, {"phase": name})
            if eval_fn is not None and self.rt.is_main and (s % cfg.val_every == 0 or s == last):
                eval_fn(s)
            if self.stop_at is not None and s >= self.stop_at:
                raise StopRequested(s)

    @staticmethod
    def _phase_id(name: str) -> float:
        return {"vae": 0, "base": 1, "lora": 2}[name]

    def _peek(self) -> tuple[int, dict | None]:
        latest = self.ckpt.latest() if self.resume else None
        if latest is None:
            if self.resume:
                raise common.TrainConfigError(f"{self.ckpt.dir}: no checkpoint to resume from (drop --resume)")
            return 0, None
        state = common.load_checkpoint(latest)
        return int(state["step"]), state

    def _restore_or_rng(self, name: str, objects: dict) -> None:
        """Restore this phase's objects when the resume checkpoint was taken in it (also at its end, when the phase's
        outputs were not written yet)."""
        if self.start_state is not None and self.start_state["extra"].get("phase") == name:
            self.ckpt.restore(objects, self.ckpt.latest())

    # ------------------------------------------------------------ phases

    def _vae_phase(self) -> None:
        cfg = self.cfg
        first, last = self._range("vae")
        if self.start >= last and (self.base_dir / "vae").is_dir():
            self.vae = vm.load_base_dir_part(self.base_dir, "vae")
            return
        torch.manual_seed(cfg.seed)
        vae = vm.tiny_vae(cfg).to(self.device)
        if last > first:
            vae.train()
            opt = torch.optim.AdamW(vae.parameters(), lr=cfg.vae_lr, weight_decay=0.0)
            sched = _scheduler(opt, cfg.warmup_steps)
            sampler = common.EpochSampler(len(self.train_ds), seed=cfg.seed + 101, rank=self.rt.rank, world=self.rt.world)
            gen = Gen(torch.Generator().manual_seed(cfg.seed + 1))
            objects = {"model": vm.Trainable(vae), "opt": opt, "sched": sched, "sampler": sampler, "gen": gen}
            self._restore_or_rng("vae", objects)
            clips: dict[int, torch.Tensor] = {}

            def frames(i: int) -> torch.Tensor:
                if i not in clips:
                    clips[i] = self.train_ds[i]["target"][:, :VAE_FRAMES]
                return clips[i]

            def step(_s: int):
                video = torch.stack([frames(i) for i in sampler.take(cfg.batch_size)]).to(self.device)
                torch.manual_seed(int(torch.randint(0, 2**31, (1,), generator=gen.g)))  # posterior sampling noise
                loss = vm.vae_loss(vae, video)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                sched.step()
                return float(loss.detach()), {}

            self._loop("vae", self.start, objects, step)
        vae.eval().requires_grad_(False)
        vm.set_latent_stats(vae, [self.train_ds[i]["target"].to(self.device) for i in range(min(16, len(self.train_ds)))])
        vm.save_base(self.base_dir, vae=vae)
        self.vae = vae

    def _latents(self) -> None:
        cfg = self.cfg
        key = f"{vdata.vae_fingerprint(self.vae)}:{cfg.frames}x{cfg.height}:{int(cfg.anchor_first_frame)}"
        root = self.rd.path / "latents"
        self.train_cache = vdata.LatentCache(root / "train", key)
        self.val_cache = vdata.LatentCache(root / "val", key)
        t0 = time.perf_counter()
        info = {}
        if not cfg.cache_latents:  # encode every batch with the frozen VAE instead (_batch)
            self.train_cache = self.val_cache = None
            self.cache_info = {"cached": False}
            return
        for name, ds, cache in (("train", self.train_ds, self.train_cache), ("val", self.val_ds, self.val_cache)):
            info[name] = vdata.build_latent_cache(ds, cache, self.vae, self.device, anchor_first_frame=cfg.anchor_first_frame,
                                                  workers=cfg.workers, rank=self.rt.rank, world=self.rt.world,
                                                  progress=self.progress)
        self.cache_info = {**info, "seconds": round(time.perf_counter() - t0, 2)}

    def _batch(self, idx: list[int], ds, cache):
        if cache is None:
            items = []
            for i in idx:
                x0, c, anchor = vdata.encode_item(self.vae, ds[i], self.device, self.cfg.anchor_first_frame)
                items.append({"x0": x0, "cond": c, "anchor": anchor})
        else:
            items = [cache.get(i, ds.rows[i]) for i in idx]
        x0 = torch.stack([it["x0"] for it in items]).to(self.device)
        cond = torch.stack([it["cond"] for it in items]).to(self.device)
        anchored = all(it["anchor"] for it in items)
        z = x0.shape[1]
        return x0, cond, (cond[:, :z, :1] if anchored else None)

    def _val_loss(self, transformer, conditioned: bool) -> float:
        """Held-out flow-matching loss at fixed sigmas and noise (dt = 0): comparable across steps and runs."""
        n = min(self.cfg.val_clips, len(self.val_ds))
        if n == 0:
            return float("nan")
        g = torch.Generator().manual_seed(999)
        total = 0.0
        transformer.eval()
        with torch.no_grad(), self.rt.autocast():
            for i in range(n):
                x0, cond, anchor = self._batch([i], self.val_ds, self.val_cache)
                for s in VAL_SIGMAS:
                    noise = torch.randn(x0.shape, generator=g).to(x0)
                    x_t = (1 - s) * x0 + s * noise
                    sig = torch.full((1,), s, device=self.device)
                    v = wl.velocity(transformer, x_t, sig, torch.zeros_like(sig) if conditioned else None,
                                    cond if conditioned else None, self.embeds.to(self.device), anchor)
                    sl = slice(1, None) if anchor is not None else slice(None)
                    total += float(((v - (noise - x0))[:, :, sl] ** 2).mean())
        transformer.train()
        return total / (n * len(VAL_SIGMAS))

    def _base_phase(self) -> None:
        cfg = self.cfg
        first, last = self._range("base")
        if cfg.base == BaseModel.WAN:
            return
        if self.start >= last and (self.base_dir / "transformer").is_dir():
            self.transformer = vm.load_base_dir_part(self.base_dir, "transformer")
            return
        torch.manual_seed(cfg.seed + 2)
        tr = vm.tiny_transformer(cfg).to(self.device)
        if last > first:
            tr.train()
            opt = torch.optim.AdamW(tr.parameters(), lr=cfg.base_lr, weight_decay=cfg.weight_decay)
            sched = _scheduler(opt, cfg.warmup_steps)
            sampler = common.EpochSampler(len(self.train_ds), seed=cfg.seed + 202, rank=self.rt.rank, world=self.rt.world)
            gen = Gen(torch.Generator().manual_seed(cfg.seed + 2))
            objects = {"model": vm.Trainable(tr), "opt": opt, "sched": sched, "sampler": sampler, "gen": gen}
            self._restore_or_rng("base", objects)
            embeds = self.embeds.to(self.device)

            def step(_s: int):
                x0, _, anchor = self._batch(sampler.take(cfg.batch_size), self.train_ds, self.train_cache)
                sigma = wt.sample_sigma(x0.shape[0], cfg.sigma_levels, gen.g).to(self.device)
                noise = torch.randn(x0.shape, generator=gen.g).to(x0)
                s = sigma.view(-1, 1, 1, 1, 1)
                with self.rt.autocast():
                    v = wl.velocity(tr, (1 - s) * x0 + s * noise, sigma, None, None,
                                    embeds.expand(x0.shape[0], -1, -1), anchor)
                sl = slice(1, None) if anchor is not None else slice(None)
                loss = (((v - (noise - x0)) ** 2)[:, :, sl]).mean()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                if cfg.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(tr.parameters(), cfg.grad_clip)
                opt.step()
                sched.step()
                return float(loss.detach()), {}

            self._loop("base", self.start, objects, step,
                       eval_fn=lambda s: self.metrics.log(s, "val", phase=1, fm_loss=self._val_loss(tr, False)))
        tr.eval().requires_grad_(False)
        vm.save_base(self.base_dir, transformer=tr)
        self.transformer = vm.load_base_dir_part(self.base_dir, "transformer").to(self.device)

    def _lora_phase(self) -> None:
        cfg = self.cfg
        first, last = self._range("lora")
        tr = self.transformer.to(self.device)
        torch.manual_seed(cfg.seed + 3)  # LoRA init: the same whether this phase starts fresh or after a resume
        params = wt.prepare_for_training(tr, wl.condition_channels(self.vae), rank=cfg.lora_rank, alpha=cfg.lora_alpha)
        for p in params:  # fp32 master weights for AdamW even when the frozen backbone is bf16
            p.data = p.data.float()
        if cfg.grad_checkpointing and self.device.type == "cuda":
            tr.enable_gradient_checkpointing()
        teacher = wt.EmaTeacher(tr, cfg.teacher_decay) if cfg.rho < 1 else None
        opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
        sched = _scheduler(opt, cfg.warmup_steps)
        sampler = common.EpochSampler(len(self.train_ds), seed=cfg.seed + 303, rank=self.rt.rank, world=self.rt.world)
        gen = Gen(torch.Generator().manual_seed(cfg.seed + 3))
        objects = {"model": vm.Trainable(tr), "opt": opt, "sched": sched, "sampler": sampler, "gen": gen}
        if teacher is not None:
            objects["teacher"] = teacher
        self._restore_or_rng("lora", objects)
        if self.rt.accelerator is not None:
            tr, opt = self.rt.prepare(tr, opt)
        embeds = self.embeds.to(self.device)
        logged = any(r["step"] == first and r["split"] == "val" and r.get("phase") == 2
                     for r in common.read_metrics(self.rd.path))
        if self.start <= first and not logged:  # the untrained (zero-initialised) stage's held-out loss
            self.metrics.log(first, "val", phase=2, fm_loss=self._val_loss(tr, True))
        tr.train()

        def step(_s: int):
            x0, cond, anchor = self._batch(sampler.take(cfg.batch_size), self.train_ds, self.train_cache)
            with self.rt.autocast():
                loss, branch = wt.shortcut_objective(
                    tr, x0, cond, embeds.expand(x0.shape[0], -1, -1), rho=cfg.rho, anchor=anchor, generator=gen.g,
                    max_steps=cfg.shortcut_levels, teacher=teacher, sigma_levels=cfg.sigma_levels,
                    split=cfg.sc_split,
                )
            opt.zero_grad(set_to_none=True)
            self.rt.backward(loss)
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
            opt.step()
            sched.step()
            if teacher is not None:
                teacher.update()
            sc = {"sc": 1.0, "fm": 0.0}.get(branch, 1.0 - cfg.rho)  # "mixed": the batch's self-consistency share
            return float(loss.detach()), {"sc": sc, "lr": sched.get_last_lr()[0]}

        def evaluate(s: int) -> None:
            self.metrics.log(s, "val", phase=2, fm_loss=self._val_loss(tr, True))
            if (cfg.val_sample_every and s % cfg.val_sample_every == 0) or s == last:
                with self.rt.autocast():  # a bf16 backbone on CUDA
                    scores = self.sampling_scores(self.rt.unwrap(tr))
                self.metrics.log(s, "val_sample", phase=2, **scores)
                tr.train()

        self._loop("lora", self.start, objects, step, eval_fn=evaluate)
        self.transformer = self.rt.unwrap(tr)

    def sampling_scores(self, transformer) -> dict[str, float]:
        """4-step shortcut and 4-step flow PSNR (all / disoccluded) on the first val_sample_clips held-out clips."""
        items = [self.val_ds[i] for i in range(min(self.cfg.val_sample_clips, len(self.val_ds)))]
        if not items:
            return {}
        out = {}
        for sampler in ("shortcut", "flow"):
            sc = sample_scores(transformer, self.vae, self.embeds, items, sampler=sampler, steps=4, device=self.device,
                               flow_shift=self.cfg.flow_shift)
            out.update({f"{sampler}4_{k}": v for k, v in sc.items()})
        return out

    # ------------------------------------------------------------ run + export

    def run(self, stop_at: int | None = None) -> dict:
        cfg = self.cfg
        self.stop_at = stop_at
        self.start, self.start_state = self._peek()
        total = sum(k for _, k in self.phases)
        self.metrics = common.MetricsLog(self.rd, resume_step=self.start if self.resume else None)
        if self.start_state is not None:
            common.set_rng_state(self.start_state["rng"])
        else:
            common.seed_everything(cfg.seed)
        t0, c0 = time.perf_counter(), time.process_time()
        self.bar = common.progress(total, initial=self.start, desc="train video", enabled=self.progress)
        try:
            if cfg.base == BaseModel.TINY:
                self.embeds = vm.tiny_prompt_embeds(cfg)
                if self.start == 0 or not (self.base_dir / "prompt_embeds.safetensors").is_file():
                    vm.save_base(self.base_dir, prompt_embeds=self.embeds)
                self._vae_phase()
            else:
                self.transformer, self.vae, self.embeds = vm.load_wan(self.weights, cfg, self.device)
                self.vae.to(self.device).eval().requires_grad_(False)
            self._latents()
            self._base_phase()
            self._lora_phase()
        except StopRequested:
            return {"stopped_at": stop_at}
        finally:
            self.bar.close()
            self.metrics.close()
        summary = {
            "steps": total, "resumed_from": self.start, "seconds": round(time.perf_counter() - t0, 1),
            "cpu_seconds": round(time.process_time() - c0, 1), "split": self.split, "latent_cache": self.cache_info,
            "export": str(self.export()),
        }
        (self.rd.path / "summary.json").write_text(__import__("json").dumps(summary, indent=2) + "\n")
        return summary

    def export(self) -> Path:
        """RUN_DIR/export: weights/ (the base; tiny only, else --weights is referenced), lora.safetensors,
        extra.safetensors, prompt_embeds.safetensors and scene.yaml for the video stage's wan-shortcut backend."""
        from panoworld.models.wan_shortcut import save_prompt_embeds

        out = self.rd.export
        tmp = out.with_name(out.name + ".part")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        if self.cfg.base == BaseModel.TINY:
            shutil.copytree(self.base_dir / "transformer", tmp / "weights" / "transformer")
            shutil.copytree(self.base_dir / "vae", tmp / "weights" / "vae")
            weights = out / "weights"
        else:
            weights = Path(self.weights).resolve()
        wl.save_trained_weights(self.transformer, tmp / "lora.safetensors", tmp / "extra.safetensors")
        save_prompt_embeds(tmp / "prompt_embeds.safetensors", self.embeds, torch.zeros_like(self.embeds))
        common.replace_dir(tmp, out)
        out = out.resolve()
        tiny = self.cfg.base == BaseModel.TINY
        common.write_export_scene_yaml(self.rd, {"video": {"backend": "wan-shortcut", "wan": {
            "weights": str(weights.resolve() if not tiny else out / "weights"),
            "lora": str(out / "lora.safetensors"), "extra_weights": str(out / "extra.safetensors"),
            "prompt_embeds": str(out / "prompt_embeds.safetensors"), "sampler": "shortcut", "steps": 4,
            "guidance": 1.0, "dtype": "bfloat16" if self.device.type == "cuda" else "float32",
            "vae_tiling": self.cfg.height >= 256,
        }}}, note=f"trained by `runner.py train video` in {self.rd.path.resolve()}; copy into a scene directory")
        return out
