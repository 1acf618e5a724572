"""Image metrics against analytic values."""

import numpy as np
import pytest

from panoworld.core.conventions import erp_pixel_solid_angle
from panoworld.render.metrics import psnr, ssim, ssim_map, video_psnr, ws_psnr


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


def _smooth_erp(h=64, seed=0):
    from scipy.ndimage import gaussian_filter

    x = gaussian_filter(np.random.default_rng(seed).random((h, 2 * h, 3)), (2, 2, 0), mode="wrap")
    return ((x - x.min()) / (x.max() - x.min()) * 255).astype(np.uint8)


def test_loop_closure_is_zero_for_a_closed_loop_and_grows_with_the_shift():
    from panoworld.render.metrics import loop_closure_flow_deg

    a = _smooth_erp()
    assert loop_closure_flow_deg(a, a.copy()) == 0.0
    scores = [loop_closure_flow_deg(a, np.roll(a, k, axis=1)) for k in (1, 2, 4, 8)]
    # A yaw of k columns moves every pixel by k columns = k * 360 / W degrees, across the seam too.
    np.testing.assert_allclose(scores, [k * 360 / 128 for k in (1, 2, 4, 8)], rtol=0.01)
    assert np.all(np.diff(scores) > 0)
    with pytest.raises(ValueError, match="ERP"):
        loop_closure_flow_deg(a[:, :100], a[:, :100])


def test_frechet_distance_matches_the_closed_form_for_gaussians():
    from panoworld.render.metrics import frechet_distance, frechet_feature_distance

    # Commuting (diagonal) covariances: tr(S1 + S2 - 2 sqrt(S1 S2)) = sum (s1 - s2)^2 over the standard deviations.
    mu1, mu2 = np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, 0.0])
    s1, s2 = np.diag([1.0, 4.0, 9.0]), np.diag([4.0, 4.0, 1.0])
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(5.0 + 1.0 + 0.0 + 4.0, rel=1e-9)
    assert frechet_distance(mu1, s1, mu1, s1) == pytest.approx(0.0, abs=1e-9)
    f = np.random.default_rng(0).normal(size=(400, 3))
    assert frechet_feature_distance(f, f) == pytest.approx(0.0, abs=1e-9)
    assert frechet_feature_distance(f, f + [2.0, 0, 0]) == pytest.approx(4.0, rel=1e-9)
    with pytest.raises(ValueError, match="N >= 2"):
        frechet_feature_distance(f[:1], f)


def test_fid_inception_loads_a_pytorch_fid_layout_file(tmp_path):
    import torch

    from panoworld.models.inception import FIDInceptionV3
    from panoworld.models.weights import MissingWeightsError

    torch.manual_seed(0)
    net = FIDInceptionV3().eval()
    state = net.state_dict()
    # Parameter names and shapes of pytorch-fid's pt_inception-2015-12-05 file.
    assert state["Conv2d_1a_3x3.conv.weight"].shape == (32, 3, 3, 3)
    assert state["Mixed_6e.branch7x7dbl_5.conv.weight"].shape == (192, 192, 1, 7)
    assert state["Mixed_7c.branch3x3dbl_3b.bn.running_var"].shape == (384,)
    assert state["fc.weight"].shape == (1008, 2048)
    path = tmp_path / "pt_inception.pth"
    torch.save({k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}, path)
    loaded = FIDInceptionV3.from_file(path)
    imgs = _rand((2, 40, 80, 3))
    f1, f2 = net.features_uint8(imgs), loaded.features_uint8(imgs)
    assert f1.shape == (2, 2048) and np.isfinite(f1).all()
    np.testing.assert_allclose(f1, f2, rtol=1e-6, atol=1e-7)
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "alexnet.pth")
    with pytest.raises(MissingWeightsError, match="pt_inception-2015-12-05"):
        FIDInceptionV3.from_file(tmp_path / "alexnet.pth")
    with pytest.raises(MissingWeightsError, match="--fid-weights"):
        FIDInceptionV3.from_file(None)


def test_fvd_i3d_loads_a_torchscript_file_with_the_reference_call(tmp_path):
    import torch

    from panoworld.models.i3d import I3DFeatures
    from panoworld.models.weights import MissingWeightsError

    class TinyI3D(torch.nn.Module):  # stands in for the exported I3D: same call signature
        def __init__(self):
            super().__init__()
            self.proj = torch.nn.Linear(3, 5)

        def forward(self, x: torch.Tensor, rescale: bool = True, resize: bool = True, return_features: bool = False):
            assert x.shape[-2:] == (224, 224) and not rescale and not resize and return_features
            return self.proj(x.mean(dim=(2, 3, 4)))

    torch.jit.script(TinyI3D()).save(str(tmp_path / "i3d_torchscript.pt"))
    i3d = I3DFeatures.from_file(tmp_path / "i3d_torchscript.pt")
    clips = _rand((3, 4, 16, 32, 3))
    f = i3d.features_uint8(clips)
    assert f.shape == (3, 5)
    mean = torch.from_numpy(clips.astype(np.float32) / 127.5 - 1).mean(dim=(1, 2, 3))
    expected = i3d.module.proj(mean).detach().double().numpy()
    np.testing.assert_allclose(f, expected, atol=2e-3)  # INTER_AREA resizing keeps the means up to rounding
    (tmp_path / "bad.pt").write_bytes(b"not torchscript")
    with pytest.raises(MissingWeightsError, match="i3d_torchscript.pt"):
        I3DFeatures.from_file(tmp_path / "bad.pt")


def _torch_fidelity_inception():
    """torch-fidelity's InceptionV3 (a separate port of the TF FID graph), imported without its package __init__,
    which pulls torchvision in; `pip install --no-deps torch-fidelity` (its torchvision requirement breaks here)."""
    import importlib.util
    import sys
    import types

    spec = importlib.util.find_spec("torch_fidelity")
    if spec is None:
        pytest.skip("torch-fidelity is not installed (pip install --no-deps torch-fidelity)")
    if "torch_fidelity" not in sys.modules:
        pkg = types.ModuleType("torch_fidelity")
        pkg.__path__ = list(spec.submodule_search_locations)
        sys.modules["torch_fidelity"] = pkg
    from torch_fidelity.feature_extractor_inceptionv3 import FeatureExtractorInceptionV3

    return FeatureExtractorInceptionV3


def test_fid_features_match_torch_fidelitys_inception_on_the_same_random_weights(tmp_path):
    import torch

    from panoworld.models.inception import FIDInceptionV3

    reference_cls = _torch_fidelity_inception()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    net = FIDInceptionV3().eval()
    with torch.no_grad():  # random BatchNorm statistics too, so every layer's eval path is exercised
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.1, 0.1)
    path = tmp_path / "inception.pth"
    torch.save({k: v for k, v in net.state_dict().items() if not k.endswith("num_batches_tracked")}, path)
    ref = reference_cls("inception-v3-compat", ["2048"], feature_extractor_weights_path=str(path)).eval()
    u8 = torch.from_numpy(_rand((2, 299, 299, 3))).permute(0, 3, 1, 2).contiguous()
    with torch.no_grad():
        expected = ref(u8)[0].double()
        # the same network input: torch-fidelity scales as the TF graph, (u - 128) / 128; ours (pytorch-fid) as
        # 2 x - 1 of x in [0, 1], so x = ((u - 128) / 128 + 1) / 2; at 299 x 299 neither resizes
        ours = net(((u8.float() - 128) / 128 + 1) / 2).double()
    assert expected.shape == ours.shape == (2, 2048)
    assert expected.abs().mean() > 1e-3
    torch.testing.assert_close(ours, expected, rtol=1e-4, atol=1e-5 * float(expected.abs().max()))
    # and the 'uint8' path of ours differs from the TF graph only by that scaling (pytorch-fid's convention)
    f = net.features_uint8(u8.permute(0, 2, 3, 1).numpy())
    assert np.abs(f - expected.numpy()).max() < 0.05 * np.abs(expected.numpy()).max()


def test_fvd_features_match_the_styleganv_preprocessing_on_the_same_random_i3d(tmp_path):
    import torch
    import torch.nn.functional as F

    from panoworld.models.i3d import I3DFeatures

    class RandomI3D(torch.nn.Module):  # random 3D-conv features behind the reference call signature
        def __init__(self):
            super().__init__()
            self.conv = torch.nn.Conv3d(3, 8, kernel_size=(3, 7, 7), stride=(1, 2, 2), padding=(1, 3, 3))
            self.head = torch.nn.Linear(8 * 4, 400)

        def forward(self, x: torch.Tensor, rescale: bool = False, resize: bool = False,
                    return_features: bool = True):
            h = torch.relu(self.conv(x))
            h = F.adaptive_avg_pool3d(h, (1, 2, 2)).flatten(1)
            return self.head(h)

    torch.manual_seed(0)
    torch.jit.script(RandomI3D()).save(str(tmp_path / "i3d_torchscript.pt"))
    i3d = I3DFeatures.from_file(tmp_path / "i3d_torchscript.pt")
    clips = _rand((2, 8, 224, 224, 3), seed=5)

    def styleganv_preprocess(video: np.ndarray) -> torch.Tensor:
        # StyleGAN-V's FVD: [0, 1] video (C, T, H, W), short side resized to 224 (bilinear), centre crop, -> [-1, 1]
        v = torch.from_numpy(video).permute(3, 0, 1, 2).float() / 255.0
        c, t, h, w = v.shape
        s = 224 / min(h, w)
        if (h, w) != (224, 224):
            v = F.interpolate(v, size=(int(np.ceil(h * s)), int(np.ceil(w * s))), mode="bilinear", align_corners=False)
        h, w = v.shape[-2:]
        v = v[:, :, (h - 224) // 2:(h - 224) // 2 + 224, (w - 224) // 2:(w - 224) // 2 + 224]
        return (v - 0.5) * 2

    with torch.no_grad():
        x = torch.stack([styleganv_preprocess(c) for c in clips])
        expected = i3d.module(x, rescale=False, resize=False, return_features=True).double().numpy()
    ours = i3d.features_uint8(clips)
    assert ours.shape == expected.shape == (2, 400)
    np.testing.assert_allclose(ours, expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())
