"""Image metrics against analytic values."""

import numpy as np
import pytest

from panoworld.conventions import erp_pixel_solid_angle
from panoworld.metrics import psnr, ssim, ssim_map, video_psnr, ws_psnr


def _rand(shape, seed=0):
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


def test_identical_images():
    a = _rand((32, 64, 3))
    assert psnr(a, a) == float("inf")
    assert ws_psnr(a, a) == float("inf")
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_psnr_constant_offset_is_analytic():
    a = _rand((16, 32, 3)).clip(0, 200).astype(np.uint8)
    b = a + np.uint8(7)
    assert psnr(a, b) == pytest.approx(20 * np.log10(255 / 7))
    assert ws_psnr(a, b) == pytest.approx(20 * np.log10(255 / 7))
    f = a.astype(np.float32) / 255
    assert psnr(f, f + 0.1) == pytest.approx(20.0, abs=1e-5)


def test_psnr_mask_selects_pixels():
    a = np.zeros((8, 16), np.uint8)
    b = a.copy()
    b[:, :4] = 50
    b[:, 4:8] = 10
    mask = np.zeros((8, 16), bool)
    mask[:, 4:8] = True
    assert psnr(a, b, mask) == pytest.approx(20 * np.log10(255 / 10))
    assert np.isnan(psnr(a, b, np.zeros_like(mask)))
    with pytest.raises(ValueError, match=r"mask.shape"):
        psnr(a, b, mask[:4])


def test_ws_psnr_weights_rows_by_solid_angle():
    H, W = 16, 32
    a = np.zeros((H, W), np.float64)
    b = a.copy()
    b[0] = 0.5  # error only on the top row, which covers a small solid angle
    w = erp_pixel_solid_angle(H, W)[:, 0]
    mse = 0.25 * w[0] / w.sum()
    assert ws_psnr(a, b) == pytest.approx(10 * np.log10(1 / mse))
    assert ws_psnr(a, b) > psnr(a, b) + 5  # the polar row counts far less than under plain PSNR
    # Solid angle is proportional to cos(latitude) at the row centre (to first order).
    lat = (0.5 - (np.arange(H) + 0.5) / H) * np.pi
    np.testing.assert_allclose(w / w.sum(), np.cos(lat) / np.cos(lat).sum(), rtol=2e-3)


def test_ssim_constant_images_closed_form():
    # Zero variance everywhere: SSIM reduces to the luminance term (2 m1 m2 + C1) / (m1^2 + m2^2 + C1).
    m1, m2 = 100.0, 140.0
    a = np.full((24, 24), m1, np.uint8)
    b = np.full((24, 24), m2, np.uint8)
    c1 = (0.01 * 255) ** 2
    expected = (2 * m1 * m2 + c1) / (m1**2 + m2**2 + c1)
    assert ssim(a, b) == pytest.approx(expected, rel=1e-9)


def test_ssim_structure_and_contrast_terms():
    # b = mean - (a - mean) flips the structure: inside flat-mean regions SSIM = (C2 - 2 var) / (2 var + C2) < 0.
    rng = np.random.default_rng(1)
    a = 0.5 + 0.2 * rng.choice([-1.0, 1.0], size=(64, 64))
    b = 1.0 - a
    m = ssim_map(a, b, data_range=1.0)
    assert ssim(a, b, data_range=1.0) < -0.5
    assert np.all(m < 0.5)
    # A constant offset leaves the structure term at exactly 1, so SSIM = luminance term only (< 1, close to it).
    s = ssim(a, a + 0.05, data_range=1.0)
    assert 0.95 < s < 1.0
    assert ssim(a, b) == pytest.approx(ssim(b, a))


def test_video_psnr_pools_frames():
    a = np.zeros((3, 8, 16, 3), np.uint8)
    b = a.copy()
    b[0] = 10  # only frame 0 differs: pooled MSE = 100 / 3
    assert video_psnr(a, b) == pytest.approx(10 * np.log10(255**2 / (100 / 3)))
    mask = np.zeros((3, 8, 16), bool)
    mask[0, :2] = True
    assert video_psnr(a, b, mask) == pytest.approx(20 * np.log10(255 / 10))
    assert video_psnr(a, b, mask, spherical=True) == pytest.approx(20 * np.log10(255 / 10))
    assert video_psnr(a, a, mask) == float("inf")
    # Spherical pooling equals ws_psnr for a single frame.
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 256, (2, 1, 8, 16, 3), dtype=np.uint8)
    assert video_psnr(x, y, spherical=True) == pytest.approx(ws_psnr(x[0], y[0]))
