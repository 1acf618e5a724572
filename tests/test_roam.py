"""The roam protocol and anti-aliased references of `runner.py eval` (panoworld/tools/eval/roam.py, groundtruth.py)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from panoworld.core.conventions import points_from_depth
from panoworld.framework import pipeline as pl
from panoworld.geometry.navmesh import load_navmesh
from panoworld.render.metrics import psnr
from panoworld.tools.eval.cli import EvalParams, GroundTruth, evaluate, is_unavailable
from panoworld.tools.eval.roam import (
    BUCKETS,
    FAR_KEY,
    sample_roam_poses,
    sector_reachable,
    source_seen,
    trajectory_reach,
)
from panoworld.tools.eval.tables import build_tables

KEYS = [b.key for b in BUCKETS] + [FAR_KEY]
PARAMS = EvalParams(roam_views=1, roam_height=32, roam_pinhole=24)
GS_ROWS = 48  # the test Gaussians: one per pixel of the ground-truth ERP at this height


@pytest.fixture(scope="module")
def scene(synth_scene, tmp_path_factory):
    """The ci-tiny scene through depth, mesh and navmesh, with Gaussians made from the exact ground truth at the
    capture point (one splat of half a pixel's size per pixel of a GS_ROWS-row ERP), so the capture-point view is
    known to be close."""
    from panoworld.io.gaussian_set import Gaussians, rgb_to_sh_dc
    from panoworld.io.splat_ply import write_gaussians_ply

    root = tmp_path_factory.mktemp("roam") / "scene"
    shutil.copytree(synth_scene, root, ignore=shutil.ignore_patterns("artifacts"))
    (root / pl.SCENE_CONFIG).write_text("preset: ci-tiny\n")
    assert pl.run(root, preset="ci-tiny", until="navmesh").ok
    rgb, depth = GroundTruth(root / "gt").render(np.eye(4), GS_ROWS, 2 * GS_ROWS)
    ok = np.isfinite(depth).reshape(-1)
    pts = points_from_depth(np.where(np.isfinite(depth), depth, 1.0)).reshape(-1, 3)[ok]
    radius = (np.where(np.isfinite(depth), depth, 0.0).reshape(-1)[ok] * 0.5 * math.pi / GS_ROWS).astype(np.float32)
    n = len(pts)
    g = Gaussians(means=pts.astype(np.float32), scales=np.repeat(radius[:, None], 3, 1),
                  quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), opacities=np.full(n, 0.95, np.float32),
                  sh_dc=rgb_to_sh_dc(rgb.reshape(-1, 3)[ok] / 255.0).astype(np.float32))
    d = root / "artifacts" / "gaussians"
    d.mkdir()
    write_gaussians_ply(d / "gaussians.ply", g)
    (d / "manifest.json").write_text(json.dumps({"info": {}}))
    return root


def test_roam_poses_are_seeded_upright_on_the_navmesh_and_in_their_buckets(scene):
    nav = load_navmesh(scene / "artifacts" / "navmesh")
    a, b = sample_roam_poses(nav, 3, seed=5), sample_roam_poses(nav, 3, seed=5)
    assert a.poses.keys() == b.poses.keys() and all(np.array_equal(a.poses[k], b.poses[k]) for k in a.poses)
    assert np.allclose(a.poses["d0"][0], np.eye(4))
    assert set(a.poses) | set(a.missing) == set(KEYS)
    for key, poses in a.poses.items():
        lo, hi = a.ranges[key]
        xz = poses[:, :3, 3][:, [0, 2]]
        assert np.allclose(poses[:, 1, 3], 0.0) and np.allclose(poses[:, :3, 1], [0, 1, 0])  # camera height, upright
        assert np.allclose(np.linalg.det(poses[:, :3, :3]), 1.0)
        d = np.linalg.norm(xz, axis=1)
        assert np.all((d >= lo - 1e-9) & (d <= hi + 1e-9)), (key, d, lo, hi)
        if key != "d0":
            assert nav.contains(xz).all()
    assert a.farthest_m >= max(np.linalg.norm(p[:, :3, 3], axis=1).max() for p in a.poses.values())
    c = sample_roam_poses(nav, 3, seed=6)
    assert not np.array_equal(c.poses["d0.5"], a.poses["d0.5"]) if "d0.5" in a.poses else True


def test_roam_metrics_per_bucket_on_a_ci_tiny_scene(scene):
    report, errors = evaluate(scene, PARAMS, stages=["roam"])
    assert errors == []
    roam = report["stages"]["roam"]
    assert "4x" in roam["reference"] and roam["erp_size"] == "32x64" and roam["pinhole"].startswith("24x24")
    for key in KEYS:
        if roam[f"{key}_count"] == 0:  # a bucket the floor does not reach says why, never a number
            assert is_unavailable(roam[f"{key}_erp_psnr"]) and "does not reach" in roam[f"{key}_erp_psnr"]["reason"]
            continue
        assert roam[f"{key}_count"] == 1
        for kind in ("erp", "pinhole"):
            assert 0.0 <= roam[f"{key}_{kind}_coverage"] <= 1.0
            assert 5.0 < roam[f"{key}_{kind}_psnr"] < 80.0 and -1.0 <= roam[f"{key}_{kind}_ssim"] <= 1.0
    assert roam["d0_count"] == 1 and roam["d0_erp_coverage"] > 0.98
    # Gaussians made from the ground truth at the capture point reproduce it there
    assert roam["d0_erp_psnr"] > 24.0 and roam["d0_erp_psnr"] > roam["far_erp_psnr"]
    assert math.isfinite(roam["d0_erp_psnr_vs_input"])
    assert is_unavailable(roam["lpips"]) and "targets" in report and "d0_erp_psnr" in report["targets"]["roam"]
    report["unit"] = "scene"
    table = next(t for t in build_tables([report]) if t.title.startswith("Roam"))
    assert table.rows[0][1][0].mean == pytest.approx(roam["d0_erp_psnr"])


def test_source_visibility_split_matches_the_source_depth_map(scene):
    from panoworld.core.conventions import erp_pixel_from_dir

    gt = GroundTruth(scene / "gt", supersample=1)
    assert source_seen(gt, np.eye(4), 32, 64).all()  # the capture point sees all it sees
    nav = load_navmesh(scene / "artifacts" / "navmesh")
    poses = sample_roam_poses(nav, 3, seed=1).poses
    pose = poses.get("far", poses.get("d1"))[0]
    H = 48
    seen = source_seen(gt, pose, H, 2 * H)
    # oracle: the view's surface points against the source's own depth map at 4x the resolution (nearest pixel)
    depth = gt.depth(pose, H, 2 * H).astype(np.float64)
    pts = points_from_depth(np.where(np.isfinite(depth), depth, 1.0)) @ pose[:3, :3].T + pose[:3, 3]
    dist = np.linalg.norm(pts, axis=-1)
    u, v = erp_pixel_from_dir(pts / dist[..., None], 4 * H, 8 * H)
    src = gt.depth(np.eye(4), 4 * H, 8 * H)[np.clip(v.astype(int), 0, 4 * H - 1), u.astype(int) % (8 * H)]
    behind = np.isfinite(depth) & (dist > src * 1.05 + 0.05)
    clear = ~np.isfinite(depth) | (dist < src * 0.99)
    assert behind.sum() > 20, "the pose should see something the capture point does not"
    assert (~seen[behind]).mean() > 0.97 and seen[clear].mean() > 0.97
    # source-only Gaussians (the fixture's): the unseen part holds more than its share of the error
    roam = evaluate(scene, EvalParams(roam_views=3, roam_height=H, roam_pinhole=0), stages=["roam"])[0]["stages"]["roam"]
    assert roam["d0_erp_unseen_fraction"] == 0.0 and roam["d0_erp_unseen_error_share"] == 0.0
    far = [k for k in KEYS if roam.get(f"{k}_erp_unseen_fraction", 0) > 0.01]
    assert far and all(0.0 <= roam[f"{k}_erp_unseen_error_share"] <= 1.0 for k in far)
    assert all(roam[f"{k}_erp_unseen_error_share"] > roam[f"{k}_erp_unseen_fraction"] for k in far), roam
    assert all(roam[f"{k}_erp_psnr_seen"] > roam[f"{k}_erp_psnr_unseen"] for k in far)


def test_scene_without_ground_truth_gets_coverage_only(scene, tmp_path):
    real = tmp_path / "real"
    shutil.copytree(scene, real, ignore=shutil.ignore_patterns("gt"))
    roam = evaluate(real, PARAMS, stages=["roam"])[0]["stages"]["roam"]
    assert "coverage only" in roam["reference"]
    assert is_unavailable(roam["d0_erp_psnr"]) and "pinhole_psnr" not in json.dumps(roam)
    assert 0.98 < roam["d0_erp_coverage"] <= 1.0 and roam["d0_erp_psnr_vs_input"] > 20.0
    for key in KEYS:
        assert roam[f"{key}_count"] == 0 or 0.0 <= roam[f"{key}_erp_coverage"] <= 1.0


def test_anti_aliased_reference_is_closer_to_a_dense_supersample(synth_scene):
    pose = np.eye(4)
    aliased = GroundTruth(synth_scene / "gt", supersample=1).render(pose, 32, 64)[0]
    aa = GroundTruth(synth_scene / "gt", supersample=4).render(pose, 32, 64)[0]
    dense = GroundTruth(synth_scene / "gt", supersample=12, max_rows=10_000).render(pose, 32, 64)[0]
    assert not np.array_equal(aa, aliased)
    assert psnr(aa, dense) > psnr(aliased, dense) + 3.0
    # the factor is capped so that the supersampled image stays within max_rows
    gt = GroundTruth(synth_scene / "gt", supersample=4, max_rows=1536)
    assert gt.factor(256) == 4 and gt.factor(720) == 2 and gt.factor(2000) == 1


def test_pinhole_reference_agrees_with_the_erp_reference(synth_scene):
    gt = GroundTruth(synth_scene / "gt", supersample=1)
    size = 33  # odd: the centre pixel looks exactly along +z
    _, d_pin = gt.scene.render_pinhole(gt.world_from_canonical, 16.0, 16.0, 16.5, 16.5, size, size)
    forward = (gt.world_from_canonical[:3, :3] @ [0.0, 0.0, 1.0])[None]
    hits = gt.scene.raycaster.cast(gt.world_from_canonical[:3, 3][None], forward)
    assert d_pin[16, 16] == pytest.approx(float(hits.distance[0]), rel=1e-5)


def test_sector_reach_matches_the_navmesh_boundary(scene):
    nav = load_navmesh(scene / "artifacts" / "navmesh")
    reach = sector_reachable(nav, 8)
    # oracle: march 1 mm steps with the point-in-NavMesh test until the walk leaves the floor
    ts = np.arange(0.0, float(np.abs(nav.vertices).max()) * 1.5, 0.001)
    for k, lon in enumerate(2 * np.pi * np.arange(8) / 8):
        inside = nav.contains(ts[:, None] * np.array([np.sin(lon), np.cos(lon)]))
        start = np.flatnonzero(inside[ts <= 0.5])
        if not len(start):
            assert reach[k] == 0.0
            continue
        left = np.flatnonzero(~inside[start[0]:])
        assert reach[k] == pytest.approx(ts[start[0] + left[0]] if len(left) else ts[-1], abs=0.011)
    assert reach.max() > 0.5
    # a straight walk out along sector 0 to 60 % of its reach reaches 60 %
    line = np.linspace(0, 0.6 * reach[0], 7)
    poses = np.tile(np.eye(4), (7, 1, 1))
    poses[:, 2, 3] = line
    r = trajectory_reach(nav, poses)
    assert r["reach_max_m"] == pytest.approx(0.6 * reach[0]) and r["sector_reached_m"][0] == pytest.approx(0.6 * reach[0], abs=1e-3)
    assert r["sector_reach_fraction_min"] == 0.0 or sum(x > 0 for x in r["sector_reachable_m"]) == 1


def test_buckets_beyond_the_floor_say_so():
    from panoworld.geometry.navmesh import NavMesh

    square = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    nav = NavMesh(square, np.array([[0, 1, 2], [0, 2, 3]]), np.array([[-1, 1, -1], [-1, -1, 0]]), [square], 1.5)
    roam = sample_roam_poses(nav, 2, seed=0)
    assert roam.farthest_m == pytest.approx(math.sqrt(0.5))
    assert set(roam.missing) == {"d1", "d2"} and "farthest point is 0.71 m" in roam.missing["d2"]
    assert len(roam.poses["d0.5"]) == 2 and roam.ranges["far"][0] == pytest.approx(0.85 * math.sqrt(0.5))
