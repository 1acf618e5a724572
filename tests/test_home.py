"""A home from several panoramas through `runner.py run` (issue #27): every stage, capture points on the NavMesh,
the trajectory visiting them, and the Gaussian scene reproducing each panorama at its capture pose."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from panoworld import artifacts as art
from panoworld import pipeline as pl
from panoworld.conventions import invert_pose
from panoworld.depth import read_panorama
from panoworld.home.layout import capture_poses
from panoworld.home.quality import capture_psnr

torch.set_num_threads(1)

SMALL = ["mesh.home_stride=4", "trajectory.sectors=4", "gaussians.source_height=128", "register.height=384"]
"""ci-tiny plus: coarser fused mesh, fewer explore paths per capture point, small per-pixel sources (test speed)."""


@pytest.fixture(scope="module")
def home_run(home_dir, tmp_path_factory):
    scene = tmp_path_factory.mktemp("run") / "scene"
    shutil.copytree(home_dir, scene, ignore=shutil.ignore_patterns("artifacts"))
    report = pl.run(scene, preset="ci-tiny", sets=SMALL)
    return scene, report


@pytest.mark.slow
def test_home_runs_every_stage_and_caches(home_run):
    scene, report = home_run
    assert [r.action for r in report.results] == ["ran"] * len(pl.Pipeline.load().order), report.table()
    again = pl.run(scene, preset="ci-tiny", sets=SMALL)
    assert {r.action for r in again.results} == {"cached"}, again.table()
    depth = art.read_manifest(scene / "artifacts" / "depth")["info"]
    assert depth["home"]["names"] == ["pano_00", "pano_01", "pano_02"]


@pytest.mark.slow
def test_home_capture_points_registered_on_navmesh_and_visited(home_run):
    scene, _ = home_run
    arts = scene / "artifacts"
    est = capture_poses(arts / "register")
    gt = {n: np.asarray(T) for n, T in json.loads((scene / "gt" / "poses.json").read_text()).items()}
    for n, E in est.items():
        G = invert_pose(gt["pano_00"]) @ gt[n]
        assert np.linalg.norm(G[:3, 3] - E[:3, 3]) < 0.05, n
    nav = art.read_manifest(arts / "navmesh")["info"]
    assert nav["capture_points_on_navmesh"] == dict.fromkeys(est, True)
    traj = art.read_manifest(arts / "trajectory")["info"]
    assert traj["kind"] == "home" and traj["invalid_poses"] == [] and traj["plan"]["unreached_captures"] == []
    poses = np.asarray(json.loads((arts / "trajectory" / "trajectory.json").read_text())["poses"])
    for n, k in traj["plan"]["capture_frames"].items():  # a frame stands at every capture point ...
        assert np.allclose(poses[k][:3, 3], est[n][:3, 3], atol=1e-6), n
    walks = [p for p in traj["plan"]["paths"] if "walk" in p]  # ... and walks join them
    assert len(walks) == 2 and all(p["stop"] > p["start"] for p in walks)
    assert len(poses) == traj["frames"] == len(json.loads((arts / "poses" / "poses.json").read_text())["poses"])


@pytest.mark.slow
def test_home_gaussians_reproduce_every_panorama_at_its_capture_pose(home_run):
    scene, _ = home_run
    arts = scene / "artifacts"
    info = art.read_manifest(arts / "gaussians")["info"]
    captures = capture_poses(arts / "register")
    panos = {n: read_panorama(scene / "panoramas" / f"{n}.png") for n in captures}
    scores = capture_psnr(arts / "gaussians" / "gaussians.ply", captures, panos, height=64)
    assert min(scores.values()) > 27.0, scores
    # Every source is anchored, but no surface twice: fewer per-pixel Gaussians than the sources' pixels.
    assert 0.4 * 3 * 128 * 256 < info["num_source_gaussians"] < 0.9 * 3 * 128 * 256
