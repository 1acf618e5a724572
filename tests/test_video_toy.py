"""The few-step toy of bench_train_video: multimodal targets, disjoint splits, and a metric that punishes the mean."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("diffusers")

from panoworld.tools.train.video import toy


def test_sliced_wasserstein_is_a_distance_between_point_sets():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(300, 1, generator=g)
    assert toy.sliced_wasserstein(a, a) == 0.0
    assert toy.sliced_wasserstein(a, a + 0.7) == pytest.approx(0.7, abs=1e-6)  # 1-D: W1 of a translation
    perm = a[torch.randperm(300, generator=g)]
    assert toy.sliced_wasserstein(a, perm) == pytest.approx(0.0, abs=1e-12)  # order-free
    with pytest.raises(ValueError, match="equal-size"):
        toy.sliced_wasserstein(a, a[:10])


def test_batches_are_multimodal_in_the_hole_and_exact_elsewhere():
    cfg = toy.ToyConfig()
    data = toy.ToyScenes(cfg, toy.scene_seeds("train", 16))
    bt = data.batch(torch.arange(64) % 16, torch.Generator().manual_seed(1))
    k = cfg.hole
    holes = toy.hole_content(bt["x0"], bt["hole"], k)
    f = toy.fills(cfg).flatten(1)
    nearest = torch.cdist(holes, f).argmin(1)
    assert torch.equal(nearest, bt["mode"]) and len(set(bt["mode"].tolist())) == cfg.modes
    mask = bt["cond"][:, cfg.z:]
    assert float(mask[:, :, 0].min()) == 1.0 and float(mask[:, :, 1].sum(dim=(1, 2, 3)).min()) == 128 - k * k
    torch.testing.assert_close(bt["cond"][:, :cfg.z] * mask, bt["x0"] * mask)  # the condition is the visible target
    assert float((bt["cond"][:, :cfg.z, 1] * (1 - mask[:, :, 1])).abs().max()) == 0.0  # and shows nothing of the hole
    for s in range(3):  # frame 1 outside the hole is frame 0 turned about the vertical axis
        r, c = bt["hole"][s].tolist()
        f1 = bt["x0"][s, :, 1].clone()
        f0 = data.bg[s % 16]
        assert any(torch.allclose(torch.roll(f0, sh, dims=-1)[:, :, :c], f1[:, :, :c]) for sh in range(-2, 3))


def test_splits_are_disjoint_and_the_mean_of_the_fills_scores_worse_than_samples():
    assert not set(toy.scene_seeds("train", 5000)) & set(toy.scene_seeds("test", 5000))
    assert not set(toy.scene_seeds("val", 5000)) & set(toy.scene_seeds("test", 5000, seed=1))
    cfg = toy.ToyConfig()
    f = toy.fills(cfg).flatten(1)
    g = torch.Generator().manual_seed(2)
    draw = f[torch.randint(0, cfg.modes, (256,), generator=g)]
    ref = f[torch.randint(0, cfg.modes, (256,), generator=g)]
    mean = f.mean(0, keepdim=True).expand(256, -1)  # what one flow-matching Euler step from noise gives
    assert toy.sliced_wasserstein(mean, ref) > 3 * toy.sliced_wasserstein(draw, ref)
    assert toy.swd_floor(cfg, 256) < toy.sliced_wasserstein(mean, ref) / 3


def test_equal_compute_matches_the_network_passes_training_makes():
    """toy.passes_per_sample (a backward = 2 forwards) against the forwards train_stage actually runs: FM-only 3 per
    sample; the shortcut model with the batch split 3.5 at rho 0.75 (a quarter of each batch: 2 teacher forwards more)."""
    torch.set_num_threads(1)
    cfg = toy.ToyConfig(batch=8, sc_split="batch")
    data = toy.ToyScenes(cfg, toy.scene_seeds("train", 8))
    base = toy.tiny_base(cfg, 0)
    count = {"passes": 0}

    def hook(module, args, kwargs, out):
        count["passes"] += kwargs["hidden_states"].shape[0] * (3 if torch.is_grad_enabled() else 1)

    base.register_forward_hook(hook, with_kwargs=True)
    for rho in (1.0, 0.75):
        count["passes"] = 0
        toy.train_stage(cfg, base, data, rho=rho, seed=0, steps=3)
        assert count["passes"] / (3 * cfg.batch) == pytest.approx(toy.passes_per_sample(rho))
    assert toy.equal_compute_steps(600, 0.75) == 700
