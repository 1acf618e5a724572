"""Real-capture failure classes rebuilt on synthetic scenes run at default settings: no crash, no invalid geometry,
the rig's blind spot walkable, clearance kept, sector coverage reported."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from panoworld.core.conventions import invert_pose, transform_points
from panoworld.framework import pipeline as pl
from panoworld.framework.scene import input_paths
from panoworld.framework.stage import StageInputError, execute_stage, load_stage
from panoworld.geometry.erp_mesh import load_erp_mesh
from panoworld.tools.synth.failure_cases import FailureCase, failure_scene, write_failure_scene
from panoworld.trajectory import mesh_clearance

STAGES = ("depth", "mesh", "navmesh", "trajectory")


def run_default(scene_dir, sets=()):
    """Run depth..trajectory in-process with the pipeline's default params (plus --set style overrides)."""
    pipe = pl.Pipeline.load()
    scene = pl.open_scene(scene_dir, pipe)
    params = pl.resolve_params(pipe, None, scene, pl.parse_sets(list(sets), pipe), list(STAGES))
    manifests = {}
    for name in STAGES:
        node = pipe.stages[name]
        manifests[name] = execute_stage(load_stage(name), input_paths(node, scene), params[name], scene.artifact_dir(name))
    return manifests, scene


def check_no_invalid_geometry(mesh_dir):
    """mesh.ply holds only referenced vertices, none near the camera centre; flagged faces join real depths."""
    from plyfile import PlyData

    ply = PlyData.read(str(mesh_dir / "mesh.ply"))
    v = np.stack([ply["vertex"].data[k] for k in "xyz"], 1)
    faces = np.stack(ply["face"].data["vertex_indices"])
    assert np.array_equal(np.unique(faces), np.arange(len(v))), "unreferenced vertices written"
    assert np.linalg.norm(v, axis=1).min() >= 0.1, "a vertex at the camera centre"
    mesh = load_erp_mesh(mesh_dir)  # the ERP layout restored: every face vertex is a real (non-zero) point
    assert np.linalg.norm(mesh.vertices[mesh.faces], axis=2).min() >= 0.1


def gt_clearance(scene_dir, poses):
    scene = failure_scene(json.loads((scene_dir / "gt_scene.json").read_text())["seed"])
    v = transform_points(invert_pose(scene.world_from_canonical), scene.vertices.astype(np.float64))
    return mesh_clearance(v, scene.faces, poses[:, :3, 3], 1.0)


@pytest.mark.parametrize("case", [FailureCase.LAYOUT_ONLY, FailureCase.ZERO_BANDS, FailureCase.RIG_BLIND_SPOT,
                                  FailureCase.OBJECT_UNDER_CAMERA, FailureCase.SPARSE_LIDAR])
def test_failure_class_runs_at_default_settings(tmp_path, case):
    scene_dir = write_failure_scene(case, tmp_path / "scene", height=128)
    m, scene = run_default(scene_dir)
    check_no_invalid_geometry(scene.artifact_dir("mesh"))
    traj = m["trajectory"]["info"]
    nav = m["navmesh"]["info"]
    poses = np.asarray(json.loads((scene.artifact_dir("trajectory") / "trajectory.json").read_text())["poses"])
    assert len(poses) == 81 and traj["invalid_poses"] == []
    radius = traj["agent_radius_m"]
    exempt = set(traj["exempt_poses"])
    if case != FailureCase.LAYOUT_ONLY:  # (the empty room is a different generated scene: its clearance is below)
        clear = gt_clearance(scene_dir, poses)
        assert all(clear[i] >= radius for i in range(len(poses)) if i not in exempt), "clearance against the true scene"
    assert 0 < traj["sectors_reachable"] <= 8
    # Reachable counts each sector alone within the budget; off the NavMesh the approach eats much of it.
    want = min(6, traj["sectors_reachable"]) if exempt == {0} else min(3, traj["sectors_reachable"])
    assert traj["sectors_covered"] >= want
    depth_info = m["depth"]["info"]
    if case == FailureCase.RIG_BLIND_SPOT:
        # The floor under the rig is unseen: the depth stage completes it from the floor plane (complete_poles), so
        # the camera starts on the NavMesh (with complete_poles=false the NavMesh's blind-spot rule assumes it).
        assert depth_info["pole_completion"]["floor_fraction"] > 0.1 and nav["camera_on_navmesh"]
        assert exempt == {0}
    elif case == FailureCase.OBJECT_UNDER_CAMERA:
        # A seen obstacle is never assumed away: start off the NavMesh, the way there is exempt and reported.
        assert not nav["camera_on_navmesh"] and traj["start_off_navmesh_m"] > 0.2
        assert nav["assumed_walkable"]["blind_spot_m2"] == 0 and len(exempt) > 1
        assert traj["exempt_min_clearance_m"] >= radius  # the way onto the NavMesh passes over the table top
    elif case == FailureCase.SPARSE_LIDAR:
        cam_h = json.loads((scene_dir / "gt_scene.json").read_text())["camera_height_m"]
        assert depth_info["rescaled"] and depth_info["max_gap_px"] >= 2
        assert any("unknown units" in d for d in depth_info["decisions"])
        assert depth_info["valid_fraction"] > 0.6  # scan-line gaps filled
        # Floor put at the default 1.6 m: the relative scale of the scene is kept.
        assert depth_info["scale_factor"] == pytest.approx(1.6 / (cam_h * 450 * 0.001), rel=0.03)
    elif case == FailureCase.LAYOUT_ONLY:
        assert depth_info["camera_height_estimated_before"] == pytest.approx(
            json.loads((scene_dir / "gt_scene.json").read_text())["camera_height_m"], rel=0.01)


@pytest.mark.parametrize("case", [FailureCase.ODD_FORMAT, FailureCase.GRAYSCALE_EXIF, FailureCase.HUGE])
def test_odd_panoramas_and_sizes(tmp_path, case):
    scene_dir = write_failure_scene(case, tmp_path / "scene", height=64)
    spec = load_stage("depth")
    pano = next(scene_dir.glob("panorama.*"))
    depth = next(scene_dir.glob("depth.*"))
    params = spec.params_cls(max_height=64)
    m = execute_stage(spec, {"panorama": pano, "depth": depth}, params, tmp_path / "depth")
    info = m["info"]
    assert (info["height"], info["width"]) == (64, 128)
    rgb = cv2.imread(str(tmp_path / "depth" / "panorama.png"))
    d = np.load(tmp_path / "depth" / "depth.npy")
    assert rgb.shape == (64, 128, 3) and d.shape == (64, 128)
    truth = failure_scene(0).render(failure_scene(0).world_from_canonical, 64, 128)[0]
    if case == FailureCase.GRAYSCALE_EXIF:
        assert {"EXIF orientation applied", "grayscale panorama expanded to RGB"} <= set(info["decisions"])
        gray = cv2.cvtColor(truth, cv2.COLOR_RGB2GRAY).astype(float)
        assert np.abs(rgb[..., 0].astype(float) - gray).mean() < 6  # upright again (JPEG loss only)
    elif case == FailureCase.ODD_FORMAT:
        assert {"16-bit panorama scaled to 8 bit", "alpha channel dropped"} <= set(info["decisions"])
        assert np.abs(cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB).astype(int) - truth).max() <= 1
        assert any("resized from 64x32" in x for x in info["decisions"])
    else:
        assert info["input_size"] == [512, 256] and any("max_height 64" in x for x in info["decisions"])


def test_planar_layout_depth_floor_fit():
    # A perfectly planar floor puts every vote into one histogram bin (the crash of the issue).
    from panoworld.room.floor import estimate_floor
    from panoworld.tools.synth.failure_cases import empty_room

    scene = empty_room(0)
    _, depth = scene.render(scene.world_from_canonical, 32, 64)
    fit = estimate_floor(depth, np.isfinite(depth) & (depth > 0))
    assert fit is not None and fit.camera_height == pytest.approx(scene.tracks[0].camera_height, rel=1e-3)


def test_rgb_only_error_names_the_fix(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-hf-cache"))  # no depth model on disk
    scene_dir = tmp_path / "rgb"
    scene_dir.mkdir()
    cv2.imwrite(str(scene_dir / "panorama.png"), np.zeros((32, 64, 3), np.uint8))
    with pytest.raises(StageInputError) as e:
        run_default(scene_dir)
    msg = str(e.value)
    assert "\n" not in msg and "python runner.py weights fetch depth-anything-v2-small" in msg
    assert "put a metric depth.npy|exr|png next to the panorama" in msg


def test_runner_prints_the_failing_stage_reason(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-hf-cache"))
    scene_dir = tmp_path / "rgb"
    scene_dir.mkdir()
    cv2.imwrite(str(scene_dir / "panorama.png"), np.zeros((32, 64, 3), np.uint8))
    report = pl.run(scene_dir, until="depth")
    (failed,) = [r for r in report.results if r.action == "failed"]
    assert failed.stage == "depth" and "weights fetch depth-anything-v2-small" in failed.reason
    # bad input: exit 2 and nothing written (no artifacts/, no lock, no log)
    assert failed.bad_input and not (scene_dir / "artifacts").exists()
