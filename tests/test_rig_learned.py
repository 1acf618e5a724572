"""The learned rig detector: the U-Net built, trained a few steps, saved and loaded; the stage option picks it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from panoworld.core import registry as backends
from panoworld.core.errors import WeightsError
from panoworld.framework.hub.registry import REGISTRY
from panoworld.models.rig_unet import RigUNet, RigUNetConfig

torch.set_num_threads(1)
TINY = RigUNetConfig(channels=4, levels=2, size=32)


def test_tiny_unet_trains_saves_and_loads(tmp_path):
    from panoworld.tools.train.rig import RigSample, train_rig_unet

    # A dark disc at the nadir on a noisy light floor, and the same floor without it: learnable in a few steps.
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:48, :48]
    disc = np.hypot(yy - 23.5, xx - 23.5) < 8
    floor = (180 + rng.normal(0, 10, (48, 48, 3))).clip(0, 255).astype(np.uint8)
    rigged = floor.copy()
    rigged[disc] = 20
    samples = [RigSample(rigged, disc, "tripod", 0), RigSample(floor, np.zeros_like(disc), "none", 0)]
    net = train_rig_unet(samples, TINY, steps=60, batch=4, lr=1e-2)
    p_rig, p_floor = net.predict(rigged), net.predict(floor)
    assert p_rig[disc].mean() > 0.5 > p_rig[~disc].mean() and p_floor.max() < 0.5
    root = net.save(tmp_path / "w")
    loaded = RigUNet.load(root)
    assert np.allclose(loaded.predict(rigged), p_rig, atol=1e-5)


def test_missing_weights_say_how_to_get_them(tmp_path):
    with pytest.raises(WeightsError, match="depth.rig_weights"):
        RigUNet.load(None)
    with pytest.raises(WeightsError, match="lacks"):
        RigUNet.load(tmp_path)


def test_detectors_are_registered_backends_with_a_registry_entry():
    assert set(backends.names("rig")) == {"heuristic", "learned"}
    entry = REGISTRY["rig-unet"]
    assert entry.kind == "trained" and entry.uses[0].param == "depth.rig_weights"
