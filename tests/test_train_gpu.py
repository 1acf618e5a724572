"""The bf16 / gradient-checkpointing / accelerate paths of both trainers on CUDA (skipped without a GPU)."""

from __future__ import annotations

import math

import pytest
import torch

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


def _video_sets(accelerate: bool) -> list[str]:
    from tests.test_train_video import TINY_SETS

    return [*TINY_SETS, "device=cuda", "mixed_precision=bf16", "grad_checkpointing=true",
            f"use_accelerate={str(accelerate).lower()}"]


@pytest.mark.parametrize("accelerate", [False, True])
def test_video_trainer_bf16_on_cuda(cond_dir, tmp_path, accelerate):
    pytest.importorskip("diffusers")
    pytest.importorskip("peft")
    if accelerate:
        pytest.importorskip("accelerate")
    from panoworld.tools.train import common
    from panoworld.tools.train.common import resolve_config
    from panoworld.tools.train.video.config import PRESETS, VideoTrainConfig
    from panoworld.tools.train.video.trainer import VideoTrainer

    cfg = resolve_config(VideoTrainConfig, PRESETS, "tiny", _video_sets(accelerate))
    trainer = VideoTrainer(cond_dir, tmp_path / "run", cfg, progress=False)
    summary = trainer.run()
    assert trainer.device.type == "cuda"
    rows = common.read_metrics(tmp_path / "run")
    losses = [r["loss"] for r in rows if r["split"] == "train" and "loss" in r]
    assert losses and all(math.isfinite(x) for x in losses)
    trainable = [p for p in trainer.transformer.parameters() if p.requires_grad]
    assert trainable and all(p.dtype == torch.float32 for p in trainable)  # fp32 master weights under bf16
    assert (tmp_path / "run" / "export" / "lora.safetensors").is_file() and summary["steps"] == 8


def test_shortcut_objective_under_bf16_autocast_on_cuda():
    pytest.importorskip("diffusers")
    pytest.importorskip("peft")
    from panoworld.models import wan_training as wt
    from panoworld.tools.train.video import toy

    cfg = toy.ToyConfig()
    tr = toy.tiny_base(cfg, 0).cuda().to(torch.bfloat16)
    params = wt.prepare_for_training(tr, cfg.z + 1, rank=4, alpha=4.0)
    for p in params:
        p.data = p.data.float()
    teacher = wt.EmaTeacher(tr, 0.99)
    data = toy.ToyScenes(cfg, toy.scene_seeds("train", 8))
    g = torch.Generator().manual_seed(0)
    bt = {k: v.cuda() for k, v in data.batch(torch.arange(8), g).items()}
    emb = toy.prompt().cuda().expand(8, -1, -1)
    for rho in (1.0, 0.0):  # the FM branch and the self-consistency branch
        with torch.autocast("cuda", dtype=torch.bfloat16):
            loss, branch = wt.shortcut_objective(tr, bt["x0"], bt["cond"], emb, rho=rho, anchor=bt["anchor"],
                                                 generator=g, teacher=teacher, max_steps=8)
        loss.backward()
        assert branch == ("fm" if rho == 1.0 else "sc") and torch.isfinite(loss)
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in params if p.grad is not None)


def test_recon_stage1_bf16_with_checkpointing_on_cuda(synth_dataset, tmp_path):
    from panoworld.models.panovggt import PanoVGGT
    from panoworld.tools.train.common import read_metrics
    from panoworld.tools.train.recon.config import ReconConfig
    from panoworld.tools.train.recon.loop import Trainer

    cfg = ReconConfig(stage=1, steps=3, image_height=16, patch_size=8, embed_dim=16, depth=2, num_heads=2,
                      num_register_tokens=1, camera_trunk_depth=1, camera_iterations=1, dpt_features=8, min_frames=2,
                      max_frames=3, val_scenes=1, val_batches=1, log_every=1, warmup_steps=1, device="cuda",
                      mixed_precision="bf16", grad_checkpointing=True)
    Trainer(cfg, synth_dataset, tmp_path / "run", progress=False).run()
    rows = read_metrics(tmp_path / "run", "train")
    assert rows and all(math.isfinite(r["loss"]) for r in rows)
    model = PanoVGGT.from_pretrained(tmp_path / "run" / "export" / "weights")
    assert all(torch.isfinite(p).all() for p in model.parameters())
