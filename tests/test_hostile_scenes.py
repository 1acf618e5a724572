"""Real-capture cases of issue #24 rebuilt synthetically: no room to move (a closet), far depth outliers, a rig hiding
1 m of floor. Each still delivers a valid trajectory, with the decision in the manifests."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from panoworld.core.conventions import erp_dirs64
from panoworld.depth.outliers import (
    BROKEN_FACTOR,
    BROKEN_SHARE,
    FAR_FACTOR,
    SPIKE_RATIO,
    mask_depth_outliers,
    spike_mask,
)
from panoworld.navmesh.no_room import MIN_ROOM_M2
from panoworld.tools.synth.failure_cases import FailureCase, failure_scene, write_failure_scene
from panoworld.trajectory.common import MAX_APPROACH_SHARE
from tests.test_real_inputs import run_default


def poses_of(scene):
    return np.asarray(json.loads((scene.artifact_dir("trajectory") / "trajectory.json").read_text())["poses"])


def test_closet_delivers_a_path_with_a_smaller_agent(tmp_path):
    m, scene = run_default(write_failure_scene(FailureCase.CLOSET, tmp_path / "closet", height=128))
    nav, traj = m["navmesh"]["info"], m["trajectory"]["info"]
    no_room = nav["no_room"]
    # The requested 0.25 m agent has no room in the closet (what stopped the pipeline before); a smaller one does.
    assert no_room["requested_agent_radius_m"] == 0.25 and "no room to move" in no_room["reason"]
    assert no_room["decision"] == "smaller agent" and no_room["agent_radius_m"] < 0.25
    assert nav["area_m2"] >= MIN_ROOM_M2 and nav["agent_radius_m"] == no_room["agent_radius_m"]
    assert traj["no_room"] == no_room["reason"] and not traj["rotation_only"]
    assert traj["frames"] == 81 and traj["invalid_poses"] == [] and traj["agent_radius_m"] == no_room["agent_radius_m"]
    held = [c for i, c in enumerate(json.loads((scene.artifact_dir("trajectory") / "trajectory.json").read_text())
                                    ["clearance_m"]) if i not in traj["exempt_poses"]]
    assert min(held) >= no_room["agent_radius_m"] - 1e-9  # clear of the closet walls (they are in the depth)
    assert traj["length_m"] > 1.0  # it walks out of the closet into the room
    from panoworld.tools.report.scene import section_plan
    from panoworld.tools.report.scene_data import ReportParams, SceneData

    body = section_plan(SceneData(scene.root), ReportParams()).body  # the HTML report says it too
    assert "no room to move" in body and "decided: smaller agent" in body


def test_no_visible_floor_gives_a_stationary_rotation_only_path(tmp_path):
    d = write_failure_scene(FailureCase.CLOSET, tmp_path / "blind", height=128)
    depth = np.load(d / "depth.npy")
    depth[depth.shape[0] // 2 + 4:] = 0.0  # nothing seen below the horizon: no floor at all
    np.save(d / "depth.npy", depth)
    m, scene = run_default(d)
    nav, traj = m["navmesh"]["info"], m["trajectory"]["info"]
    assert nav["no_room"]["decision"] == "stationary" and "no walkable floor" in nav["no_room"]["reason"]
    assert [t["problem"] is not None for t in nav["no_room"]["tried"]] == [True, True]
    assert traj["rotation_only"] and traj["no_room"] and traj["invalid_poses"] == []
    poses = poses_of(scene)
    assert len(poses) == 81 and np.abs(poses[:, :3, 3]).max() < 1e-9 and np.allclose(poses[0], np.eye(4))
    yaw = np.unwrap(np.arctan2(poses[:, 0, 2], poses[:, 0, 0]))
    np.testing.assert_allclose(np.diff(yaw), 2 * np.pi / 81, atol=1e-9)  # one uniform turn, upright
    np.testing.assert_allclose(poses[:, 1, :3], np.tile([0, 1, 0], (81, 1)), atol=1e-12)


def test_far_outliers_are_masked_and_the_navmesh_is_the_room(tmp_path):
    d = write_failure_scene(FailureCase.FAR_OUTLIERS, tmp_path / "far", height=128)
    facts = json.loads((d / "gt_scene.json").read_text())
    clean = tmp_path / "clean"
    clean.mkdir()
    scene = failure_scene(0)
    _, truth = scene.render(scene.world_from_canonical, 128, 256)
    np.save(clean / "depth.npy", np.where(np.isfinite(truth), truth, 0).astype(np.float32))
    (clean / "panorama.png").write_bytes((d / "panorama.png").read_bytes())
    m, _ = run_default(d)
    m_clean, _ = run_default(clean)
    rec = m["depth"]["info"]["outliers"]
    assert rec["far_px"] + rec["spike_px"] >= 0.95 * facts["outlier_pixels"]
    assert rec["max_depth_before"] > 200 and rec["max_depth_after"] < 10
    assert any(s.startswith("depth outliers masked") for s in m["depth"]["info"]["decisions"])
    assert abs(m["depth"]["info"]["scale_factor"] - 1.0) < 0.02  # the floor fit is not spoiled (it was: 1/400)
    area, area_clean = m["navmesh"]["info"]["area_m2"], m_clean["navmesh"]["info"]["area_m2"]
    assert abs(area - area_clean) <= 0.05 * area_clean
    assert m_clean["depth"]["info"]["outliers"]["far_px"] == 0  # nothing masked in the clean room


def test_spikes_are_found_and_depth_edges_are_not_spikes():
    rng = np.random.default_rng(3)
    d = cv2.GaussianBlur(rng.uniform(1, 4, (128, 256)).astype(np.float32), (0, 0), 3)
    d[:, 60:90] *= 0.1  # a near object: its edges are depth jumps of 10x, not spikes
    d[40:44, 150:154] *= 0.1  # a small near object
    spikes = np.zeros(d.shape, bool)
    spikes[rng.integers(2, 126, 40), rng.integers(100, 140, 40)] = True
    d[spikes] *= SPIKE_RATIO + 1
    valid = np.ones(d.shape, bool)
    found = spike_mask(d, valid)
    assert found[spikes].mean() > 0.95 and not found[~spikes].any()
    kept, rec = mask_depth_outliers(d, valid)
    assert rec["far_px"] == 0 and rec["spike_px"] == found.sum() and not kept[found].any()


def _box_depth(dirs, x, z, y, open_x1_beyond_z=None):
    """Ray distance (H, W) to a box room (x, z, y: (low, high) metres about the camera, y down) seen from inside: its
    four walls, an endless floor and ceiling; open_x1_beyond_z: the wall x = x[1] has no segment beyond that z (the rays
    through the gap reach the floor or ceiling planes far away, as a layout seen from outside its polygon gives them)."""
    t = np.full(dirs.shape[:2], np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, (lo, hi) in ((0, x), (2, z), (1, y)):
            d = dirs[..., axis]
            hit = np.where(d > 0, hi / d, np.where(d < 0, lo / d, np.inf))
            if axis != 1:  # a wall ends where the other walls meet it
                other, (olo, ohi) = (2, z) if axis == 0 else (0, x)
                at = hit * dirs[..., other]
                hit = np.where((at >= olo - 1e-9) & (at <= ohi + 1e-9), hit, np.inf)
            if axis == 0 and open_x1_beyond_z is not None:
                hit = np.where((d > 0) & (hit * dirs[..., 2] > open_x1_beyond_z), np.inf, hit)
            t = np.minimum(t, hit)
    return t.astype(np.float32)


def test_a_long_hallway_seen_from_its_end_is_kept_and_a_broken_layout_is_still_masked():
    dirs = erp_dirs64(256, 512)
    # A hallway 1 m wide and 12 m long, the camera 0.5 m from its end: its median depth is that of the near walls, and
    # the far end lies 15x beyond it, farther than FAR_FACTOR but within any room (BROKEN_FACTOR): all of it is kept.
    hall = _box_depth(dirs, (-0.5, 0.5), (-0.5, 11.5), (-1.0, 1.5))
    kept, rec = mask_depth_outliers(hall, np.ones(hall.shape, bool))
    assert hall.max() > 1.5 * FAR_FACTOR * rec["median_depth"]  # what a median rule of FAR_FACTOR alone would cut
    assert kept.all() and rec["far_px"] == 0 and rec["far_factor"] == BROKEN_FACTOR and rec["broken_share"] == 0
    assert rec["max_depth_after"] == pytest.approx(float(hall.max()))
    # The same hallway with one wall missing beyond 3 m: the floor and ceiling there run on for hundreds of metres, so
    # the depth is broken, and everything beyond FAR_FACTOR x its median goes (the hallway's far end with it).
    broken = _box_depth(dirs, (-0.5, 0.5), (-0.5, 11.5), (-1.0, 1.5), open_x1_beyond_z=3.0)
    kept, rec = mask_depth_outliers(broken, np.ones(broken.shape, bool))
    assert broken.max() > 100 * rec["median_depth"] and rec["broken_share"] > BROKEN_SHARE
    assert rec["far_factor"] == FAR_FACTOR
    np.testing.assert_array_equal(kept, broken <= FAR_FACTOR * rec["median_depth"])
    assert rec["max_depth_after"] <= rec["far_threshold"] == pytest.approx(FAR_FACTOR * rec["median_depth"])
    # A few lone far values (less than BROKEN_SHARE of the sphere) do not make a depth broken; they go all the same.
    spiky = hall.copy()
    spiky[100, 200:203] = 500.0
    kept, rec = mask_depth_outliers(spiky, np.ones(spiky.shape, bool))
    assert rec["far_factor"] == BROKEN_FACTOR and rec["far_px"] == 3 and not kept[100, 200:203].any()
    assert kept.sum() == kept.size - 3


def test_start_off_the_navmesh_costs_at_most_a_tenth_of_the_poses(tmp_path):
    m, scene = run_default(write_failure_scene(FailureCase.RIG_HIDES_FLOOR, tmp_path / "rig", height=128))
    traj = m["trajectory"]["info"]
    assert traj["start_off_navmesh_m"] > 1.0  # the rig hides more than 1 m of floor
    approach = traj["plan"]["approach_steps"]
    assert 1 <= approach <= MAX_APPROACH_SHARE * (traj["frames"] - 1)
    assert len(traj["exempt_poses"]) - 1 <= approach and traj["invalid_poses"] == []
    poses = poses_of(scene)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps[:approach].max() == pytest.approx(traj["start_off_navmesh_m"] / approach, rel=1e-6)
    assert traj["sectors_covered"] >= 2


@pytest.mark.slow
def test_no_visible_floor_still_delivers_gaussians_end_to_end(tmp_path):
    from panoworld.framework import pipeline as pl

    d = write_failure_scene(FailureCase.CLOSET, tmp_path / "blind", height=64)
    depth = np.load(d / "depth.npy")
    depth[depth.shape[0] // 2 + 2:] = 0.0
    np.save(d / "depth.npy", depth)
    report = pl.run(d, preset="ci-tiny", sets=["poses.backend=colmap"])  # COLMAP, not the plan
    assert report.ok, report.table()
    poses = json.loads((d / "artifacts" / "poses" / "manifest.json").read_text())["info"]
    assert any("planned poses used" in x for x in poses["decisions"])
    assert (d / "artifacts" / "gaussians" / "gaussians.ply").stat().st_size > 0
