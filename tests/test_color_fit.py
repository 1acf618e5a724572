"""The colour fit's operator on part of a view, and view-dependent (degree-1 SH) colours fitted from several views."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from panoworld.core.conventions import pose_from_rt
from panoworld.io.gaussian_set import Gaussians, rgb_to_sh_dc
from panoworld.render.erp import render_erp

torch.set_num_threads(1)


def shell_and_clutter(seed: int = 0) -> Gaussians:
    """Opaque Gaussians on a sphere of radius 3 around the origin, and overlapping, partly transparent ones inside it
    (some large and near the camera, some behind it)."""
    rng = np.random.default_rng(seed)
    n, m = 2500, 300
    k = np.arange(n) + 0.5
    y = 1 - 2 * k / n
    lon = np.pi * (1 + 5**0.5) * k
    d = np.stack([np.sqrt(1 - y**2) * np.cos(lon), y, np.sqrt(1 - y**2) * np.sin(lon)], 1)
    means = np.concatenate([3.0 * d, rng.uniform(-1.5, 1.5, (m, 3))])
    scales = np.concatenate([np.full((n, 3), 3.0 * np.sqrt(4 * np.pi / n)), rng.uniform(0.01, 0.4, (m, 3))])
    return Gaussians(
        means=means.astype(np.float32), scales=scales.astype(np.float32),
        quats=rng.normal(size=(n + m, 4)).astype(np.float32),
        opacities=np.concatenate([np.full(n, 0.99), rng.uniform(0.05, 1.0, m)]).astype(np.float32),
        sh_dc=rng.normal(size=(n + m, 3)).astype(np.float32),
    )


def test_face_candidates_keep_every_gaussian_project_keeps():
    from panoworld.render.erp import erp_faces, face_cull
    from panoworld.render.splats import _prepare, covariance_3d, invert_pose, project

    g = shell_and_clutter(1)
    pose = np.eye(4)
    pose[:3, 3] = [0.3, -0.2, 0.1]
    prep = _prepare(g, pose[:3, 3])
    cull = face_cull(prep, g.scales, pose[:3, 3], 0.01)
    assert torch.allclose(prep.cov, covariance_3d(torch.as_tensor(g.scales), torch.as_tensor(g.quats)))
    total = kept = 0
    for fc in erp_faces(pose, 24, 48, pole_scale=2.0):
        full = project(prep, invert_pose(fc.world_from_face), fc.f, fc.f, fc.c, fc.c, fc.n, fc.n)
        cand = cull(fc)[1]
        assert set(full.index.tolist()) <= set(cand.tolist())
        total, kept = total + len(cand), kept + len(full.index)
    assert total < 1.5 * kept < 3 * len(g), (total, kept)  # not every Gaussian on all six faces


def test_view_candidates_keep_every_gaussian_an_off_centre_pinhole_keeps():
    # render_perspective projects only view_candidates' Gaussians: a superset of what project keeps on all of them,
    # here for a pinhole with fx != fy and the principal point off centre, in several directions.
    from panoworld.render.splats import _prepare, cull_terms, invert_pose, project, render_perspective, view_candidates

    g = shell_and_clutter(2)
    pose = np.eye(4)
    pose[:3, 3] = [-0.2, 0.1, 0.25]
    prep = _prepare(g, pose[:3, 3])
    total = kept = 0
    for yaw in np.deg2rad([0.0, 70.0, 160.0, 250.0]):
        c, s = np.cos(yaw), np.sin(yaw)
        pose[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
        view = (30.0, 22.0, 9.0, 25.0, 33, 41)  # fx, fy, cx, cy, H, W
        full = project(prep, invert_pose(pose), *view)
        cand = view_candidates(*cull_terms(g.means, g.opacities, g.scales, pose[:3, 3]), pose[:3, :3].T, *view, 0.01)
        assert set(full.index.tolist()) <= set(cand.tolist())
        total, kept = total + len(cand), kept + len(full.index)
        with torch.no_grad():  # the culled numba path (auto) against the unculled differentiable one
            fast = render_perspective(g, pose, *view)
        means = torch.tensor(g.means, requires_grad=True)
        slow = render_perspective(Gaussians(means=means, scales=g.scales, quats=g.quats, opacities=g.opacities,
                                            sh_dc=g.sh_dc), pose, *view)
        assert float((fast.rgb - slow.rgb.detach()).abs().max()) <= 1e-5
    assert total < 1.5 * kept < 3 * len(g), (total, kept)  # a cull, not every Gaussian


@pytest.mark.parametrize("supersample, tile", [(1, 8), (2, 4), (2, 16)])
def test_masked_operator_is_the_render_on_the_pixels_it_keeps(supersample, tile):
    from panoworld.render.erp_operator import ErpColorOperator

    g = shell_and_clutter()
    pose = np.eye(4)
    pose[:3, 3] = [0.2, -0.1, 0.3]
    H, W = 24, 48
    rng = np.random.default_rng(2)
    mask = np.zeros((H, W), bool)
    mask[3:20, 5:30] = True
    mask[rng.random((H, W)) < 0.1] = True  # and scattered pixels, the poles' rows among them
    colors = torch.rand(len(g), 3)
    ref = render_erp(Gaussians(g.means, g.scales, g.quats, g.opacities, rgb_to_sh_dc(colors.numpy())), pose, H, W,
                     supersample=supersample).rgb  # the CPU tile rasteriser, the oracle
    full = ErpColorOperator(g, pose, H, W, supersample=supersample, tile=tile)
    part = ErpColorOperator(g, pose, H, W, supersample=supersample, tile=tile, mask=mask)
    torch.testing.assert_close(full(colors), ref, atol=2e-5, rtol=0)
    got = part(colors)
    torch.testing.assert_close(got[mask], ref[mask], atol=2e-5, rtol=0)
    assert float(got[~mask].abs().max()) == 0.0
    assert sum(f[2].nnz for f in part.faces) < 0.8 * sum(f[2].nnz for f in full.faces)  # fewer pixels composited
    img = torch.rand(H, W, 3, dtype=torch.float64)  # its adjoint: <A x, y> = <x, A^T y>
    lhs, rhs = float((got.double() * img).sum()), float((colors.double() * part.adjoint(img.float())).sum())
    assert abs(lhs - rhs) < 1e-4 * abs(lhs)
    r = np.ascontiguousarray(np.broadcast_to(img.float().numpy()[:, None, :, None] / supersample**2,
                                             (H, supersample, W, supersample, 3))).reshape(-1, 3)
    sums = sum((A.T @ (S.T @ r[index]) for index, S, A in part.faces), np.zeros((len(g), 3), np.float32))
    np.testing.assert_array_equal(part.adjoint(img.float()).numpy(), sums)  # scipy's products, sum for sum
    samples = np.zeros((H * supersample * W * supersample, 3), np.float32)
    for index, S, A in full.faces:
        samples[index] = S @ (A @ colors.numpy())
    np.testing.assert_array_equal(full(colors).numpy(), samples.reshape(H, supersample, W, supersample, 3).mean((1, 3)))
    for op in (full, part):  # the face pixels no sample reads dropped: the same products, bit for bit
        read = op.read_rows()
        np.testing.assert_array_equal(read(colors).numpy(), op(colors).numpy())
        np.testing.assert_array_equal(read.adjoint(img.float()).numpy(), op.adjoint(img.float()).numpy())
        assert sum(f[2].shape[0] for f in read.faces) < sum(f[2].shape[0] for f in op.faces)
    empty = ErpColorOperator(g, pose, H, W, mask=np.zeros((H, W), bool))
    assert float(empty(colors).abs().max()) == 0.0 and empty.adjoint(img.float()).shape == (len(g), 3)


def test_pruned_weights_are_each_rows_smallest_within_its_share():
    import scipy.sparse

    from panoworld.render.erp_operator import prune_weights

    rng = np.random.default_rng(3)
    m = scipy.sparse.random(300, 200, density=0.2, format="csr", dtype=np.float32, random_state=4)
    m.data[:] = (rng.random(m.nnz) ** 6).astype(np.float32)  # many tiny weights, as a pixel's tail of Gaussians
    m.data[: m.indptr[2]] = 0.25  # two rows of ties
    for share in (0.0, 0.01, 0.1):
        p = prune_weights(m, share)
        full, kept = m.toarray(), p.toarray()
        dropped = full - kept
        assert ((kept == 0) | (kept == full)).all()  # entries are kept whole or dropped
        np.testing.assert_array_less(dropped.sum(1), share * full.sum(1) + 1e-7)
        for i in range(m.shape[0]):  # nothing dropped outweighs what the row keeps
            assert dropped[i].max(initial=0) <= kept[i][kept[i] > 0].min(initial=np.inf)
        if share == 0:
            assert p.nnz == m.nnz
    assert prune_weights(m, 0.1).nnz < 0.8 * m.nnz
    ties = prune_weights(scipy.sparse.csr_matrix(np.array([[0.25, 0.25, 0, 0.25, 0.25], [0, 0, 0, 0, 0]],
                                                            np.float32)), 0.6)
    np.testing.assert_array_equal(ties.toarray(), [[0, 0, 0, 0.25, 0.25], [0, 0, 0, 0, 0]])  # the earlier ties go


def test_a_pruned_operators_render_is_off_by_at_most_its_share():
    from panoworld.render.erp_operator import ErpColorOperator

    g = shell_and_clutter()
    pose = np.eye(4)
    pose[:3, 3] = [0.2, -0.1, 0.3]
    H, W = 24, 48
    colors = torch.rand(len(g), 3)
    full = ErpColorOperator(g, pose, H, W, supersample=2, tile=8)
    for share in (0.002, 0.02):
        pruned = ErpColorOperator(g, pose, H, W, supersample=2, tile=8, prune=share)
        assert sum(f[2].nnz for f in pruned.faces) < sum(f[2].nnz for f in full.faces)
        gap = (full(colors) - pruned(colors)).abs().max()
        assert 0 < float(gap) <= share * float(colors.max()) + 1e-6
    with pytest.raises(ValueError, match="prune"):
        ErpColorOperator(g, pose, H, W, prune=1.0)


SHELL_H, SHELL_W = 24, 48
"""The size of view_dependent_shell's views."""


def shifted(x: float, y: float = 0.0) -> np.ndarray:
    """world_from_cam of a camera moved by (x, y, 0) from the origin, unrotated."""
    return pose_from_rt(np.eye(3), [x, y, 0.0])


def plain_wall() -> Gaussians:
    """The shell of shell_and_clutter(3) in one grey, its Gaussians denser than the capture poses' pixels and narrower
    than their spacing (as per-pixel Gaussians of a finer panorama are)."""
    g, n = shell_and_clutter(3), 2500
    pitch = 3.0 * np.sqrt(4 * np.pi / n)
    return Gaussians(g.means[:n], np.full((n, 3), 0.6 * pitch, np.float32), g.quats[:n], np.full(n, 0.98, np.float32),
                     rgb_to_sh_dc(np.full((n, 3), 0.5, np.float32)))


def view_dependent_shell(seed: int):
    """The first 2500 shell Gaussians in mid-grey (what a fit starts from), the truth with degree-1 colours along x
    (their sign follows the Gaussian's side), its x-term, the pose at x (m) along the x axis, and view(x, gs=truth):
    the render of gs from there (SHELL_H x SHELL_W, (H, W, 3) numpy)."""
    g = shell_and_clutter()
    n = 2500
    g = Gaussians(g.means[:n], g.scales[:n], np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32), g.opacities[:n],
                  rgb_to_sh_dc(np.full((n, 3), 0.5, np.float32)))
    rng = np.random.default_rng(seed)
    rest = np.zeros((n, 3, 3), np.float32)
    rest[:, 2] = rng.uniform(1.0, 2.0, (n, 3)) * np.sign(g.means[:, :1])  # the -x basis term
    truth = Gaussians(g.means, g.scales, g.quats, g.opacities,
                      rgb_to_sh_dc(rng.uniform(0.3, 0.7, (n, 3))).astype(np.float32), rest)

    def view(x, gs=truth):
        return render_erp(gs, shifted(x), SHELL_H, SHELL_W, supersample=1).rgb.numpy()

    return g, truth, rest, shifted, view


def test_degree_one_fit_recovers_a_view_dependent_colour_between_its_views():
    # A shell whose true colours depend on the side it is seen from (degree-1 SH along x); three views 0.6 m apart
    # along x. Fitting DC only gives one colour per Gaussian; the degree-1 fit follows the change, so a held-out view
    # between two of them is closer to the truth. Seen from one view only, the degree-1 terms stay near 0.
    from panoworld.gaussians.pixel import fit_colors

    g, truth, rest, pose_at, view = view_dependent_shell(3)
    H, W = SHELL_H, SHELL_W

    src = pose_at(0.0)
    extra = [(view(x), pose_at(x), np.ones((H, W), np.float32)) for x in (-0.6, 0.6)]
    dc, _ = fit_colors(g, view(0.0), src, iters=10, extra=extra, supersample=1)
    sh, _ = fit_colors(g, view(0.0), src, iters=10, extra=extra, supersample=1, sh_degree=1, sh_damping=0.001)
    assert dc.sh_degree == 0 and sh.sh_degree == 1

    def err(gs, x):
        return float(np.abs(view(x, gs) - view(x)).mean())

    assert err(sh, -0.3) < 0.5 * err(dc, -0.3), (err(sh, -0.3), err(dc, -0.3))  # 0.014 against 0.040
    assert err(sh, 0.0) < err(dc, 0.0) and err(sh, -0.6) < 0.5 * err(dc, -0.6)
    # what the fit found is the truth's view dependence: the x-term's sign follows the Gaussians' side
    side = np.abs(g.means[:, 2]) > 2.5  # in front and behind, where moving along x turns the view direction
    assert np.mean(np.sign(sh.sh_rest[side, 2]) == np.sign(rest[side, 2])) > 0.8
    one, _ = fit_colors(g, view(0.0), src, iters=10, supersample=1, sh_degree=1, sh_damping=0.001)
    assert float(np.abs(one.sh_rest).max()) == 0.0  # seen from one place: no direction to fit
    assert err(one, 0.0) == pytest.approx(err(fit_colors(g, view(0.0), src, iters=10, supersample=1)[0], 0.0), abs=1e-6)
    with pytest.raises(ValueError, match="sh_degree"):
        fit_colors(g, view(0.0), src, sh_degree=2)


def test_views_fitting_only_the_degree_one_terms_keep_the_capture_points_fit():
    # views_sh_only: the capture point renders exactly as its fit without the views (its colours are that fit's), while
    # the degree-1 terms the views fit still bring a held-out view between them closer to the truth.
    from panoworld.gaussians.pixel import fit_colors

    g, truth, _, pose_at, view = view_dependent_shell(4)
    H, W = SHELL_H, SHELL_W

    src = pose_at(0.0)
    extra = [(view(x), pose_at(x), np.ones((H, W), np.float32)) for x in (-0.6, 0.6)]
    alone, info_alone = fit_colors(g, view(0.0), src, iters=10, supersample=1)
    only, info = fit_colors(g, view(0.0), src, iters=10, extra=extra, supersample=1, sh_degree=1, views_sh_only=True)
    assert only.sh_degree == 1 and float(np.abs(only.sh_rest[:, :3]).max()) > 0
    np.testing.assert_allclose(view(0.0, only), view(0.0, alone), atol=1e-5)  # the capture point: unchanged
    assert info["rmse_after"] == info_alone["rmse_after"]
    np.testing.assert_allclose(info["render"][0], info_alone["render"][0])

    def err(gs, x):
        return float(np.abs(view(x, gs) - view(x)).mean())

    assert err(only, -0.3) < 0.7 * err(alone, -0.3), (err(only, -0.3), err(alone, -0.3))
    assert err(only, 0.6) < 0.7 * err(alone, 0.6)


def test_the_views_fit_on_the_gaussians_they_see_alone_is_the_fit_on_all():
    # views_seen_only (the default): the s-only CG runs on the Gaussians the views' weighted pixels see; the others'
    # gradient is 0, so the fit is the one on all Gaussians (to float32 rounding: CG's sums run over other lengths),
    # and those keep the capture fit's colours exactly.
    from panoworld.gaussians.pixel import fit_colors
    from panoworld.render.erp_operator import ErpColorOperator

    g, truth, _, pose_at, view = view_dependent_shell(5)
    H, W = SHELL_H, SHELL_W

    src = pose_at(0.0)
    half = np.zeros((H, W), np.float32)
    half[: H // 2] = 0.3  # the views weigh their upper half only: the shell's lower part is seen from the capture point alone
    extra = [(view(x), pose_at(x), half) for x in (-0.6, 0.6)]
    kw = dict(iters=10, extra=extra, supersample=1, sh_degree=1, views_sh_only=True)
    seen, info_seen = fit_colors(g, view(0.0), src, **kw)
    full, info_full = fit_colors(g, view(0.0), src, **kw, views_seen_only=False)
    alone, _ = fit_colors(g, view(0.0), src, iters=10, supersample=1)
    moved = np.abs(full.sh_rest).max((1, 2)) > 0
    assert 0.2 < moved.mean() < 0.8  # the restriction bites: part of the shell is not in the views' fit
    np.testing.assert_allclose(seen.sh_rest, full.sh_rest, rtol=1e-4, atol=1e-5)  # seen: 2e-5 on 1.06
    np.testing.assert_allclose(seen.sh_dc, full.sh_dc, rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(seen.sh_dc[~moved], alone.sh_dc[~moved])
    assert info_seen["rmse_after"] == info_full["rmse_after"]
    # the restricted operator is the full one's columns, renumbered
    op = ErpColorOperator(g, pose_at(0.6), H, W, supersample=1, mask=half > 0)
    cols = np.flatnonzero(op.adjoint(torch.ones(H, W, 3))[:, 0].numpy() > 0)
    c = torch.rand(len(g), 3)
    c[np.setdiff1d(np.arange(len(g)), cols)] = 0
    sub = op.restricted(cols)
    np.testing.assert_array_equal(sub(c[cols]).numpy(), op(c).numpy())
    np.testing.assert_array_equal(sub.adjoint(torch.ones(H, W, 3)).numpy(), op.adjoint(torch.ones(H, W, 3)).numpy()[cols])
    with pytest.raises(ValueError, match="cols"):
        op.restricted(cols[1:])


def test_capture_fit_gives_each_capture_point_its_own_colours():
    # Two capture points see the same shell in different colours (degree-1 SH along x): one colour per Gaussian cannot
    # reproduce both, the degree-1 fit at both does, and a view between them lands nearer the truth too; the
    # Gaussians neither sees keep their colours exactly.
    from panoworld.gaussians.capture_fit import fit_capture_colors

    g, truth, _, pose_at, view = view_dependent_shell(6)
    H, W = SHELL_H, SHELL_W
    far = Gaussians(*(np.concatenate([a, a[:5]]) for a in (g.means, g.scales, g.quats, g.opacities, g.sh_dc)))
    far.means[len(g):] *= 10.0  # outside the opaque shell: seen from neither capture point
    views = [(view(x), pose_at(x)) for x in (-0.6, 0.6)]
    dc, info_dc = fit_capture_colors(far, views, height=H, supersample=1, iters=15, sh_degree=0)
    sh, info_sh = fit_capture_colors(far, views, height=H, supersample=1, iters=15, sh_degree=1)
    assert dc.sh_degree == 0 and sh.sh_degree == 1
    assert 0.9 * len(g) < info_sh["fitted"] <= len(g) and info_sh["views"] == 2
    for k in range(2):  # 0.32 -> 0.015 (degree 1) against 0.076 (one colour)
        assert info_sh["rmse_after"][k] < 0.1 * info_sh["rmse_before"][k], info_sh
        assert info_sh["rmse_after"][k] < 0.3 * info_dc["rmse_after"][k], (info_sh, info_dc)
    np.testing.assert_array_equal(sh.sh_dc[len(g):], far.sh_dc[len(g):])
    assert float(np.abs(sh.sh_rest[len(g):]).max()) == 0.0
    np.testing.assert_array_equal(sh.means, far.means)

    def err(gs, x):
        return float(np.abs(view(x, gs) - view(x)).mean())

    assert err(sh, 0.0) < 0.5 * err(dc, 0.0)  # between the two: 0.017 against 0.045
    # the fit's error figures are the renderer's (which clamps each colour it sees at 0; the fit's operator does not)
    img = render_erp(sh, pose_at(0.6), H, W, supersample=1).rgb.numpy()
    assert float(np.sqrt(np.mean((img - view(0.6)) ** 2))) == pytest.approx(info_sh["rmse_after"][1], rel=0.03)
    with pytest.raises(ValueError, match="sh_degree"):
        fit_capture_colors(g, views, height=H, sh_degree=2)


def test_capture_fit_seen_from_one_place_fits_the_base_colour_alone():
    # One capture point: no direction tells colours apart, so the degree-1 terms stay 0 and the fit is the one-colour
    # fit, which brings the render there close to its target.
    from panoworld.gaussians.capture_fit import fit_capture_colors

    g, truth, _, pose_at, view = view_dependent_shell(7)
    one = [(view(0.0), pose_at(0.0))]
    sh, info = fit_capture_colors(g, one, height=SHELL_H, supersample=1, iters=15)
    dc, info_dc = fit_capture_colors(g, one, height=SHELL_H, supersample=1, iters=15, sh_degree=0)
    assert info["rmse_after"][0] < 0.2 * info["rmse_before"][0], info
    assert float(np.abs(sh.sh_rest).max()) == 0.0
    np.testing.assert_allclose(sh.sh_dc, dc.sh_dc, atol=1e-3)  # float32 sums over more unknowns


def test_capture_fit_over_its_memory_budget_is_skipped_and_says_why():
    from panoworld.gaussians.capture_fit import fit_capture_colors, operator_nbytes
    from panoworld.render.erp_operator import ErpColorOperator

    g, _, _, pose_at, view = view_dependent_shell(8)
    views = [(view(x), pose_at(x)) for x in (-0.6, 0.0, 0.6)]
    one = operator_nbytes(ErpColorOperator(g, views[0][1], SHELL_H, SHELL_W, supersample=1).read_rows())  # as held
    out, info = fit_capture_colors(g, views, height=SHELL_H, supersample=1, iters=3, max_bytes=2.5 * one)
    assert out is g and "3 capture poses" in info["skipped"] and info["views"] == 3
    fitted, info = fit_capture_colors(g, views, height=SHELL_H, supersample=1, iters=3, max_bytes=4 * one)
    assert "skipped" not in info and fitted is not g


def test_capture_fit_shows_its_progress_on_a_terminal_and_fits_the_same(monkeypatch):
    """A home's capture fit runs minutes at tour size: on a terminal it shows a bar through its operators, its steps
    and its smoothing (nothing where stderr is no terminal, nothing with progress off); the fit is the same bytes."""
    import io
    import sys

    from panoworld.core.progress import PROGRESS_ENV
    from panoworld.gaussians.capture_fit import fit_capture_colors

    monkeypatch.delenv(PROGRESS_ENV, raising=False)  # as a stage not started by a runner on a terminal

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    g, _, _, pose_at, view = view_dependent_shell(8)
    views = [(view(x), pose_at(x)) for x in (-0.6, 0.6)]
    runs = {}
    for progress, stream in ((True, Terminal()), (False, Terminal()), (True, io.StringIO())):
        monkeypatch.setattr(sys, "stderr", stream)
        out, _ = fit_capture_colors(g, views, height=SHELL_H, supersample=1, iters=3, smooth=True, progress=progress)
        runs[progress, type(stream).__name__] = (stream.getvalue(), out)
    shown = runs[True, "Terminal"][0]
    for phase in ("operators", "steps", "smoothing"):
        assert f"capture fit at {SHELL_H} rows: {phase}" in shown
    assert "0/6 " in shown  # 2 operators, 3 steps, the smoothing
    assert runs[False, "Terminal"][0] == "" and runs[True, "StringIO"][0] == ""
    for _, out in runs.values():
        np.testing.assert_array_equal(out.sh_dc, runs[True, "Terminal"][1].sh_dc)
        np.testing.assert_array_equal(out.sh_rest, runs[True, "Terminal"][1].sh_rest)


def test_capture_fit_view_kernels_match_torch_and_are_each_others_adjoint():
    """capture_fit's numba kernels against their torch reference (the colours a view sees of the (n, 12) unknowns:
    colour plus degree-1 terms weighted by the view's basis), and the gradient kernel as that map's exact adjoint."""
    from panoworld.gaussians.capture_fit import _add_view_grad, _view_colors

    rng = np.random.default_rng(3)
    n, m = 50, 20
    x = rng.normal(size=(n, 12)).astype(np.float32)
    cols = rng.choice(n, size=m, replace=False).astype(np.int64)
    basis = rng.normal(size=(m, 3)).astype(np.float32)
    xt, bt = torch.from_numpy(x)[torch.from_numpy(cols)], torch.from_numpy(basis)
    ref = xt[:, :3] + torch.einsum("nj,njc->nc", bt, xt[:, 3:].reshape(-1, 3, 3))
    assert np.array_equal(_view_colors(x, cols, basis), ref.numpy())
    g = rng.normal(size=(m, 3)).astype(np.float32)
    out = np.zeros((n, 12), np.float32)
    _add_view_grad(out, cols, g, basis)
    assert not out[np.setdiff1d(np.arange(n), cols)].any()
    assert np.sum(_view_colors(x, cols, basis).astype(np.float64) * g) == pytest.approx(
        np.sum(x.astype(np.float64) * out), rel=1e-5)


def test_capture_fit_reaches_the_damped_least_squares_optimum():
    # The fit's objective solved exactly (each view's operator assembled as one sparse matrix, the normal equations
    # solved directly): in 20 preconditioned conjugate-gradient steps the fitted colours are that solution to 1e-3,
    # the clutter inside the shell (large, overlapping, partly transparent Gaussians: footprints from a fraction of a
    # pixel to much of the view) included. Without the preconditioner 20 steps leave errors up to 0.5.
    import scipy.sparse
    import scipy.sparse.linalg

    from panoworld.gaussians.capture_fit import fit_capture_colors
    from panoworld.render.erp_operator import ErpColorOperator

    g = shell_and_clutter(9)
    g = Gaussians(g.means, g.scales, g.quats, g.opacities, rgb_to_sh_dc(np.full((len(g), 3), 0.5, np.float32)))
    truth = Gaussians(g.means, g.scales, g.quats, g.opacities,
                      rgb_to_sh_dc(np.random.default_rng(9).uniform(0.2, 0.8, (len(g), 3))).astype(np.float32))
    poses = [shifted(x) for x in (-0.5, 0.5)]
    views = [(render_erp(truth, p, SHELL_H, SHELL_W, supersample=1).rgb.numpy(), p) for p in poses]
    damping = 0.05
    fitted, info = fit_capture_colors(g, views, height=SHELL_H, supersample=1, iters=20, damping=damping,
                                      sh_degree=0)

    normal, rhs = scipy.sparse.csr_matrix((len(g), len(g))), np.zeros((len(g), 3))
    seen = np.zeros(len(g))
    for img, p in views:
        op = ErpColorOperator(g, p, SHELL_H, SHELL_W, supersample=1, tile=8)
        rows = [scipy.sparse.csr_matrix((S @ A).toarray()) for _, S, A in op.faces]
        order = np.concatenate([index for index, _, _ in op.faces])
        m = scipy.sparse.vstack(rows).tocsr()[np.argsort(order)]  # the ERP pixels in row-major order
        normal = normal + (m.T @ m)
        rhs += m.T @ img.reshape(-1, 3)
        seen += np.asarray(m.sum(0)).ravel()
    lam = damping * np.clip(seen, 1e-3, None)
    c0 = g.base_colors().astype(np.float64)
    exact = scipy.sparse.linalg.spsolve((normal + scipy.sparse.diags(lam)).tocsc(), rhs + lam[:, None] * c0)
    exact = np.clip(exact, 0.0, 1.0)
    assert info["fitted"] >= np.count_nonzero(seen) > 2500
    err = np.abs(fitted.base_colors() - exact)  # the Gaussians no view sees stay at c0 in both
    assert float(err.max()) < 1e-3, float(err.max())


def test_capture_fit_smoothed_change_keeps_a_plain_wall_plain_from_elsewhere():
    # A plain wall (the shell in one grey, its Gaussians denser than the capture poses' pixels and narrower than their
    # spacing, as per-pixel Gaussians of a finer panorama are) photographed with a little noise: the least-squares
    # change chases each pixel's noise with Gaussian-to-Gaussian swings that a view from elsewhere shows as a pattern
    # (0.033 rms there against the photos' 0.03); made one the capture poses' renders hold, the wall stays plain from
    # there (0.015) and as bright, while each capture pose's error still falls below 0.15 of where it started.
    from panoworld.gaussians.capture_fit import fit_capture_colors

    wall = plain_wall()
    rng = np.random.default_rng(0)
    views = [(np.clip(0.7 + 0.03 * rng.standard_normal((SHELL_H, SHELL_W, 3)), 0, 1).astype(np.float32), shifted(x))
             for x in (-0.5, 0.5)]
    out = {}
    for smooth in (False, True):
        fitted, info = fit_capture_colors(wall, views, height=SHELL_H, supersample=1, iters=5, smooth=smooth)
        assert max(info["rmse_after"]) < 0.15 * min(info["rmse_before"]), (smooth, info)
        elsewhere = render_erp(fitted, shifted(0.0, 0.6), 4 * SHELL_H, 4 * SHELL_W).rgb.numpy()[16:-16]
        out[smooth] = (float(elsewhere.std()), float(elsewhere.mean()))
    assert out[True][0] < 0.6 * out[False][0], out
    assert out[True][1] == pytest.approx(out[False][1], abs=0.005)


def test_capture_fit_smoothed_change_keeps_the_degree_1_terms_smooth_too():
    # Two capture poses 2 m apart photograph a plain wall at two exposures (0.6 and 0.75, 3 % noise): the degree-1
    # terms let each see its own brightness, and their least-squares change swings from Gaussian to Gaussian as the
    # colours' does (shown as rings on the wall from anywhere between). Made one the capture poses' renders hold, they
    # vary a third as much between neighbouring Gaussians, and each capture pose still sees its own exposure.
    from scipy.spatial import cKDTree

    from panoworld.gaussians.capture_fit import fit_capture_colors

    wall = plain_wall()
    rng = np.random.default_rng(0)
    views = [(np.clip(v + 0.03 * rng.standard_normal((SHELL_H, SHELL_W, 3)), 0, 1).astype(np.float32), shifted(x))
             for v, x in ((0.6, -1.0), (0.75, 1.0))]
    _, nn = cKDTree(wall.means).query(wall.means, k=2)
    rough = {}
    for smooth in (False, True):
        fitted, info = fit_capture_colors(wall, views, height=SHELL_H, supersample=1, iters=5, smooth=smooth)
        assert fitted.sh_rest.shape[1] == 3
        rough[smooth] = float(np.sqrt(((fitted.sh_rest - fitted.sh_rest[nn[:, 1]]) ** 2).mean()))
        assert max(info["rmse_after"]) < 0.3 * min(info["rmse_before"]), (smooth, info)
        for (img, p) in views:
            assert float(render_erp(fitted, p, SHELL_H, SHELL_W).rgb.mean()) == pytest.approx(float(img.mean()), abs=0.02)
    assert rough[True] < 0.4 * rough[False], rough


def test_capture_fit_goes_on_for_the_capture_poses_left_below_its_floor_alone():
    # Two rooms 20 m apart (two plain walls), one capture pose in each: the first photographs a noisy wall, the second
    # a plain one. After the smoothed fit the first still reads below the floor, so further rounds are run for it
    # alone: its error falls and the second room's Gaussians keep the one-round fit's colours to the bit. With no
    # floor (0 dB) the fit is the one-round fit to the bit; an unreachable floor stops at max_rounds.
    from panoworld.gaussians.capture_fit import fit_capture_colors

    a, b = plain_wall(), plain_wall()
    b.means[:, 0] += 20.0
    two = Gaussians(*(np.concatenate([getattr(a, f), getattr(b, f)]) for f in ("means", "scales", "quats",
                                                                               "opacities", "sh_dc")))
    rng = np.random.default_rng(1)
    views = [(np.clip(0.6 + 0.15 * rng.standard_normal((SHELL_H, SHELL_W, 3)), 0, 1).astype(np.float32), shifted(0.0)),
             (np.full((SHELL_H, SHELL_W, 3), 0.7, np.float32), shifted(20.0))]
    kw = dict(height=SHELL_H, supersample=1, iters=3, smooth=True)
    one, info1 = fit_capture_colors(two, views, **kw)
    psnr1 = [-20 * np.log10(r) for r in info1["rmse_after"]]
    assert info1["rounds"] == [] and psnr1[0] < psnr1[1] - 10, psnr1
    same, info0 = fit_capture_colors(two, views, min_psnr=0.0, max_rounds=3, **kw)
    assert info0["rounds"] == []
    np.testing.assert_array_equal(same.sh_dc, one.sh_dc)
    np.testing.assert_array_equal(same.sh_rest, one.sh_rest)
    floor = 0.5 * (psnr1[0] + psnr1[1])
    more, info = fit_capture_colors(two, views, min_psnr=floor, max_rounds=3, **kw)
    assert info["rounds"] and all(r == [0] for r in info["rounds"]) and len(info["rounds"]) <= 2, info["rounds"]
    assert info["rmse_after"][0] < 0.97 * info1["rmse_after"][0], (info["rmse_after"], info1["rmse_after"])
    n = len(a)
    np.testing.assert_array_equal(more.sh_dc[n:], one.sh_dc[n:])
    np.testing.assert_array_equal(more.sh_rest[n:], one.sh_rest[n:])
    _, info_max = fit_capture_colors(two, views, min_psnr=200.0, max_rounds=3, **kw)
    assert info_max["rounds"] == [[0, 1], [0, 1]]
