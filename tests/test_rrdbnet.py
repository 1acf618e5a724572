"""Real-ESRGAN x2 RRDBNet: official layout, weight loading, tiling and ERP seam/pole continuity on a tiny config."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from panoworld.models.rrdbnet import (
    RRDBNet,
    load_rrdbnet,
    pad_erp,
    upscale_frames,
    upscale_realesrgan,
    upscale_tensor,
)
from panoworld.models.weights import MissingWeightsError

# receptive field of the tiny net (num_block=1) is ~37 input pixels; PAD covers it, so tiling and the seam are exact
PAD = 40


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


@pytest.fixture
def tiny_weights(tmp_path):
    torch.manual_seed(0)
    model = RRDBNet(scale=2, num_feat=8, num_block=1, num_grow_ch=4)
    path = tmp_path / "RealESRGAN_x2plus.pth"
    torch.save({"params_ema": model.state_dict()}, path)  # the official release's layout
    return model.eval(), path


def frames(t: int = 2, h: int = 64, w: int = 128, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (t, h // 8, w // 8, 3)).astype(np.float32)
    smooth = np.repeat(np.repeat(base, 8, axis=1), 8, axis=2)
    return np.clip(smooth + rng.normal(0, 20, smooth.shape), 0, 255).astype(np.uint8)


def test_official_architecture_layout():
    model = RRDBNet()
    state = model.state_dict()
    assert sum(p.numel() for p in model.parameters()) == 16_703_171  # RealESRGAN_x2plus
    assert state["conv_first.weight"].shape == (64, 12, 3, 3)
    assert state["body.22.rdb3.conv5.weight"].shape == (64, 64 + 4 * 32, 3, 3)
    assert {f"{n}.weight" for n in ("conv_body", "conv_up1", "conv_up2", "conv_hr", "conv_last")} <= set(state)


def test_load_round_trip_shape_and_determinism(tiny_weights, tmp_path):
    model, path = tiny_weights
    x = frames()
    out = upscale_realesrgan(x, path, pad=PAD)
    assert out.shape == (2, 128, 256, 3) and out.dtype == np.uint8 and out.std() > 0
    np.testing.assert_array_equal(out, upscale_frames(model, x, pad=PAD))
    np.testing.assert_array_equal(out, upscale_realesrgan(x, path, pad=PAD))
    loaded = load_rrdbnet(path)
    assert (loaded.scale, len(loaded.body), loaded.conv_first.out_channels) == (2, 1, 8)
    torch.save({"params": model.state_dict()}, tmp_path / "params.pth")
    np.testing.assert_array_equal(out, upscale_realesrgan(x, tmp_path / "params.pth", pad=PAD))


def test_tiled_equals_whole_frame(tiny_weights):
    model, _ = tiny_weights
    x = torch.from_numpy(frames(1)).permute(0, 3, 1, 2).float() / 255
    whole = upscale_frames(model, frames(1), pad=PAD)
    tiled = upscale_frames(model, frames(1), tile=24, pad=PAD)  # uneven: 64 = 24 + 24 + 16
    assert np.abs(whole.astype(int) - tiled).max() <= 1
    whole_f, tiled_f = upscale_tensor(model, x, pad=PAD), upscale_tensor(model, x, tile=24, pad=PAD)
    torch.testing.assert_close(whole_f, tiled_f, atol=1e-5, rtol=0)


def test_seam_continuity_rolling_input_rolls_output(tiny_weights):
    model, _ = tiny_weights
    x = frames(1)
    out = upscale_frames(model, x, pad=PAD)
    rolled = upscale_frames(model, np.roll(x, 20, axis=2), pad=PAD)
    assert np.abs(np.roll(out, 40, axis=2).astype(int) - rolled).max() <= 1
    # without sphere padding the seam is where zero padding bites
    plain = upscale_frames(model, x, pad=0)
    plain_rolled = upscale_frames(model, np.roll(x, 20, axis=2), pad=0)
    assert np.abs(np.roll(plain, 40, axis=2).astype(int) - plain_rolled).max() > 5


def test_pad_erp_continues_the_sphere():
    img = torch.arange(2 * 4 * 8, dtype=torch.float32).view(1, 2, 4, 8)
    p = pad_erp(img, 2)
    assert p.shape == (1, 2, 8, 12)
    torch.testing.assert_close(p[..., 2:6, :2], img[..., :, 6:])  # left pad = rightmost columns
    torch.testing.assert_close(p[..., 2:6, -2:], img[..., :, :2])
    # the row above row 0 is row 0 seen across the pole: 180 degrees of longitude away
    torch.testing.assert_close(p[..., 1, 2:10], torch.roll(img[..., 0, :], 4, dims=-1))
    torch.testing.assert_close(p[..., 0, 2:10], torch.roll(img[..., 1, :], 4, dims=-1))
    torch.testing.assert_close(p[..., 6, 2:10], torch.roll(img[..., 3, :], 4, dims=-1))


def test_missing_or_bad_weights(tmp_path):
    with pytest.raises(MissingWeightsError, match="RealESRGAN_x2plus.pth"):
        upscale_realesrgan(frames(1), tmp_path / "nope.pth")
    with pytest.raises(MissingWeightsError, match="--upscale-weights"):
        upscale_realesrgan(frames(1), None)
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(MissingWeightsError, match="cannot read"):
        load_rrdbnet(tmp_path / "junk.pth")
    with pytest.raises(ValueError, match="expected \\(T, H, W, 3\\) uint8"):
        upscale_frames(RRDBNet(num_feat=4, num_block=1, num_grow_ch=4), np.zeros((4, 4, 3), np.uint8))
