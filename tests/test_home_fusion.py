"""A home's panoramas fused: depth holes completed from the other panoramas, the panoramas' Gaussians alone."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from panoworld.gaussians.home import depth_from_others
from panoworld.geometry.raycast import Raycaster

ROOM = np.array([4.0, 2.6, 5.0])


def _pose(x, y, z):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def _box_depths(poses, H=48):
    rc = Raycaster(*(lambda m: (m.vertices, m.faces))(trimesh.creation.box(extents=ROOM)))
    return {n: rc.render_erp(T, H, 2 * H).distance.astype(np.float32) for n, T in poses.items()}


def test_depth_holes_are_completed_from_the_surfaces_the_other_panoramas_see():
    poses = {"a": _pose(0, 0, 0), "b": _pose(0.9, 0.2, -1.1)}
    truth = _box_depths(poses)
    depths = {n: d.copy() for n, d in truth.items()}
    depths["a"][10:38, 30:70] = 0.0  # a band of a's walls with no depth (an implausible layout masked)
    got = depth_from_others(0, ["a", "b"], depths, poses, height=48)
    assert got.shape == truth["a"].shape
    hole = depths["a"] == 0
    rel = np.abs(got[hole] - truth["a"][hole]) / truth["a"][hole]
    assert (got[hole] > 0).all() and np.median(rel) < 0.04 and np.quantile(rel, 0.95) < 0.1
    # nothing to complete from: a lone panorama, or others without depth
    assert not depth_from_others(0, ["a"], {"a": depths["a"]}, {"a": poses["a"]}).any()
    assert not depth_from_others(0, ["a", "b"], {"a": depths["a"], "b": np.zeros_like(depths["b"])}, poses).any()


def test_a_home_without_frames_is_its_panoramas_gaussians():
    from panoworld.gaussians.fusion_params import SourcePixelParams
    from panoworld.gaussians.home import home_anchored_fusion

    poses = {"a": _pose(0, 0, 0), "b": _pose(0.9, 0.2, -1.1)}
    depths = _box_depths(poses, H=32)
    rgb = np.full((32, 64, 3), 128, np.uint8)
    sources = {n: (rgb, depths[n], poses[n]) for n in poses}
    params = SourcePixelParams(voxel_size=0.05, unseen_voxel_size=0.05, source_height=0, capture_fit_iters=0)
    res = home_anchored_fusion(None, sources, params)
    assert len(res.gaussians) == res.num_source > 500 and res.num_voxels == 0
    # b's Gaussians stand only where a does not see the same wall from nearer: fewer than one per pixel of each
    assert res.num_source < 2 * 32 * 64


def test_a_home_without_panoramas_is_refused_in_one_line():
    from panoworld.core.errors import InputError
    from panoworld.gaussians.fusion_params import SourcePixelParams
    from panoworld.gaussians.home import home_anchored_fusion

    with pytest.raises(InputError, match="no panorama to build from"):
        home_anchored_fusion(None, {}, SourcePixelParams())


def test_the_panoramas_gaussians_on_several_threads_are_those_of_one_thread(monkeypatch):
    """Each panorama's pixel Gaussians are computed on their own and merged in the panoramas' order: the home's
    Gaussians are the same to the bit on one worker thread and on two."""
    from panoworld.gaussians import home
    from panoworld.gaussians.fusion_params import SourcePixelParams

    poses = {"a": _pose(0, 0, 0), "b": _pose(0.9, 0.2, -1.1), "c": _pose(-1.2, 0.1, 0.8)}
    depths = _box_depths(poses, H=32)
    rng = np.random.default_rng(0)
    sources = {n: (rng.integers(0, 256, (32, 64, 3), dtype=np.uint8), depths[n], poses[n]) for n in poses}
    params = SourcePixelParams(voxel_size=0.05, unseen_voxel_size=0.05, source_height=0, capture_fit_iters=0)
    got = {}
    for workers in (1, 2):
        monkeypatch.setattr(home, "cpu_threads", lambda most, w=workers: w)
        got[workers] = home.home_anchored_fusion(None, sources, params).gaussians
    assert len(got[1]) > 1000
    for field in ("means", "scales", "quats", "opacities", "sh_dc"):
        assert np.array_equal(np.asarray(getattr(got[1], field)), np.asarray(getattr(got[2], field))), field


def test_a_surface_another_panorama_saw_through_is_dropped():
    # b's depth holds a wall across the room 1 m in front of a (a layout's doorway line); a saw the room's far wall
    # through it, so those points of b are seen through, b's true walls are not
    from panoworld.core.conventions import erp_dirs, transform_points
    from panoworld.gaussians.home import seen_through

    poses = {"a": _pose(0, 0, 0), "b": _pose(0.9, 0.2, -1.1)}
    depths = _box_depths(poses)
    H, W = depths["b"].shape
    dirs = erp_dirs(H, W, np.float64)
    to_plane = (1.0 - poses["b"][2, 3]) / np.where(dirs[..., 2] > 1e-6, dirs[..., 2], np.nan)  # the plane z = 1
    fake = np.isfinite(to_plane) & (to_plane < depths["b"]) & (np.abs(dirs[..., 1] * to_plane) < 0.8)
    d = np.where(fake, to_plane, depths["b"])
    pts = transform_points(poses["b"], dirs.reshape(-1, 3) * d.reshape(-1, 1))
    got = seen_through(1, pts, ["a", "b"], {"a": depths["a"], "b": d}, poses, tol=0.1).reshape(H, W)
    assert got[fake].mean() > 0.9 and got[~fake].mean() < 0.01
    assert not seen_through(1, pts, ["a", "b"], {"a": np.zeros_like(depths["a"]), "b": d}, poses, tol=0.1).any()


def test_a_home_fits_its_colours_at_every_capture_point():
    # Two panoramas see the same box in different colours (a surface's texture where each one's depth put it): without
    # the fit each capture pose shows the other's colours where the other sees a wall from nearer; with it each
    # capture pose reproduces its own panorama, and the manifest's figures say so per panorama.
    from panoworld.gaussians.fusion_params import SourcePixelParams
    from panoworld.gaussians.home import home_anchored_fusion
    from panoworld.render.erp import render_erp

    poses = {"a": _pose(0, 0, 0), "b": _pose(0.9, 0.2, -1.1)}
    H = 32
    depths = _box_depths(poses, H=H)
    rows = np.linspace(0, 1, H)[:, None, None]
    rgbs = {"a": np.broadcast_to(np.array([200, 60, 40]) * rows + 20, (H, 2 * H, 3)).astype(np.uint8),
            "b": np.broadcast_to(np.array([40, 90, 210]) * (1 - rows) + 20, (H, 2 * H, 3)).astype(np.uint8)}
    sources = {n: (rgbs[n], depths[n], poses[n]) for n in poses}
    params = dict(voxel_size=0.05, unseen_voxel_size=0.05, source_height=0, capture_fit_height=H)
    plain = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_iters=0))
    fitted = home_anchored_fusion(None, sources, SourcePixelParams(**params))
    rough = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_smooth=False))
    assert plain.color_fit is None and fitted.gaussians.sh_degree == 1
    np.testing.assert_array_equal(fitted.gaussians.means, plain.gaussians.means)

    def rmse(g, n):
        img = render_erp(g, poses[n], H, 2 * H, supersample=1).rgb.numpy()
        return float(np.sqrt(np.mean((img - rgbs[n] / 255.0) ** 2)))

    for n in poses:
        assert rmse(fitted.gaussians, n) < 0.5 * rmse(plain.gaussians, n), n
        assert fitted.color_fit["rmse_after"][n] < 0.5 * fitted.color_fit["rmse_before"][n]
    # a stiffer damping keeps the colours nearer the fused ones, and the capture poses further from their panoramas
    # (the change as the least squares leave it, capture_fit_smooth off, for the damping alone)
    stiff = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_damping=1.0,
                                                                  capture_fit_smooth=False))

    def moved(g):
        return float(np.abs(g.base_colors() - plain.gaussians.base_colors()).mean())

    assert moved(stiff.gaussians) < 0.8 * moved(rough.gaussians)
    for n in poses:
        assert rough.color_fit["rmse_after"][n] < stiff.color_fit["rmse_after"][n] < stiff.color_fit["rmse_before"][n]


def test_the_capture_fit_falls_back_to_a_lower_height_when_its_operators_exceed_the_memory_cap():
    # The operators of a 128-row fit would exceed capture_fit_max_gb, those of a 64-row one do not: the fit runs at
    # 64 rows, as it would have with capture_fit_height 64, and the manifest's figures say which height was refused
    # and why. Under the cap at every height down to CAPTURE_FIT_MIN_HEIGHT the fit is skipped, the colours as fused.
    from panoworld.gaussians.fusion_params import SourcePixelParams
    from panoworld.gaussians.home import CAPTURE_FIT_MIN_HEIGHT, home_anchored_fusion

    poses = {"a": _pose(0, 0, 0), "b": _pose(0.9, 0.2, -1.1)}
    H = 64
    assert H == CAPTURE_FIT_MIN_HEIGHT
    depths = _box_depths(poses, H=H)
    rng = np.random.default_rng(0)
    rgbs = {n: rng.integers(0, 255, (H, 2 * H, 3), dtype=np.uint8) for n in poses}
    sources = {n: (rgbs[n], depths[n], poses[n]) for n in poses}
    params = dict(voxel_size=0.05, unseen_voxel_size=0.05, source_height=0, capture_fit_iters=5)
    low = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_height=H)).color_fit
    high = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_height=2 * H)).color_fit
    assert "reduced_from" not in low and high["height"] == 2 * H and high["operators_gb"] > 2 * low["operators_gb"]
    cap = (low["operators_gb"] + high["operators_gb"]) / 2
    fell = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_height=2 * H,
                                                                 capture_fit_max_gb=cap, capture_fit_prune_fallback=0))
    assert fell.color_fit["height"] == H and fell.color_fit["rmse_after"] == low["rmse_after"]
    (refused,) = fell.color_fit["reduced_from"]
    assert refused["height"] == 2 * H and refused["prune"] == high["prune"] == 0.002 and "more than" in refused["why"]
    none = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_height=2 * H,
                                                                 capture_fit_max_gb=low["operators_gb"] / 4))
    assert "skipped" in none.color_fit and none.gaussians.sh_degree == 0
    assert [(r["height"], r["prune"]) for r in none.color_fit["reduced_from"]] == [(2 * H, 0.002), (2 * H, 0.01),
                                                                                 (H, 0.002)]


def test_the_capture_fit_prunes_harder_before_it_halves_its_height():
    # With a cap between the 128-row operators at capture_fit_prune and at capture_fit_prune_fallback, the fit keeps
    # its 128 rows with the fallback's pruning, as a fit asked for that pruning does, and says what it refused.
    from panoworld.gaussians.fusion_params import SourcePixelParams
    from panoworld.gaussians.home import home_anchored_fusion

    poses = {"a": _pose(0, 0, 0), "b": _pose(0.9, 0.2, -1.1)}
    H = 128
    depths = _box_depths(poses, H=H)
    rng = np.random.default_rng(1)
    rgbs = {n: rng.integers(0, 255, (H, 2 * H, 3), dtype=np.uint8) for n in poses}
    sources = {n: (rgbs[n], depths[n], poses[n]) for n in poses}
    params = dict(voxel_size=0.05, unseen_voxel_size=0.05, source_height=0, capture_fit_iters=5, capture_fit_height=H)
    light = home_anchored_fusion(None, sources, SourcePixelParams(**params)).color_fit
    hard = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_prune=0.05)).color_fit
    assert hard["operators_gb"] < 0.9 * light["operators_gb"] and light["prune"] == 0.002
    cap = (light["operators_gb"] + hard["operators_gb"]) / 2
    fell = home_anchored_fusion(None, sources, SourcePixelParams(**params, capture_fit_max_gb=cap,
                                                                 capture_fit_prune_fallback=0.05)).color_fit
    assert fell["height"] == H and fell["prune"] == 0.05 and fell["rmse_after"] == hard["rmse_after"]
    (refused,) = fell["reduced_from"]
    assert (refused["height"], refused["prune"]) == (H, 0.002) and "more than" in refused["why"]


def test_nearest_source_equals_its_every_pair_reference():
    """geometry.nearest_source (each panorama tests the points still kept, where it is nearer) against the plain
    loop over every point and every other panorama, on a box seen from three capture points (ties included)."""
    from panoworld.core.conventions import erp_dirs, invert_pose, transform_points
    from panoworld.geometry.panoramas import depth_along, nearest_source

    poses = {"a": _pose(0, 0, 0), "b": _pose(0.9, 0.2, -1.1), "c": _pose(-1.0, -0.3, 1.2)}
    depths = _box_depths(poses)
    names = list(poses)
    depths["b"][5:20, 10:40] = 0.0  # no depth there: b explains nothing
    for k, n in enumerate(names):
        d = depths[n].astype(np.float64)
        pts = transform_points(poses[n], erp_dirs(*d.shape, np.float64).reshape(-1, 3) * d.reshape(-1, 1))
        pts = np.concatenate([pts, poses[names[(k + 1) % 3]][:3, 3][None]])  # a point at another capture point
        r_k = np.linalg.norm(pts - poses[n][:3, 3], axis=1)
        ref = np.ones(len(pts), bool)
        for j, other in enumerate(names):
            if j != k:
                p = transform_points(invert_pose(poses[other]), pts)
                r_j = np.linalg.norm(p, axis=1)
                d_j = depth_along(np.asarray(depths[other], np.float64), p)
                seen = np.isfinite(d_j) & (d_j > 0) & (np.abs(np.log(np.maximum(r_j, 1e-6) / np.maximum(d_j, 1e-6))) < 0.03)
                ref &= ~(seen & ((r_j < r_k) | ((r_j == r_k) & (j < k))))
        got = nearest_source(k, pts, names, depths, poses, tol=0.03)
        assert 0.05 < got.mean() < 0.95
        np.testing.assert_array_equal(got, ref)


def test_a_panorama_given_twice_keeps_every_surface_once():
    """Two panoramas at one pose (a user's duplicate, rotated and off the origin): the first keeps every point it
    sees, the second none, whatever the rounding of the two ways to a point's range."""
    from panoworld.core.conventions import erp_dirs, transform_points
    from panoworld.geometry.panoramas import nearest_source

    c, s = np.cos(2.2), np.sin(2.2)
    T = np.array([[c, 0, s, -0.873959777], [0, 1, 0, 0.000138522], [-s, 0, c, -1.334104734], [0, 0, 0, 1.0]])
    poses = {"a": T, "a_copy": T.copy()}
    depths = _box_depths({"a": T})
    depths["a_copy"] = depths["a"].copy()
    d = depths["a"].astype(np.float64)
    pts = transform_points(T, erp_dirs(*d.shape, np.float64).reshape(-1, 3) * d.reshape(-1, 1))
    assert nearest_source(0, pts, ["a", "a_copy"], depths, poses).all()
    assert not nearest_source(1, pts, ["a", "a_copy"], depths, poses).any()


def test_a_panoramas_pixels_without_depth_get_its_own_fill_where_no_other_panorama_sees():
    # a has no depth in a band of its view (an implausible layout masked) across the +x wall and parts of the +z and
    # -z walls; b, farther from the +x wall, saw those two but not the +x wall. Coarse grey Gaussians (the frames'
    # voxel ones) stand in there. a's own pixels fill its band where no other panorama measured a surface (the +x
    # wall): in front of what a sees there, never on or in front of a surface b measured, so b's view of its own
    # surfaces stays as it was while a's view shows its own colours.
    from panoworld.core.conventions import erp_dirs, invert_pose, transform_points
    from panoworld.gaussians.fusion_params import SourcePixelParams
    from panoworld.gaussians.home import add_own_fill, home_anchored_fusion
    from panoworld.gaussians.pixel import merge_gaussians, pixel_gaussians
    from panoworld.geometry.panoramas import depth_along, erp_pixel_index
    from panoworld.io.gaussian_set import FusionResult
    from panoworld.render.erp import render_erp

    poses = {"a": _pose(0, 0, 0), "b": _pose(-0.9, 0.2, -1.1)}
    H = 48
    truth = _box_depths(poses, H=H)
    dirs = erp_dirs(H, 2 * H, np.float64)

    def texture(n):  # smooth world-space colours: both panoramas see the same colours on a surface
        p = transform_points(poses[n], dirs.reshape(-1, 3) * truth[n].reshape(-1, 1))
        c = 0.5 + 0.4 * np.sin(p @ np.array([[1.5, 0.0, 0.6], [0.4, 1.8, 0.0], [0.0, 0.7, 1.6]]))
        return (255 * c).reshape(H, 2 * H, 3).astype(np.uint8)

    rgbs = {n: texture(n) for n in poses}
    depths = {n: d.copy() for n, d in truth.items()}
    hole = np.zeros((H, 2 * H), bool)
    hole[10:38, int(0.55 * 2 * H):int(0.95 * 2 * H)] = True
    depths["a"][hole] = 0.0
    pts_b = transform_points(poses["b"], dirs.reshape(-1, 3) * truth["b"].reshape(-1, 1)).reshape(H, 2 * H, 3)
    depths["b"][pts_b[..., 0] > ROOM[0] / 2 - 0.05] = 0.0  # b has no depth on the +x wall
    params = SourcePixelParams(voxel_size=0.05, unseen_voxel_size=0.05, source_height=0, capture_fit_iters=0,
                               source_fill_height=H)
    pix = home_anchored_fusion(None, {n: (rgbs[n], depths[n], poses[n]) for n in poses},
                               SourcePixelParams(**{**vars(params), "source_fill": False})).gaussians
    h = H // 2  # the stand-ins: a's true surfaces in its band, coarser and grey
    coarse = np.where(hole[::2, ::2], truth["a"][::2, ::2], 0.0).astype(np.float32)
    stand_in = pixel_gaussians(np.full((h, 2 * h, 3), 128, np.uint8), coarse, poses["a"], params)
    scene = FusionResult(merge_gaussians([pix, stand_in]), 0, 0, 0, [0.0] * 3, 0.05, num_source=len(pix))
    filled, stats = add_own_fill(scene, list(poses), rgbs, depths, poses, params)

    assert set(stats) == {"a", "b"}
    n_left = len(filled) - len(pix) - stats["a"]["filled"] - stats["b"]["filled"]
    assert len(stand_in) - n_left == stats["a"]["stood_for"] + stats["b"]["stood_for"]
    idx = np.arange(len(filled))
    np.testing.assert_array_equal(np.asarray(filled.means)[:len(pix)], np.asarray(pix.means))
    fill_a = np.asarray(filled.subset(idx >= len(pix) + n_left).means, np.float64)[:stats["a"]["filled"]]
    assert len(fill_a) > 100
    # along a's rays without depth, never beyond the surface a sees there, never on or in front of one b measured
    rows, cols = erp_pixel_index(fill_a, H, 2 * H)
    assert hole[rows, cols].all() and (np.linalg.norm(fill_a, axis=1) < truth["a"][rows, cols] * 1.05).all()
    from_b = transform_points(invert_pose(poses["b"]), fill_a)
    d_b = depth_along(depths["b"].astype(np.float64), from_b)
    assert not ((d_b > 0) & (np.linalg.norm(from_b, axis=1) < d_b * 1.03)).any()

    def error(g, n, where):
        img = render_erp(g, poses[n], H, 2 * H, supersample=1).rgb.numpy()
        return np.abs(img - rgbs[n] / 255.0).mean(-1)[where]

    on_x = hole & (transform_points(poses["a"], dirs.reshape(-1, 3) * truth["a"].reshape(-1, 1))[:, 0]
                   .reshape(H, 2 * H) > ROOM[0] / 2 - 0.05)
    before, after = error(scene.gaussians, "a", on_x), error(filled, "a", on_x)
    assert np.median(after) < 0.3 * np.median(before)
    seen_b = depths["b"] > 0  # b's view of the surfaces it measured: no worse
    assert error(filled, "b", seen_b).mean() < error(scene.gaussians, "b", seen_b).mean() + 0.002
    # nothing without depth: nothing added
    whole, stats = add_own_fill(scene, list(poses), rgbs, truth, poses, params)
    assert whole is scene.gaussians and stats == {}


def test_a_panoramas_own_fill_is_as_fine_as_its_measured_pixels_by_default():
    # The fill stands beside the panorama's measured per-pixel Gaussians: at fewer rows it is visibly coarser there
    # (on real homes the capture poses of the panoramas whose layout is masked read 0.3-2.2 dB lower at half the rows).
    from panoworld.gaussians.backends.voxel_fusion import VoxelFusionOptions
    from panoworld.gaussians.fusion_params import SourcePixelParams

    for params in (SourcePixelParams(), VoxelFusionOptions()):
        assert params.source_fill_height == params.source_height > 0


def test_nothing_the_frames_see_within_the_rig_radius_of_a_capture_point_is_fused():
    # a has no depth in a band of its view across the +x wall (an implausible layout masked), b none on that wall.
    # A frame 0.5 m towards that wall holds a stray surface a few cm in front of a's camera, in that band (a warped
    # condition's smear where the rig stood). A capture point stood there: nothing is fused there, a's own fill
    # stands beyond the rig's radius, not at the stray surface, and a's view of its band shows a's own colours.
    from panoworld.core.conventions import erp_dirs, invert_pose, transform_points
    from panoworld.gaussians.fusion_params import SourcePixelParams
    from panoworld.gaussians.home import home_anchored_fusion
    from panoworld.gaussians.pixel import SourceVisibility
    from panoworld.render.erp import render_erp
    from panoworld.room.plausible import NEAR_PLANE_M

    poses = {"a": _pose(0, 0, 0), "b": _pose(-0.9, 0.2, -1.1)}
    H = 48
    truth = _box_depths(poses, H=H)
    rows, cols = np.mgrid[0:H, 0:2 * H] / H
    smooth = np.stack([np.sin(3 * cols), np.cos(2 * rows + cols), np.sin(2 * rows)], -1)
    rgbs = {n: (128 + 70 * smooth).astype(np.uint8) for n in poses}
    depths = {n: d.copy() for n, d in truth.items()}
    hole = np.zeros((H, 2 * H), bool)
    hole[10:38, int(0.55 * 2 * H):int(0.95 * 2 * H)] = True  # across the +x wall
    depths["a"][hole] = 0.0
    dirs = erp_dirs(H, 2 * H, np.float64)
    pts_b = transform_points(poses["b"], dirs.reshape(-1, 3) * truth["b"].reshape(-1, 1)).reshape(H, 2 * H, 3)
    depths["b"][pts_b[..., 0] > ROOM[0] / 2 - 0.05] = 0.0  # b has no depth on the +x wall
    frame_pose = _pose(0.5, 0.0, 0.0)
    fd = _box_depths({"f": frame_pose}, H=H)["f"]
    # the frame's rays that pass within 8 cm of a's camera stop 4-9 cm in front of it
    to_a = transform_points(invert_pose(frame_pose), np.zeros((1, 3)))[0]
    along = dirs @ to_a
    miss = np.linalg.norm(dirs * along[..., None] - to_a, axis=-1)
    stray = (along > 0) & (miss < 0.08)
    fd = np.where(stray, along - 0.04, fd).astype(np.float32)
    assert stray.sum() >= 4
    frames = [(np.full((H, 2 * H, 3), 250, np.uint8), fd, frame_pose)]
    params = SourcePixelParams(voxel_size=0.02, unseen_voxel_size=0.02, source_height=0, capture_fit_iters=0,
                               source_fill_height=H)
    res = home_anchored_fusion(frames, {n: (rgbs[n], depths[n], poses[n]) for n in poses}, params)
    means = np.asarray(res.gaussians.means, np.float64)
    assert np.linalg.norm(means, axis=1).min() > NEAR_PLANE_M
    assert res.own_fill["a"]["filled"] > 100
    img = render_erp(res.gaussians, poses["a"], H, 2 * H, supersample=1).rgb.numpy()
    err = np.abs(img - rgbs["a"] / 255.0).mean(-1)
    assert np.median(err[hole]) < 0.05
    # the rule itself: within `near` of the camera is explained whatever the depth (none here), beyond it is not
    vis = SourceVisibility(np.zeros((H, 2 * H), np.float32), poses["a"], 0.03, near=NEAR_PLANE_M)
    got = vis.explained(np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 0.2]]))
    assert got.tolist() == [True, False]
    assert not SourceVisibility(np.zeros((H, 2 * H), np.float32), poses["a"], 0.03).explained(np.zeros((1, 3))).any()
