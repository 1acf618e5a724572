"""Training infrastructure (config, sampler, checkpoints, metrics) and `train video` on tiny sizes: resume, export."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from panoworld.tools.train import common

pytest.importorskip("diffusers")
pytest.importorskip("peft")


@dataclass(kw_only=True)
class _Cfg:
    lr: float = 1e-3
    """learning rate"""
    steps: int = 10
    """steps"""
    name: str = "x"
    """a name"""


def test_config_resolution_and_run_dir(tmp_path):
    cfg = common.resolve_config(_Cfg, {"tiny": {"steps": 3, "name": "t"}}, "tiny", ["lr=2e-4", "name=hello world"])
    assert (cfg.lr, cfg.steps, cfg.name) == (2e-4, 3, "hello world")
    with pytest.raises(common.TrainConfigError, match=r"foo: unknown param"):
        common.resolve_config(_Cfg, {}, None, ["foo=1"])
    with pytest.raises(common.TrainConfigError, match="--preset big: unknown"):
        common.resolve_config(_Cfg, {"tiny": {}}, "big")
    with pytest.raises(common.TrainConfigError, match="cannot read 'abc' as int"):
        common.resolve_config(_Cfg, {}, None, ["steps=abc"])
    rd = common.RunDir(tmp_path / "run")
    with pytest.raises(common.TrainConfigError, match="no run to resume"):
        rd.start(cfg, resume=True)
    rd.start(cfg, resume=False)
    assert "lr: 0.0002" in (rd.path / "config.yaml").read_text()
    rd.start(cfg, resume=True)
    with pytest.raises(common.TrainConfigError, match=r"different config \(steps: 3 -> 4\)"):
        rd.start(common.resolve_config(_Cfg, {}, None, ["steps=4", "lr=2e-4", "name=hello world"]), resume=True)


def test_epoch_sampler_shards_and_resumes():
    shards = [common.EpochSampler(10, seed=3, rank=r, world=3) for r in range(3)]
    first_epoch = [s.take(len(s)) for s in shards]
    assert len({len(x) for x in first_epoch}) == 1  # equal steps per rank
    assert set(np.concatenate(first_epoch)) == set(range(10))
    a = common.EpochSampler(7, seed=1)
    a.take(5)
    b = common.EpochSampler(7, seed=1)
    b.load_state_dict(a.state_dict())
    assert a.take(9) == b.take(9)
    with pytest.raises(common.TrainConfigError, match="resume on the same data"):
        common.EpochSampler(8, seed=1).load_state_dict(a.state_dict())


def test_checkpoint_restores_everything_and_metrics_truncate(tmp_path):
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.AdamW(model.parameters(), lr=0.1)
    model(torch.randn(4, 3)).sum().backward()
    opt.step()
    sampler = common.EpochSampler(5, seed=2)
    sampler.take(3)
    ck = common.Checkpointer(tmp_path, keep=2)
    for step in (2, 4, 6):
        ck.save(step, {"model": model, "opt": opt, "sampler": sampler}, {"phase": "x"})
    assert [p.name for p in ck.list()] == ["step_00000004.pt", "step_00000006.pt"]
    expect = (torch.rand(3), np.random.rand(), sampler.take(4))
    model2 = torch.nn.Linear(3, 2)
    opt2 = torch.optim.AdamW(model2.parameters(), lr=0.1)
    sampler2 = common.EpochSampler(5, seed=2)
    step, extra = ck.restore({"model": model2, "opt": opt2, "sampler": sampler2})
    assert step == 6 and extra == {"phase": "x"}
    assert torch.equal(model2.weight, model.weight) and opt2.state_dict()["state"][0]["step"] == 1
    got = (torch.rand(3), np.random.rand(), sampler2.take(4))
    assert torch.equal(got[0], expect[0]) and got[1] == expect[1] and got[2] == expect[2]

    log = common.MetricsLog(tmp_path, tensorboard=False)
    for s in range(1, 8):
        log.log(s, "train", loss=s)
    log = common.MetricsLog(tmp_path, resume_step=4, tensorboard=False)
    assert [r["step"] for r in common.read_metrics(tmp_path)] == [1, 2, 3, 4]
    path = common.write_export_scene_yaml(tmp_path, {"video": {"backend": "wan-shortcut", "steps": 4}})
    assert "params:\n  video:\n    backend: wan-shortcut" in path.read_text()


def test_scene_split_is_by_scene_and_stable():
    from panoworld.tools.train.video.data import split_scenes

    scenes = [f"s{i:02d}" for i in range(20)]
    train, val = split_scenes(scenes * 3, 0.2, seed=0)
    assert len(val) == 4 and not set(train) & set(val) and set(train) | set(val) == set(scenes)
    train2, val2 = split_scenes(scenes + ["s99", "s98"], 0.2, seed=0)
    assert set(val) - set(val2) <= set() or all(v in val2 or v in train2 for v in val)
    assert split_scenes(["a", "b"], 0.01)[1] != []  # at least one held-out scene


TINY_SETS = ["frames=5", "height=32", "vae_steps=2", "base_steps=2", "steps=4", "checkpoint_every=2", "log_every=1",
             "val_every=2", "val_clips=1", "val_sample_clips=1", "batch_size=1", "tiny_layers=1", "tiny_heads=2",
             "tiny_z=4", "lora_rank=2", "lora_alpha=2", "val_fraction=0.34"]


def _train(cond_dir, out, sets=(), **kw):
    from panoworld.tools.train.common import resolve_config
    from panoworld.tools.train.video.config import PRESETS, VideoTrainConfig
    from panoworld.tools.train.video.trainer import VideoTrainer

    cfg = resolve_config(VideoTrainConfig, PRESETS, "tiny", [*TINY_SETS, *sets])
    resume = kw.pop("resume", False)
    return VideoTrainer(cond_dir, out, cfg, resume=resume, progress=False).run(**kw)


@pytest.mark.slow
def test_dataset_items_and_kill_resume_reproduces_the_loss_curve(cond_dir, tmp_path):
    from panoworld.tools.train.video.data import ClipDataset, read_index

    ds = ClipDataset(read_index(cond_dir), frames=5, height=32)
    item = ds[0]
    assert item["target"].shape == item["cond"].shape == (3, 5, 32, 64) and item["mask"].shape == (1, 5, 32, 64)
    assert -1 <= item["target"].min() and item["target"].max() <= 1 and set(item["mask"].unique().tolist()) <= {0.0, 1.0}
    assert item["poses"].shape == (5, 4, 4) and torch.allclose(item["poses"][0], torch.eye(4, dtype=torch.float64))
    assert len(ClipDataset(read_index(cond_dir), frames=9, height=32)) == 0  # 5-frame clips are too short for 9

    full = tmp_path / "full"
    summary = _train(cond_dir, full)
    assert summary["split"]["val_clips"] >= 1 and not set(summary["split"]["train_scenes"]) & set(summary["split"]["val_scenes"])
    killed = tmp_path / "killed"
    # phases: vae steps 0-1, base 2-3, lora 4-7; checkpoints every 3 steps and at each phase end
    assert _train(cond_dir, killed, ["checkpoint_every=3"], stop_at=4) == {"stopped_at": 4}  # resumes mid-base (3)
    with pytest.raises(common.TrainConfigError, match="already holds checkpoints"):
        _train(cond_dir, killed, ["checkpoint_every=3"])
    assert _train(cond_dir, killed, ["checkpoint_every=3"], resume=True, stop_at=7) == {"stopped_at": 7}  # mid-lora (6)
    _train(cond_dir, killed, ["checkpoint_every=3"], resume=True)
    a, b = common.read_metrics(full), common.read_metrics(killed)
    assert [r["step"] for r in a] == [r["step"] for r in b]
    for ra, rb in zip(a, b):
        assert ra.keys() == rb.keys() and ra["split"] == rb["split"], (ra, rb)
        assert all(ra[k] == pytest.approx(rb[k], rel=1e-6, abs=1e-9) for k in ra if k != "split"), (ra, rb)
    assert {r["phase"] for r in a if r["split"] == "train"} == {0.0, 1.0, 2.0}
    assert any(r["split"] == "val_sample" and "shortcut4_psnr" in r for r in a)

    # the export is what the video stage's wan-shortcut backend loads
    import yaml

    from panoworld.models.wan_shortcut import WanShortcutConfig, WanShortcutGenerator

    video = yaml.safe_load((full / "export" / "scene.yaml").read_text())["params"]["video"]
    assert video["backend"] == "wan-shortcut"
    video = video["wan"]
    assert video["steps"] == 4
    gen = WanShortcutGenerator.from_pretrained(WanShortcutConfig(
        weights=video["weights"], lora=video["lora"], extra_weights=video["extra_weights"],
        prompt_embeds=video["prompt_embeds"], device="cpu", dtype="float32", vae_tiling=False))
    cond = ((item["cond"].permute(1, 2, 3, 0) + 1) * 127.5).round().to(torch.uint8).numpy()
    out, info = gen.generate(cond, item["mask"][0].numpy() > 0)
    assert out.shape == (5, 32, 64, 3) and info["nfe"] == 4


def test_cli_errors_are_one_line(tmp_path, capsys):
    from panoworld.tools.train.cli import main as train_main

    assert train_main(["video", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--preset", "tiny"]) == 2
    assert "index.jsonl: missing; run `python runner.py precompute" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()  # nothing written
    assert train_main(["video", "--data", str(tmp_path), "--out", str(tmp_path / "run2")]) == 2
    assert "needs --weights WAN_DIR" in capsys.readouterr().err
    assert train_main(["video", "--data", str(tmp_path), "--out", str(tmp_path / "r3"), "--set", "rho"]) == 2
    assert "--set rho: expected KEY=VALUE" in capsys.readouterr().err
    assert train_main([]) == 2 and "train {video,recon}" in capsys.readouterr().err


def test_every_paper_preset_value_names_its_source():
    from panoworld.tools.train.video.config import MATRIX3D_LORA, PRESETS, SOURCES

    for preset in ("paper", "tiny"):
        missing = sorted(set(PRESETS[preset]) - set(SOURCES[preset]))
        assert not missing, f"{preset} preset values without a source: {missing}"
    # the defaults the paper preset inherits and that shape the weights carry a source too
    for key in ("weight_decay", "warmup_steps", "grad_clip", "shortcut_levels", "teacher_decay", "sc_split"):
        assert key not in PRESETS["paper"] and SOURCES["paper"][key]
    assert all(s.startswith(("paper", "ours", "VGGT", "Wan", "torch", "Frans")) for s in SOURCES["paper"].values()
               if s is not MATRIX3D_LORA)
    assert "Wan2.1-I2V-14B" in SOURCES["paper"]["lora_init"]
