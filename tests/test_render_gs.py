"""Gaussian renderer: tile rasteriser against the brute-force oracle, analytic EWA footprints, ERP cube-face resampling."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from panoworld.core.conventions import erp_pixel_from_dir, rotmat_from_quat_wxyz
from panoworld.io.gaussian_set import SH_C0, Gaussians, rgb_to_sh_dc
from panoworld.render.erp import render_erp
from panoworld.render.splats import LOWPASS, covariance_3d, eval_sh, render_perspective, rotmat_from_quat

torch.set_num_threads(1)


def random_gaussians(n: int, seed: int = 0, sh_k: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1, 1, (n, 3)) * [1.5, 1.0, 2.8] + [0, 0, 2.5]  # some behind the camera, some outside the view
    return Gaussians(
        means=means.astype(np.float32),
        scales=rng.uniform(0.01, 0.3, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=rng.uniform(0.0, 1.0, n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=0.3 * rng.normal(size=(n, sh_k, 3)).astype(np.float32),
    )


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_tiles_match_brute_force_reference(backend):
    g = random_gaussians(400, sh_k=3)
    pose = np.eye(4)
    pose[:3, 3] = [0.1, -0.05, 0.2]
    H, W = 45, 70  # not multiples of the tile size
    args = (g, pose, 55.0, 50.0, 33.0, 24.0, H, W)
    tile = render_perspective(*args, background=[0.2, 0.3, 0.4], backend=backend)
    ref = render_perspective(*args, background=[0.2, 0.3, 0.4], reference=True)
    assert (tile.rgb - ref.rgb).abs().max() < 1e-5
    assert (tile.alpha - ref.alpha).abs().max() < 1e-5
    assert ((tile.depth - ref.depth).abs() / ref.depth.clamp(min=1)).max() < 1e-5
    assert 0.3 < float(ref.alpha.mean()) < 1.0  # a non-trivial image


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_early_termination_matches_reference(backend):
    # A stack of opaque Gaussians: pixels saturate and stop before the back layers, in both renderers.
    n = 60
    means = np.stack([np.zeros(n), np.zeros(n), np.linspace(1.0, 3.0, n)], 1).astype(np.float32)
    colors = np.tile([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], (n // 2, 1))
    g = Gaussians(
        means=means, scales=np.full((n, 3), 0.5, np.float32), quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
        opacities=np.full(n, 0.95, np.float32), sh_dc=rgb_to_sh_dc(colors).astype(np.float32),
    )
    args = (g, np.eye(4), 20.0, 20.0, 16.5, 16.5, 32, 32)
    tile = render_perspective(*args, backend=backend)
    ref = render_perspective(*args, reference=True)
    assert (tile.rgb - ref.rgb).abs().max() < 1e-6
    assert (tile.alpha - ref.alpha).abs().max() < 1e-6
    # At the centre pixel each layer has alpha 0.95: after 3 layers T = 1.25e-4, the 4th would take it below 1e-4,
    # so compositing stops with T = 0.05^3 (not 0.05^60).
    assert 1 - float(tile.alpha[16, 16]) == pytest.approx(0.05**3, rel=1e-3)
    assert float(tile.rgb[16, 16, 0]) == pytest.approx(0.95 + 0.95 * 0.05**2, abs=1e-5)
    assert float(tile.rgb[16, 16, 2]) == pytest.approx(0.95 * 0.05, abs=1e-5)


def test_single_gaussian_has_the_analytic_ewa_footprint():
    # An isotropic Gaussian on the optical axis projects to sigma_px = f s / z (the Jacobian is exact there), plus 0.3.
    f, s, z, o = 40.0, 0.05, 2.0, 0.8
    g = Gaussians(
        means=np.array([[0.0, 0.0, z]], np.float32), scales=np.full((1, 3), s, np.float32),
        quats=np.array([[1.0, 0, 0, 0]], np.float32), opacities=np.array([o], np.float32),
        sh_dc=np.zeros((1, 3), np.float32),
    )
    H = W = 33
    out = render_perspective(g, np.eye(4), f, f, W / 2, H / 2, H, W)
    var = (f * s / z) ** 2 + LOWPASS
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    expect = o * np.exp(-0.5 * ((jj - W / 2) ** 2 + (ii - H / 2) ** 2) / var)
    expect[expect < 1 / 255] = 0
    assert np.abs(out.alpha.numpy() - expect).max() < 1e-5
    assert np.allclose(out.depth.numpy()[expect > 0], z, atol=1e-5)
    assert np.allclose(out.rgb.numpy()[..., 0], expect * 0.5, atol=1e-5)  # colour 0.5 over black


def test_covariance_and_rotation_helpers_agree_with_conventions():
    q = torch.randn(16, 4)
    R = rotmat_from_quat(q).numpy()
    assert np.allclose(R, rotmat_from_quat_wxyz(q.numpy()), atol=1e-6)
    s = torch.rand(16, 3)
    cov = covariance_3d(s, q).numpy()
    assert np.allclose(cov, R @ np.einsum("ni,ij->nij", s.numpy() ** 2, np.eye(3)) @ R.transpose(0, 2, 1), atol=1e-6)


def test_eval_sh_degree_one_depends_on_view_direction():
    dc = torch.zeros(2, 3)
    rest = torch.zeros(2, 3, 3)
    rest[:, 1, 0] = 1.0  # the z-coefficient of the red channel
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    rgb = eval_sh(dc, rest, dirs)
    assert float(rgb[0, 0]) == pytest.approx(0.5 + 0.4886025119029199, abs=1e-6)
    assert float(rgb[1, 0]) == pytest.approx(0.5 - 0.4886025119029199, abs=1e-6)
    assert torch.allclose(rgb[:, 1:], torch.full((2, 2), 0.5))
    assert SH_C0 == pytest.approx(0.5 / np.sqrt(np.pi))


def shell(radius: float, n: int = 3000) -> tuple[Gaussians, callable]:
    """Opaque Gaussians on a Fibonacci sphere around the origin; colour is a smooth function of direction."""
    k = np.arange(n) + 0.5
    y = 1 - 2 * k / n
    lon = np.pi * (1 + 5**0.5) * k
    d = np.stack([np.sqrt(1 - y**2) * np.cos(lon), y, np.sqrt(1 - y**2) * np.sin(lon)], 1)

    def color(dirs):
        return 0.5 + 0.3 * dirs[..., [0, 1, 2]] * [1.0, 1.0, -1.0]

    spacing = radius * np.sqrt(4 * np.pi / n)
    g = Gaussians(
        means=(radius * d).astype(np.float32), scales=np.full((n, 3), spacing, np.float32),
        quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32), opacities=np.full(n, 0.99, np.float32),
        sh_dc=rgb_to_sh_dc(color(d)).astype(np.float32),
    )
    return g, color


def test_erp_of_a_shell_is_complete_with_exact_depth_across_seam_and_poles():
    from panoworld.core.conventions import erp_dirs

    g, color = shell(2.0)
    pose = np.eye(4)
    H, W = 32, 64
    out = render_erp(g, pose, H, W)
    assert float(out.alpha.min()) > 0.99
    assert np.allclose(out.depth.numpy(), 2.0, atol=0.05)
    expect = color(erp_dirs(H, W))
    assert np.abs(out.rgb.numpy() - expect).max() < 0.05
    # A rotated camera sees the same shell rotated: the seam and poles move, the image stays consistent.
    pose[:3, :3] = rotmat_from_quat_wxyz(np.array([0.9, 0.1, 0.3, -0.2]))
    out = render_erp(g, pose, H, W)
    dirs_world = erp_dirs(H, W) @ pose[:3, :3].T
    assert np.abs(out.rgb.numpy() - color(dirs_world)).max() < 0.05


def test_erp_places_a_gaussian_at_its_direction():
    d = np.array([0.6, -0.3, -0.74])
    d /= np.linalg.norm(d)
    g = Gaussians(
        means=(3.0 * d)[None].astype(np.float32), scales=np.full((1, 3), 0.05, np.float32),
        quats=np.array([[1.0, 0, 0, 0]], np.float32), opacities=np.array([0.9], np.float32),
        sh_dc=np.zeros((1, 3), np.float32),
    )
    H, W = 64, 128
    out = render_erp(g, np.eye(4), H, W)
    i, j = np.unravel_index(int(out.alpha.argmax()), (H, W))
    u, v = erp_pixel_from_dir(d, H, W)
    assert abs(j + 0.5 - u) <= 1.0 and abs(i + 0.5 - v) <= 1.0
    assert float(out.depth[i, j]) == pytest.approx(3.0, abs=0.02)


def test_bad_arguments_raise():
    g = random_gaussians(4)
    with pytest.raises(ValueError, match="2:1"):
        render_erp(g, np.eye(4), 32, 48)
    with pytest.raises(ValueError, match="expected \\(4, 4\\)"):
        render_perspective(g, np.eye(3), 10, 10, 5, 5, 10, 10)
    with pytest.raises(ValueError, match="backend"):
        render_perspective(g, np.eye(4), 10, 10, 5, 5, 10, 10, backend="vulkan")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat path needs CUDA")
def test_gsplat_matches_torch_renderer():
    pytest.importorskip("gsplat")
    g = random_gaussians(300)
    args = (np.eye(4), 55.0, 50.0, 33.0, 24.0, 48, 64)
    cpu = render_perspective(g, *args, backend="torch")
    gt = Gaussians(**{k: torch.as_tensor(getattr(g, k)).cuda() for k in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")})
    gpu = render_perspective(gt, *args, backend="gsplat")
    assert (gpu.rgb.cpu() - cpu.rgb).abs().max() < 1e-2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat path needs CUDA")
def test_gsplat_erp_matches_torch_erp():
    pytest.importorskip("gsplat")
    from panoworld.tools.synth.surfels import room_surfels

    g = room_surfels(3000)  # surfaces: the faces' depth along each ray is the centres' distance there
    gt = Gaussians(**{k: torch.as_tensor(getattr(g, k)).cuda() for k in ("means", "scales", "quats", "opacities", "sh_dc")})
    cpu = render_erp(g, np.eye(4), 32, 64, backend="torch")
    gpu = render_erp(gt, np.eye(4), 32, 64)
    assert (gpu.rgb - cpu.rgb).abs().max() < 2e-2 and (gpu.alpha - cpu.alpha).abs().max() < 2e-2
    seen = (cpu.alpha > 0.5) & (gpu.alpha > 0.5)
    assert seen.any() and ((gpu.depth - cpu.depth).abs() / cpu.depth)[seen].median() < 0.01


def test_renderer_gradients_match_finite_differences():
    # Smooth conditions: large, semi-transparent Gaussians in view (few alpha-threshold crossings, no clamping).
    rng = np.random.default_rng(3)
    g = random_gaussians(20, seed=3)
    g.means[:, 2] = rng.uniform(2.0, 4.0, 20)
    g.scales[:] = rng.uniform(0.15, 0.3, (20, 3))
    g.opacities[:] = rng.uniform(0.2, 0.6, 20)
    names = ("means", "scales", "opacities", "sh_dc")
    base = {k: torch.tensor(getattr(g, k), dtype=torch.float64) for k in ("means", "scales", "quats", "opacities", "sh_dc")}
    target = torch.rand(20, 28, 3, generator=torch.Generator().manual_seed(0))

    def loss(p):
        out = render_perspective(Gaussians(**p), np.eye(4), 25.0, 25.0, 14.0, 10.0, 20, 28, backend="torch")
        return ((out.rgb - target) ** 2).sum()

    params = {k: v.clone().requires_grad_(k in names) for k, v in base.items()}
    loss(params).backward()
    rng = np.random.default_rng(0)
    for name in names:
        v = torch.from_numpy(rng.normal(size=base[name].shape)) * 1e-3
        hi = loss({**base, name: base[name] + v})
        lo = loss({**base, name: base[name] - v})
        numeric = float(hi - lo) / 2
        analytic = float((params[name].grad * v).sum())
        assert analytic == pytest.approx(numeric, rel=0.05, abs=1e-4), name


def test_erp_supersampling_averages_detail_finer_than_a_pixel():
    """Stripes 1.3 px wide: supersampled renders approach the area average of the texture, a plain one aliases."""
    from panoworld.core.conventions import erp_dirs

    n = 40000
    k = np.arange(n) + 0.5
    y = 1 - 2 * k / n
    lon = np.pi * (1 + 5**0.5) * k
    d = np.stack([np.sqrt(1 - y**2) * np.cos(lon), y, np.sqrt(1 - y**2) * np.sin(lon)], 1)

    def color(dirs):
        stripe = np.sin(48 * np.arctan2(dirs[..., 0], dirs[..., 2])) > 0
        return np.repeat(np.where(stripe, 0.9, 0.1)[..., None], 3, -1)

    spacing = 2.0 * np.sqrt(4 * np.pi / n)
    g = Gaussians(
        means=(2.0 * d).astype(np.float32), scales=np.full((n, 3), 0.6 * spacing, np.float32),
        quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32), opacities=np.full(n, 0.99, np.float32),
        sh_dc=rgb_to_sh_dc(color(d)).astype(np.float32),
    )
    H, W, s = 32, 64, 8
    ref = color(erp_dirs(s * H, s * W)).reshape(H, s, W, s, 3).mean((1, 3))
    rows = slice(H // 4, 3 * H // 4)  # |lat| < 45 deg: the stripes are finer than a pixel there
    err = {}
    for ss in (1, 2, 4):
        out = render_erp(g, np.eye(4), H, W, supersample=ss, pole_scale=1.0)  # finer pole faces show the gaps
        assert float(out.alpha.min()) > 0.99
        assert np.allclose(out.depth.numpy(), 2.0, atol=0.05)
        err[ss] = float(np.abs(out.rgb.numpy() - ref)[rows].mean())
    assert err[4] < 0.5 * err[1] and err[2] < 0.9 * err[1], err
    with pytest.raises(ValueError, match="supersample"):
        render_erp(g, np.eye(4), H, W, supersample=0)


@pytest.mark.parametrize("supersample, pole_scale", [(1, 1.0), (2, 1.0), (2, 2.0)])
def test_erp_color_operator_is_the_render_as_a_linear_map_of_colours(supersample, pole_scale):
    from panoworld.render.erp_operator import ErpColorOperator

    g, _ = shell(3.0, 2000)
    inner = random_gaussians(300, seed=3)  # overlapping, partly transparent Gaussians in front of the shell
    inner = Gaussians(inner.means * 0.4, inner.scales * 0.5, inner.quats, inner.opacities, inner.sh_dc)
    both = Gaussians(*(np.concatenate([getattr(a, f) for a in (g, inner)]) for f in
                       ("means", "scales", "quats", "opacities", "sh_dc")))
    pose = np.eye(4)
    pose[:3, 3] = [0.2, -0.1, 0.3]
    op = ErpColorOperator(both, pose, 24, 48, supersample=supersample, pole_scale=pole_scale)
    rgb = (0.5 + SH_C0 * torch.from_numpy(both.sh_dc)).clamp(min=0)  # eval_sh's colour
    want = render_erp(both, pose, 24, 48, supersample=supersample, pole_scale=pole_scale).rgb
    torch.testing.assert_close(op(rgb), want, atol=2e-5, rtol=0)
    other = torch.rand(len(both), 3)  # linear: any colours, not only the Gaussians' own
    mixed = Gaussians(both.means, both.scales, both.quats, both.opacities, rgb_to_sh_dc(other.numpy()))
    torch.testing.assert_close(op(other), render_erp(mixed, pose, 24, 48, supersample=supersample,
                                                     pole_scale=pole_scale).rgb,
                               atol=2e-5, rtol=0)
    img = torch.rand(24, 48, 3, dtype=torch.float64)  # the adjoint: <A x, y> = <x, A^T y>
    lhs, rhs = float((op(other).double() * img).sum()), float((other.double() * op.adjoint(img.float())).sum())
    assert abs(lhs - rhs) < 1e-4 * abs(lhs)


def test_erp_pole_scale_resolves_longitude_detail_near_the_poles():
    """Radial stripes around both poles, 2 ERP columns wide: near a pole they are finer than a cube-face pixel (ERP
    rows sample longitude tan(lat) times more finely than the face), so finer pole faces follow the area average."""
    from panoworld.core.conventions import erp_dirs
    from panoworld.render.erp import erp_faces

    n = 60000
    k = np.arange(n) + 0.5
    y = np.sign(k - n / 2) * (0.8 + 0.2 * (np.abs(2 * k / n - 1)))  # |y| in [0.8, 1]: the polar caps only
    lon = np.pi * (1 + 5**0.5) * k
    d = np.stack([np.sqrt(1 - y**2) * np.cos(lon), y, np.sqrt(1 - y**2) * np.sin(lon)], 1)

    def color(dirs):
        stripe = np.sin(16 * np.arctan2(dirs[..., 0], dirs[..., 2])) > 0
        return np.repeat(np.where(stripe, 0.9, 0.1)[..., None], 3, -1)

    spacing = np.sqrt(2 * 2 * np.pi * 0.2 / n)
    g = Gaussians(
        means=(2.0 * d).astype(np.float32), scales=np.full((n, 3), 0.6 * spacing * 2.0, np.float32),
        quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32), opacities=np.full(n, 0.99, np.float32),
        sh_dc=rgb_to_sh_dc(color(d)).astype(np.float32),
    )
    H, W, s = 32, 64, 8
    ref = color(erp_dirs(s * H, s * W)).reshape(H, s, W, s, 3).mean((1, 3))
    lat = 90 - (np.arange(H) + 0.5) / H * 180
    rows = (np.abs(lat) > 70) & (np.abs(lat) < 85)
    err = {}
    for pole in (1, 3):
        sizes = {f.n for f in erp_faces(np.eye(4), H, W, pole_scale=pole)}
        assert len(sizes) == (1 if pole == 1 else 2)
        out = render_erp(g, np.eye(4), H, W, pole_scale=pole)
        assert float(out.alpha[rows].min()) > 0.99
        err[pole] = float(np.abs(out.rgb.numpy() - ref)[rows].mean())
    assert err[3] < 0.6 * err[1], err
    with pytest.raises(ValueError, match="pole_scale"):
        render_erp(g, np.eye(4), H, W, pole_scale=0.5)


@pytest.mark.parametrize("n, opacity", [(400, None), (120, 0.95)])
def test_numba_face_weights_match_the_torch_tile_rasteriser(n, opacity):
    # The colour fit's kernel (splat_weights) against rasterize_tiles(weights=...): the same (pixel, Gaussian) pairs,
    # the same weights up to exp's last bit. Tiles hold > 32 Gaussians (several chunks); opaque ones stop pixels early.
    from panoworld.render.splats import _prepare, bin_tiles, face_weights, project, rasterize_tiles

    g = random_gaussians(n, seed=5)
    if opacity is not None:
        g = Gaussians(g.means * [0.2, 0.2, 1.0], g.scales, g.quats, np.full(n, opacity, np.float32), g.sh_dc)
    H, W = 45, 70  # not multiples of the tile size
    proj = project(_prepare(g, np.zeros(3)), np.eye(4), 55.0, 50.0, 33.0, 24.0, H, W)
    parts: list = []
    torch_T = rasterize_tiles(proj, H, W, torch.zeros(3), weights=parts).alpha
    pix, gid, w = (torch.cat(x).numpy() for x in zip(*parts))
    pix2, gid2, w2 = face_weights(proj, H, W)
    assert pix2.dtype == gid2.dtype == np.int32 and w2.dtype == np.float32
    key, key2 = pix * n + gid, pix2.astype(np.int64) * n + gid2
    o, o2 = np.argsort(key), np.argsort(key2)
    np.testing.assert_array_equal(key[o], key2[o2])
    # float32 transmittance chains: a few weights differ in the last bits with the CPU's vector width (3e-6 seen)
    np.testing.assert_allclose(w2[o2], w[o], rtol=2e-5, atol=1e-8)
    assert int(bin_tiles(proj, H, W)[3].max()) > 2 * 32  # tiles hold several chunks
    alpha = np.bincount(pix2, weights=w2, minlength=H * W).reshape(H, W)  # the weights sum to 1 - T
    np.testing.assert_allclose(alpha, torch_T.numpy(), atol=1e-5)
    if opacity is not None:
        assert float(torch_T.max()) > 1 - 1e-3  # saturated pixels: early termination exercised


@pytest.mark.parametrize("dtype", [np.int32, np.float32])
def test_numba_weight_buffers_grow_keeping_their_contents(dtype):
    from panoworld.render.splat_weights import _grow

    a = np.arange(7).astype(dtype) * 3
    out = _grow(a, 11)
    assert out.dtype == dtype and out.shape == (11,)
    np.testing.assert_array_equal(out[:7], a)


def cull_scene(seed: int = 0) -> tuple[Gaussians, np.ndarray]:
    """Gaussians around a turned, moved camera: a shell, some on the cube faces' edges and corners (straddling two or
    three faces), some near the camera's centre (behind and in front of the near plane), big ones close to it, and
    opacities at the 1/255 threshold."""
    from panoworld.render.splats import ALPHA_MIN

    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = rotmat_from_quat_wxyz(np.array([0.9, 0.2, -0.3, 0.1]) / np.linalg.norm([0.9, 0.2, -0.3, 0.1]))
    pose[:3, 3] = [0.3, -0.2, 0.1]
    n = 1500
    k = np.arange(n) + 0.5
    y = 1 - 2 * k / n
    lon = np.pi * (1 + 5**0.5) * k
    shell = 3.0 * np.stack([np.sqrt(1 - y**2) * np.cos(lon), y, np.sqrt(1 - y**2) * np.sin(lon)], 1)
    edges = np.array([[a, b, 0] for a in (-1, 1) for b in (-1, 1)] + [[a, 0, b] for a in (-1, 1) for b in (-1, 1)]
                     + [[0, a, b] for a in (-1, 1) for b in (-1, 1)] + [[a, b, c] for a in (-1, 1) for b in (-1, 1)
                                                                         for c in (-1, 1)], float)
    edges = np.repeat(edges / np.linalg.norm(edges, axis=1, keepdims=True), 10, 0)
    edges = (edges + rng.normal(0, 0.01, edges.shape)) * rng.uniform(0.3, 4.0, (len(edges), 1))
    near = rng.normal(size=(20, 3))
    near *= rng.uniform(0.002, 0.03, (20, 1)) / np.linalg.norm(near, axis=1, keepdims=True)
    big = rng.normal(size=(12, 3))
    big *= rng.uniform(0.2, 0.8, (12, 1)) / np.linalg.norm(big, axis=1, keepdims=True)
    local = np.concatenate([shell, edges, near, big])
    m = len(local)
    scales = np.concatenate([np.full((n, 3), 0.1), rng.uniform(0.005, 0.3, (len(edges), 3)),
                             rng.uniform(0.001, 0.05, (20, 3)), rng.uniform(0.3, 1.2, (12, 3))])
    scales[rng.random(m) < 0.2, 0] *= 10  # some needles
    opacity = rng.uniform(0.05, 1.0, m)
    opacity[-32:] = rng.uniform(0.01, 0.1, 32)  # the near and big ones: the shell shows through
    opacity[rng.choice(m, 40, replace=False)] = ALPHA_MIN * rng.choice([0.999, 1.0, 1.000001, 1.001, 1.1], 40)
    g = Gaussians(means=(local @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32), scales=scales.astype(np.float32),
                  quats=rng.normal(size=(m, 4)).astype(np.float32), opacities=opacity.astype(np.float32),
                  sh_dc=rng.normal(size=(m, 3)).astype(np.float32), sh_rest=0.3 * rng.normal(size=(m, 3, 3)).astype(np.float32))
    return g, pose


def render_erp_projecting_all(g: Gaussians, pose: np.ndarray, H: int, W: int, background, **kw):
    """render_erp's torch path as it was before the face cull: every Gaussian projected on every face."""
    from panoworld.render.erp import _compose_erp, erp_faces
    from panoworld.render.splats import _prepare, invert_pose, project, rasterize_tiles

    prep = _prepare(g, pose[:3, 3])
    bg = torch.as_tensor(background, dtype=torch.float32)

    def face(fc):
        proj = project(prep, invert_pose(fc.world_from_face), fc.f, fc.f, fc.c, fc.c, fc.n, fc.n)
        return rasterize_tiles(proj, fc.n, fc.n, bg, raw=True, distance=True)

    return _compose_erp(erp_faces(pose, H, W, **kw), H, W, kw.get("supersample", 2), face)


@pytest.mark.parametrize("supersample, pole_scale", [(1, 1.0), (2, 2.0), (2, 1.5)])
def test_erp_face_cull_renders_what_projecting_every_gaussian_renders(supersample, pole_scale):
    from panoworld.render.erp import erp_faces, face_cull
    from panoworld.render.splats import _prepare, invert_pose, project

    g, pose = cull_scene()
    H, W = 24, 48
    kw = dict(supersample=supersample, pole_scale=pole_scale)
    prep = _prepare(g, pose[:3, 3])
    cull = face_cull(prep, g.scales, pose[:3, 3], 0.01)
    total = 0
    for fc in erp_faces(pose, H, W, **kw):  # the culled faces keep exactly the Gaussians project keeps, in order
        full = project(prep, invert_pose(fc.world_from_face), fc.f, fc.f, fc.c, fc.c, fc.n, fc.n)
        sub, cand = cull(fc)
        part = project(sub, invert_pose(fc.world_from_face), fc.f, fc.f, fc.c, fc.c, fc.n, fc.n)
        assert torch.equal(cand[part.index], full.index)
        total += len(cand)
    assert total < 2.5 * len(g), total  # most Gaussians projected on one or two faces, not six
    bg = [0.2, 0.5, 0.7]
    want = render_erp_projecting_all(g, pose, H, W, bg, **kw)
    got = render_erp(g, pose, H, W, background=bg, backend="torch", **kw)
    for name in ("rgb", "depth", "alpha"):
        assert float((getattr(got, name) - getattr(want, name)).abs().max()) <= 1e-6, name
    assert float(got.alpha.mean()) > 0.9 and float(got.depth.max() - got.depth.min()) > 1.0  # not a blank view


def test_erp_face_cull_keeps_gradients():
    g, pose = cull_scene(1)
    target = torch.rand(16, 32, 3, generator=torch.Generator().manual_seed(0))
    grads = []
    for render in (render_erp, render_erp_projecting_all):
        means = torch.tensor(g.means, requires_grad=True)
        opac = torch.tensor(g.opacities, requires_grad=True)
        gi = Gaussians(means=means, scales=torch.tensor(g.scales), quats=torch.tensor(g.quats), opacities=opac,
                       sh_dc=torch.tensor(g.sh_dc), sh_rest=torch.tensor(g.sh_rest))
        out = render(gi, pose, 16, 32, background=[0.0, 0.0, 0.0], supersample=1)
        ((out.rgb - target) ** 2).sum().backward()
        grads.append((means.grad, opac.grad))
    for a, b in zip(*grads):
        assert a.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def sh1_scene() -> tuple[Gaussians, np.ndarray]:
    """cull_scene with view-dependent colour (SH degree 1) strong enough to change the image."""
    g, pose = cull_scene(2)
    rest = np.random.default_rng(3).normal(0, 0.4, (len(g), 3, 3)).astype(np.float32)
    return Gaussians(g.means, g.scales, g.quats, g.opacities, g.sh_dc, rest), pose


@pytest.mark.parametrize("supersample, pole_scale", [(2, 2.0), (1, 1.5)])
def test_erp_numba_backend_equals_the_torch_rasteriser(supersample, pole_scale):
    # The torch tile rasteriser is the oracle; "auto" without gradients is the numba path.
    g, pose = sh1_scene()
    assert g.sh_degree == 1
    kw = dict(background=[0.2, 0.5, 0.7], supersample=supersample, pole_scale=pole_scale)
    want = render_erp(g, pose, 24, 48, backend="torch", **kw)
    got = render_erp(g, pose, 24, 48, backend="numba", **kw)
    auto = render_erp(g, pose, 24, 48, **kw)
    for name in ("rgb", "depth", "alpha"):
        assert float((getattr(got, name) - getattr(want, name)).abs().max()) <= 1e-5, name
        assert torch.equal(getattr(auto, name), getattr(got, name)), name
    sh0 = render_erp(Gaussians(g.means, g.scales, g.quats, g.opacities, g.sh_dc), pose, 24, 48, **kw)
    assert float((sh0.rgb - got.rgb).abs().max()) > 0.05  # the SH term shows
    assert float(got.alpha.min()) < 0.95  # the background colour shows through somewhere
    assert float(got.depth.max() - got.depth.min()) > 1.0


def test_erp_with_requires_grad_gaussians_takes_the_torch_path():
    g, pose = sh1_scene()
    means = torch.tensor(g.means, requires_grad=True)
    gi = Gaussians(means=means, scales=torch.tensor(g.scales), quats=torch.tensor(g.quats),
                   opacities=torch.tensor(g.opacities), sh_dc=torch.tensor(g.sh_dc), sh_rest=torch.tensor(g.sh_rest))
    kw = dict(background=[0.2, 0.5, 0.7], supersample=2)
    out = render_erp(gi, pose, 16, 32, **kw)
    assert out.rgb.requires_grad
    out.rgb.sum().backward()
    assert means.grad is not None and float(means.grad.abs().max()) > 0
    with pytest.raises(ValueError, match="requires grad"):
        render_erp(gi, pose, 16, 32, backend="numba", **kw)
    with torch.no_grad():  # no gradient wanted: the numba path
        fast = render_erp(gi, pose, 16, 32, **kw)
    assert not fast.rgb.requires_grad
    assert torch.equal(fast.rgb, render_erp(g, pose, 16, 32, backend="numba", **kw).rgb)
    assert float((fast.rgb - out.rgb.detach()).abs().max()) <= 1e-5



def test_erp_numba_path_of_requires_grad_gaussians_under_no_grad_on_several_threads():
    # render_erp composites the faces on torch's threads; grad mode is per thread, so the workers must not track
    # gradients of a Gaussian tensor that requires grad when the caller asked for none (torch.no_grad)
    g, pose = sh1_scene()
    gi = Gaussians(means=torch.tensor(g.means, requires_grad=True), scales=torch.tensor(g.scales),
                   quats=torch.tensor(g.quats), opacities=torch.tensor(g.opacities), sh_dc=torch.tensor(g.sh_dc),
                   sh_rest=torch.tensor(g.sh_rest))
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with torch.no_grad():
            fast = render_erp(gi, pose, 16, 32, supersample=2)
    finally:
        torch.set_num_threads(threads)
    assert not fast.rgb.requires_grad
    assert torch.equal(fast.rgb, render_erp(g, pose, 16, 32, supersample=2, backend="numba").rgb)

def test_perspective_numba_backend_equals_the_torch_rasteriser_and_keeps_gradients():
    # Pinhole views: "auto" without gradients is the numba path, within float32 rounding of the torch oracle; with a
    # Gaussian tensor that requires grad it is the differentiable torch path, and "numba" refuses.
    g, pose = sh1_scene()
    args = (pose, 30.0, 28.0, 21.0, 15.5, 31, 44)
    want = render_perspective(g, *args, background=[0.2, 0.5, 0.7], backend="torch")
    got = render_perspective(g, *args, background=[0.2, 0.5, 0.7], backend="numba")
    auto = render_perspective(g, *args, background=[0.2, 0.5, 0.7])
    for name in ("rgb", "depth", "alpha"):
        assert float((getattr(got, name) - getattr(want, name)).abs().max()) <= 1e-5, name
        assert torch.equal(getattr(auto, name), getattr(got, name)), name
    assert float(got.alpha.min()) < 0.9 and float(got.depth.max() - got.depth.min()) > 0.3  # a non-trivial view
    means = torch.tensor(g.means, requires_grad=True)
    gi = Gaussians(means=means, scales=torch.tensor(g.scales), quats=torch.tensor(g.quats),
                   opacities=torch.tensor(g.opacities), sh_dc=torch.tensor(g.sh_dc), sh_rest=torch.tensor(g.sh_rest))
    out = render_perspective(gi, *args)
    out.rgb.sum().backward()
    assert means.grad is not None and float(means.grad.abs().max()) > 0
    with pytest.raises(ValueError, match="requires grad"):
        render_perspective(gi, *args, backend="numba")


def test_all_zero_sh_rest_renders_as_degree_zero_and_nonzero_rest_still_shows():
    # A degree-3 .ply of degree-0 colours (45 zero f_rest columns) skips the SH terms: bit for bit the same image.
    g, pose = sh1_scene()
    zero = Gaussians(g.means, g.scales, g.quats, g.opacities, g.sh_dc, np.zeros((len(g), 15, 3), np.float32))
    dc = Gaussians(g.means, g.scales, g.quats, g.opacities, g.sh_dc)
    a, b = render_erp(zero, pose, 16, 32), render_erp(dc, pose, 16, 32)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)
    one = zero.sh_rest.copy()
    one[7, 2] = 0.5  # a single non-zero coefficient keeps every term
    c = render_erp(Gaussians(g.means, g.scales, g.quats, g.opacities, g.sh_dc, one), pose, 16, 32)
    assert not torch.equal(c.rgb, a.rgb)


def test_room_surfels_lie_on_the_rooms_shell():
    from panoworld.tools.synth.surfels import ROOM_HALF_M, room_surfels

    g = room_surfels(500)
    on_face = np.isclose(np.abs(g.means), np.array(ROOM_HALF_M, np.float32)).any(axis=1)
    assert on_face.all() and (np.abs(g.means) <= np.array(ROOM_HALF_M) + 1e-6).all()


@pytest.mark.parametrize("tile", [8, 16])
def test_numba_bin_tiles_equal_torch(tile):
    # face_weights bins by a numba counting sort; bin_tiles (torch argsort by (tile, depth rank)) is its oracle
    from panoworld.render.splat_weights import bin_tiles_numba
    from panoworld.render.splats import _prepare, bin_tiles, project

    g = random_gaussians(500, seed=7)
    H, W = 45, 70
    proj = project(_prepare(g, np.zeros(3)), np.eye(4), 55.0, 50.0, 33.0, 24.0, H, W)
    proj.z[::7] = proj.z[3]  # ties in depth: both keep index order
    ref = bin_tiles(proj, H, W, tile)
    ours = bin_tiles_numba(proj.xy.numpy(), proj.extent.numpy(), proj.z.numpy(), H, W, tile)
    assert ours[:2] == ref[:2] and len(ref[2]) > 500
    for a, b in zip(ours[2:], ref[2:]):
        assert np.array_equal(a, b.numpy())


@pytest.mark.parametrize("supersample", [1, 2])
def test_erp_of_some_pixels_renders_only_their_faces_and_keeps_their_values(supersample):
    # A patch of pixels below the horizon in front of the camera and another at the north pole: the render of those
    # pixels alone equals the full render there, and the faces that sample neither are not rendered (their pixels 0).
    g, pose = cull_scene()
    H, W = 24, 48
    full = render_erp(g, pose, H, W, supersample=supersample)
    pixels = np.zeros((H, W), bool)
    pixels[14:17, 20:24] = True
    pixels[0, :5] = True
    part = render_erp(g, pose, H, W, supersample=supersample, pixels=pixels)
    for name in ("rgb", "depth", "alpha"):
        torch.testing.assert_close(getattr(part, name)[torch.from_numpy(pixels)],
                                   getattr(full, name)[torch.from_numpy(pixels)], rtol=0, atol=0)
    assert float(full.alpha.min()) > 0 and (part.alpha == 0).float().mean() > 0.3
    with pytest.raises(ValueError, match="pixels.shape"):
        render_erp(g, pose, H, W, pixels=pixels[:, :10])
