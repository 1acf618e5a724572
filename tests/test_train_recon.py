"""Reconstruction training on tiny sizes: losses, frozen heads in stage 2, exact resume, export, CLI errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

from panoworld.tools.train.common import read_metrics
from panoworld.tools.train.recon.cli import main as cli_main
from panoworld.tools.train.recon.config import ReconConfig
from panoworld.tools.train.recon.data import SceneFrames, list_scenes, split_scenes
from panoworld.tools.train.recon.loop import Trainer
from panoworld.tools.train.recon.losses import camera_loss, depth_loss

torch.set_num_threads(1)

TINY = dict(
    image_height=16, patch_size=8, embed_dim=16, depth=2, num_heads=2, num_register_tokens=1, camera_trunk_depth=1,
    camera_iterations=1, dpt_features=8, min_frames=2, max_frames=3, val_scenes=1, val_batches=1, log_every=1,
    warmup_steps=2, num_threads=1, gs_embed_dim=16, gs_heads=2, gs_feature_dim=4, gs_token_dim=8, gs_knn_k=4,
    gs_mlp_hidden=16, gs_per_voxel=1, voxel_size=0.25, context_views=2, target_views=1, render_height=16,
)


def pose(t=(0.0, 0.0, 0.0), yaw=0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = t
    return T


def test_camera_loss_is_on_relative_poses():
    gt = torch.from_numpy(np.stack([pose(), pose((0.5, 0, 0)), pose((0.5, 0, 1.0), 0.3)]))[None]
    assert float(camera_loss(gt, gt)["loss"]) == 0.0
    # Moving the whole trajectory rigidly changes no relative pose.
    moved = torch.from_numpy(pose((3.0, -1.0, 2.0), 1.2)) @ gt
    assert float(camera_loss(moved, gt)["loss"]) < 1e-12
    # One frame off by 0.2 m along x: pairs (0,1) and (1,2) see it, (0,2) does not; Huber(0.2, beta 0.05) = 0.175.
    off = gt.clone()
    off[0, 1, 0, 3] += 0.2
    out = camera_loss(off, gt)
    np.testing.assert_allclose(float(out["trans"]), 2 * 0.175 / 3, rtol=1e-6)
    assert float(out["rot"]) == 0.0
    turned = gt.clone()
    turned[0, 2, :3, :3] = torch.from_numpy(pose(yaw=0.3 + 0.1)[:3, :3])
    chord = 2 * np.sqrt(2) * np.sin(0.1 / 2)
    np.testing.assert_allclose(float(camera_loss(turned, gt)["rot"]), 2 * chord / 3, rtol=1e-6)


def test_depth_loss_scale_invariance_and_confidence():
    g = torch.Generator().manual_seed(0)
    gt = 1.0 + 3.0 * torch.rand(1, 2, 8, 16, generator=g)
    gt[0, 0, 0, :4] = 0.0  # invalid pixels are ignored
    one = torch.ones_like(gt)
    pred = 2.5 * gt.clamp(min=1.0)
    assert abs(float(depth_loss(pred, one, gt, lam=1.0, alpha=0.0)["loss"])) < 1e-6  # fully scale invariant
    assert float(depth_loss(pred, one, gt, lam=0.85, alpha=0.0)["loss"]) > 0.1  # lam < 1 keeps metric scale
    noisy = gt * torch.exp(0.1 * torch.randn(gt.shape, generator=g))
    base = float(depth_loss(noisy, one, gt, alpha=0.0)["loss"])
    assert float(depth_loss(noisy, 2 * one, gt, alpha=0.0)["loss"]) > base  # confidence weights the error
    assert float(depth_loss(noisy, 2 * one, gt, alpha=1.0)["loss"]) < float(depth_loss(noisy, 2 * one, gt, alpha=0.0)["loss"])


def test_batches_sample_one_track_and_validation_scenes_never_train(synth_dataset):
    scenes = list_scenes(synth_dataset)
    train, val = split_scenes(scenes, 1)
    assert val == scenes[-1:] and set(train).isdisjoint(val)
    data = SceneFrames(train, 16)
    b = data.sample(np.random.default_rng(0), 2, 5)
    assert 2 <= len(b.frames) <= 5 and b.frames == sorted(b.frames)
    assert b.rgb.shape == (len(b.frames), 16, 32, 3) and b.depth.shape == (len(b.frames), 16, 32)
    np.testing.assert_allclose(b.world_from_cam[0], np.eye(4))
    track = data.scenes[[s.name for s in data.scenes].index(b.scene)].poses(b.track)[b.frames]
    np.testing.assert_allclose(b.world_from_cam, np.linalg.inv(track[0]) @ track, atol=1e-9)
    with pytest.raises(ValueError, match="val_scenes=3 must leave"):
        split_scenes(scenes, 3)



@pytest.mark.slow
def test_stage1_resume_after_a_kill_reproduces_the_loss_curve(synth_dataset, tmp_path):
    kw = dict(stage=1, steps=5, ckpt_every=2, val_every=5)
    full = Trainer(ReconConfig(**TINY, **kw), synth_dataset, tmp_path / "full", progress=False)
    full.run()
    killed = Trainer(ReconConfig(**TINY, **kw), synth_dataset, tmp_path / "cut", progress=False)
    assert killed.run(stop_at=3) == {"stopped_at": 3}  # step 3 was logged, the last checkpoint is step 2
    assert [r["step"] for r in read_metrics(tmp_path / "cut", "train")] == [1, 2, 3]
    resumed = Trainer(ReconConfig(**TINY, **kw), synth_dataset, tmp_path / "cut", resume=True, progress=False)
    resumed.run()
    a, b = read_metrics(tmp_path / "full"), read_metrics(tmp_path / "cut")
    assert [r["step"] for r in a] == [r["step"] for r in b] == [1, 2, 3, 4, 5, 5]
    for ra, rb in zip(a, b):
        assert ra == rb  # bit-identical losses, metrics and learning rates
    sa, sb = full.model.state_dict(), resumed.model.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    # The export loads unchanged through the poses stage's loader and names it in scene.yaml.
    from panoworld.models.panovggt import PanoVGGT

    weights = tmp_path / "cut" / "export" / "weights"
    loaded = PanoVGGT.from_pretrained(weights)
    assert torch.equal(loaded.state_dict()["patch_embed.weight"], sa["patch_embed.weight"])
    assert loaded.cfg.pose_refine_iters == ReconConfig().pose_refine_iters > 0  # tiny exports refine by default
    doc = yaml.safe_load((tmp_path / "cut" / "export" / "scene.yaml").read_text())
    assert doc["params"] == {"poses": {"backend": "vggt", "weights": str(weights.resolve()), "align": "se3"}}
    with pytest.raises(ValueError, match="different config"):
        Trainer(ReconConfig(**{**TINY, **kw, "lr": 0.1}), synth_dataset, tmp_path / "cut", resume=True, progress=False)


def test_stage2_trains_only_the_gaussian_head_and_exports_both_backends(synth_dataset, tmp_path):
    s1 = Trainer(ReconConfig(**TINY, stage=1, steps=1), synth_dataset, tmp_path / "s1", progress=False)
    init = s1.run() and tmp_path / "s1" / "export" / "weights"
    t = Trainer(ReconConfig(**TINY, stage=2, steps=2, val_every=2, pose_refine_iters=0), synth_dataset,
                tmp_path / "s2", init=init, progress=False)
    before = {k: v.clone() for k, v in t.model.state_dict().items()}
    result = t.run()
    after = t.model.state_dict()
    changed = {k.split(".")[0] for k in after if not torch.equal(before[k], after[k])}
    assert changed == {"gaussian_head"}  # backbone, camera and depth heads frozen
    assert {"psnr_context", "psnr_novel", "ssim_novel"} <= set(result["val"])
    doc = yaml.safe_load((tmp_path / "s2" / "export" / "scene.yaml").read_text())
    assert doc["params"]["gaussians"]["backend"] == "decoder" and doc["params"]["poses"]["backend"] == "vggt"
    cfg = json.loads((tmp_path / "s2" / "export" / "weights" / "config.json").read_text())
    assert cfg["gaussian_head"]["voxel_size"] == TINY["voxel_size"]
    assert cfg["pose_refine_iters"] == 0  # the run's value, not the --init export's


def test_cli_errors_name_the_fix(synth_dataset, tmp_path, capsys):
    assert cli_main(["--stage", "2", "--data", str(synth_dataset), "--out", str(tmp_path / "r"),
                     "--set", "val_scenes=1"]) == 2
    assert "pass --init" in capsys.readouterr().err
    assert cli_main(["--stage", "1", "--data", str(tmp_path), "--out", str(tmp_path / "r")]) == 2
    assert "no scene directory with gt/gt.json" in capsys.readouterr().err
    assert cli_main(["--stage", "1", "--data", str(synth_dataset), "--out", str(tmp_path / "r"),
                     "--set", "image_height=20"]) == 2
    assert "multiple of patch_size" in capsys.readouterr().err
    assert cli_main(["--stage", "1", "--data", str(synth_dataset), "--out", str(tmp_path / "r"),
                     "--set", "nope=1"]) == 2
    assert "nope" in capsys.readouterr().err


def test_yaw_augmentation_is_exact_for_erp(synth_dataset):
    from panoworld.tools.dataset import DatasetScene
    from panoworld.tools.train.recon.data import roll_yaw

    scene = DatasetScene(list_scenes(synth_dataset)[0])
    pose = scene.poses(0)[1]
    rgb, depth = scene._synth.render(pose, 16, 32)
    for k in (1, 7):
        r2, d2, p2 = roll_yaw(rgb, depth, pose, k)
        rgb_t, depth_t = scene._synth.render(p2, 16, 32)  # the camera really turned: the renderer agrees
        assert np.array_equal(r2, rgb_t) and np.allclose(d2, depth_t, atol=1e-5)


def test_yaw_augment_modes_keep_or_randomise_relative_rotations(synth_dataset):
    from panoworld.tools.train.recon.data import SceneFrames

    data = SceneFrames(list_scenes(synth_dataset)[:1], 16)
    batches = {m: data.sample(np.random.default_rng(3), 4, 4, yaw_augment=m) for m in ("none", "shared", "per-frame")}
    none, shared, per_frame = batches["none"], batches["shared"], batches["per-frame"]
    assert none.frames == shared.frames == per_frame.frames
    # shared: one turn for the whole batch. Relative rotations are those of the track, the direction of travel in the
    # first camera is turned, and every frame's pixels are rolled by the same number of columns.
    assert np.allclose(shared.world_from_cam[:, :3, :3], none.world_from_cam[:, :3, :3], atol=1e-9)
    assert not np.allclose(shared.world_from_cam[-1, :3, 3], none.world_from_cam[-1, :3, 3], atol=1e-3)
    assert np.allclose(np.linalg.norm(shared.world_from_cam[:, :3, 3], axis=1),
                       np.linalg.norm(none.world_from_cam[:, :3, 3], axis=1))
    k = next(k for k in range(32) if np.array_equal(np.roll(none.rgb[0], k, axis=1), shared.rgb[0]))
    assert all(np.array_equal(np.roll(a, k, axis=1), b) for a, b in zip(none.rgb, shared.rgb))
    # per-frame: the frames are turned independently, so relative rotations change.
    assert not np.allclose(per_frame.world_from_cam[1:, :3, :3], none.world_from_cam[1:, :3, :3], atol=1e-3)
    with pytest.raises(ValueError, match="expected none, shared or per-frame"):
        data.sample(np.random.default_rng(3), 4, 4, yaw_augment="sometimes")


def test_paper_preset_values_name_their_source_and_follow_vggt():
    from panoworld.tools.train.recon.config import PRESETS, SOURCES, ReconConfig, dpt_layers, model_config

    missing = sorted(set(PRESETS["paper"]) - set(SOURCES["paper"]))
    assert not missing, f"paper preset values without a source: {missing}"
    assert dpt_layers(24) == (4, 11, 17, 23)  # VGGT's DPT head
    assert dpt_layers(4) == (0, 1, 2, 3)  # the tiny model's, unchanged
    assert PRESETS["paper"]["warmup_steps"] == 8000 and PRESETS["paper"]["lr"] == 2e-4  # VGGT's schedule
    cfg = ReconConfig(**{k: v for k, v in PRESETS["paper"].items()})
    assert tuple(model_config(cfg, with_head=False).dpt_layers) == (4, 11, 17, 23)
