"""Trajectories: GT-checked planning on synthetic scenes, resampling/smoothing, exact clearance, file I/O and the stage."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from panoworld.core.conventions import invert_pose, pose_from_rt, rotmat_from_quat_wxyz, transform_points
from panoworld.geometry.erp_mesh import erp_mesh_from_depth
from panoworld.geometry.navmesh import NavMesh
from panoworld.geometry.polygons import triangulate_rings
from panoworld.io.trajectory import (
    TrajectoryFileError,
    load_clips,
    load_trajectory,
    read_trajectory_doc,
    read_trajectory_file,
    write_trajectory,
)
from panoworld.navmesh import build_navmesh
from panoworld.trajectory import (
    PathKind,
    TrajectoryParams,
    YawMode,
    mesh_clearance,
    plan_path,
    polyline_length,
    poses_from_positions,
    resample_polyline,
    sector_coverage,
    sector_of,
    sector_reach,
    smooth_polyline,
    step_lengths,
    yaw_of_path,
)
from tests.test_navmesh import _make_mesh_artifact, box_room, erp_depth


def _synth(seed: int, height: int = 128):
    from panoworld.tools.synth import generate_scene

    scene = generate_scene(seed, "ci-tiny")
    w_from_c = scene.world_from_canonical
    depth = scene.raycaster.render_erp(w_from_c, height, 2 * height).distance.astype(np.float32)
    mesh = erp_mesh_from_depth(depth, np.zeros(depth.shape + (3,), np.uint8))
    return mesh, transform_points(invert_pose(w_from_c), scene.vertices.astype(np.float64)), scene.faces


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_planned_paths_are_safe_against_ground_truth(seed):
    # NavMesh from the ERP mesh of the GT depth (what the pipeline sees); clearance against the full GT mesh.
    mesh, gt_v, gt_f = _synth(seed)
    nav = build_navmesh(mesh.vertices, mesh.faces, mesh.face_valid)
    radius = nav.agent["agent_radius_m"]
    _, reach = sector_reach(nav, np.zeros(2), 8)
    for kind in (PathKind.SECTOR, PathKind.RING):
        for stride in (1, 4):
            plan = plan_path(nav, TrajectoryParams(kind=kind, stride=stride))
            poses = poses_from_positions(plan.positions)
            assert poses.shape == (81, 4, 4) and np.array_equal(poses[0], np.eye(4))
            assert mesh_clearance(gt_v, gt_f, poses[:, :3, 3]).min() >= radius
            assert nav.contains(plan.positions).all()
            steps = step_lengths(poses)
            assert steps.std() / steps.mean() <= 0.1
            assert steps.max() <= 0.05 * stride + 1e-9
            if kind == PathKind.RING:
                assert np.linalg.norm(plan.positions[-1] - plan.positions[0]) <= steps.max() + 1e-9
            else:
                covered = sector_coverage(plan.positions, np.zeros(2), 8, 0.1).sum()
                assert covered >= min(6, int((reach >= 0.1).sum()))


def _walk_extent(nav, sector: int, reach_m: float, n: int = 4000) -> float:
    """Farthest NavMesh sample of a sector (8 around the camera) whose shortest walk from the camera is <= reach_m."""
    pts = nav.sample_points(n, 1)
    pts = pts[sector_of(pts, np.zeros(2), 8) == sector]
    for q in pts[np.argsort(-np.linalg.norm(pts, axis=1))]:
        try:
            if polyline_length(nav.path(np.zeros(2), q)) <= reach_m:
                return float(np.linalg.norm(q))
        except ValueError:  # not connected to the camera's piece of floor
            continue
    return 0.0


@pytest.mark.parametrize("seed", [0, 3])
def test_explore_paths_leave_the_camera_into_every_sector_and_reach_the_room(seed):
    # One path per sector from the camera: safe against the GT mesh, on the NavMesh, uniform steps within each path,
    # each leaving from pose 0, and each tip >= 70 % of the sector's extent (independently: A* walks to samples).
    mesh, gt_v, gt_f = _synth(seed)
    nav = build_navmesh(mesh.vertices, mesh.faces, mesh.face_valid)
    radius = nav.agent["agent_radius_m"]
    params = TrajectoryParams(kind=PathKind.EXPLORE)
    plan = plan_path(nav, params)
    poses = poses_from_positions(plan.positions)
    assert poses.shape == (81, 4, 4) and np.array_equal(poses[0], np.eye(4))
    assert mesh_clearance(gt_v, gt_f, poses[:, :3, 3]).min() >= radius
    assert nav.contains(plan.positions).all()
    paths = plan.info["paths"]
    assert [p["start"] for p in paths] == [1] + [p["stop"] for p in paths[:-1]] and paths[-1]["stop"] == 81
    assert len(paths) >= 6
    for p in paths:
        walk = plan.positions[[0, *range(p["start"], p["stop"])]]
        steps = np.linalg.norm(np.diff(walk, axis=0), axis=1)
        assert steps.max() <= 1.35 * steps.mean()  # smoothing and corners: chords a little shorter than arcs
        extent = _walk_extent(nav, p["sector"], params.reach_m or np.inf)
        tip = float(np.linalg.norm(walk[-1]))
        assert tip >= 0.7 * extent - 0.05, (p, extent)
        if extent >= 1.5:
            assert tip >= 1.0


def test_explore_reaches_the_far_end_of_a_long_hall_within_the_step_bound():
    # An 8 m hall, the camera 2 m off its centre: the default (no reach cap) walks >= 70 % of each sector's straight walkable distance (the eval's
    # own measure, ray cast on the NavMesh) with a mean step <= max_step_m; the old 3 m cap does not; a tighter
    # max_step_m cuts the paths to one fraction of their length (cut_lengths) and the step follows.
    from panoworld.tools.eval.roam import trajectory_reach
    from panoworld.trajectory.explore import cut_lengths
    from tests.test_navmesh import nav_of

    nav = nav_of(box_room(size=(8.0, 2.8, 5.0), cam_xz=(-2.0, 0.0), obstacles=()), 128)
    for params, ok in ((TrajectoryParams(), True), (TrajectoryParams(reach_m=3.0), False)):
        plan = plan_path(nav, params)
        r = trajectory_reach(nav, poses_from_positions(plan.positions))
        assert (r["sector_reach_fraction_min"] >= 0.7) == ok, r
        steps = plan.info["path_steps_m"]
        assert plan.step_m <= params.max_step_m + 1e-9 and max(steps) <= 1.2 * params.max_step_m
    tight = plan_path(nav, TrajectoryParams(max_step_m=0.15))
    assert tight.step_m == pytest.approx(0.15, rel=0.02) and tight.info["path_cut_fraction"] < 0.7
    lengths = np.array([0.5, 2.0, 6.0, 9.0])
    assert np.array_equal(cut_lengths(lengths, 100.0), lengths)
    cut = cut_lengths(lengths, 8.0)  # the same fraction f of each, but >= 1 m of each that long
    assert cut.sum() == pytest.approx(8.0) and cut[0] == 0.5 and cut[1] == pytest.approx(1.0)
    assert cut[2] / 6.0 == pytest.approx(cut[3] / 9.0)


def test_camera_off_the_navmesh_walks_straight_onto_it():
    # The camera stands 0.1 m from a wall: only the poses on the straight way to the NavMesh are off it.
    from tests.test_navmesh import nav_of

    nav = nav_of(box_room(cam_xz=(2.4, 0.0)), 128)
    assert not nav.info["camera_on_navmesh"]
    for kind in PathKind:
        plan = plan_path(nav, TrajectoryParams(kind=kind, stride=2))
        hub = np.asarray(plan.info["hub"])
        assert plan.info["start_off_navmesh_m"] > 0.15 and len(plan.exempt) >= 2
        rest = np.setdiff1d(np.arange(len(plan.positions)), plan.exempt)
        assert nav.contains(plan.positions[rest]).all()
        off = plan.positions[plan.exempt]
        assert np.allclose(off[:, 0] * hub[1] - off[:, 1] * hub[0], 0, atol=1e-9)  # on the line camera -> hub


def test_ring_runs_laps_in_a_small_room_to_keep_the_step():
    from tests.test_navmesh import nav_of

    nav = nav_of(box_room(size=(2.6, 2.8, 2.6), obstacles=()), 96)
    plan = plan_path(nav, TrajectoryParams(kind=PathKind.RING, stride=4))  # 16 m of loop in a 2.6 m room
    steps = np.linalg.norm(np.diff(np.concatenate([plan.positions, plan.positions[:1]]), axis=0), axis=1)
    assert plan.info["ring_laps"] >= 2 and not plan.info["step_adapted"]
    assert np.all(np.abs(steps - 0.2) < 0.02) and nav.contains(plan.positions).all()
    assert plan.info["loop_length_m"] * plan.info["ring_laps"] <= 81 * 0.2 + 1e-6


def test_resample_gives_uniform_steps_and_closes_loops():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    closed = resample_polyline(square, 40, closed=True)
    d = np.linalg.norm(np.diff(np.concatenate([closed, closed[:1]]), axis=0), axis=1)
    assert np.allclose(d, 0.1) and np.allclose(closed[0], [0, 0])
    open_ = resample_polyline(square, 31)
    assert np.allclose(open_[[0, -1]], square[[0, -1]])
    assert np.allclose(np.linalg.norm(np.diff(open_, axis=0), axis=1), 0.1)
    # Off-corner samples: chords would be shorter than arcs at the corners; equalisation evens them out.
    raw = np.linalg.norm(np.diff(resample_polyline(square, 26, equalize=0), axis=0), axis=1)
    even = np.linalg.norm(np.diff(resample_polyline(square, 26), axis=0), axis=1)
    assert raw.std() / raw.mean() > 0.03 and even.std() / even.mean() < 0.01


def test_smoothing_cuts_corners_only_inside_the_navmesh():
    # An L-shaped corridor 0.4 m wide; a path hugging its inner corner cannot be cut there.
    ring = np.array([[0, 0], [2, 0], [2, 2], [1.6, 2], [1.6, 0.4], [0, 0.4]], np.float64)
    v, t, adj = triangulate_rings([ring], 0.05)
    nav = NavMesh(v, t, adj, [ring], floor_y=1.0)
    path = np.array([[0.1, 0.2], [1.6, 0.4 - 1e-6], [1.8, 1.9]])  # through the inner corner
    sm = smooth_polyline(nav, path, closed=False, iterations=4)
    assert np.allclose(sm[[0, -1]], path[[0, -1]])
    assert not nav.blocked(sm[:-1], sm[1:]).any()
    wide = np.array([[0.1, 0.2], [1.8, 0.2], [1.8, 1.9]])  # a corner with room: it is rounded
    sw = smooth_polyline(nav, wide, closed=False, iterations=4)
    assert len(sw) > 3 and not nav.blocked(sw[:-1], sw[1:]).any()
    assert np.linalg.norm(sw - [1.8, 0.2], axis=1).min() > 0.05


def test_yaw_follows_the_path_and_stays_upright():
    pos = np.array([[0, 0], [0, 0.1], [0, 0.2], [0.1, 0.2], [0.2, 0.2]], np.float64)
    yaw = yaw_of_path(pos, closed=False, sigma_frames=0)
    assert yaw[0] == 0 and np.isclose(yaw[-1], np.pi / 2)  # heading +z turned to +x
    poses = poses_from_positions(pos, yaw)
    assert np.array_equal(poses[0], np.eye(4))
    assert np.allclose(poses[:, :3, 1], [0, 1, 0]) and np.allclose(poses[:, 1, :3], [0, 1, 0])
    assert np.allclose(poses[-1, :3, 2], [1, 0, 0])  # camera forward (+z) points along +x
    assert np.allclose(np.linalg.det(poses[:, :3, :3]), 1)


def test_mesh_clearance_is_exact():
    box = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    rng = np.random.default_rng(0)
    pts = rng.uniform(-2, 2, (200, 3))
    _, ref, _ = trimesh.proximity.closest_point_naive(box, pts)
    assert np.allclose(mesh_clearance(box.vertices, box.faces, pts), ref, atol=1e-9)
    assert np.allclose(mesh_clearance(box.vertices, box.faces, pts, cap=0.5), np.minimum(ref, 0.5), atol=1e-9)


def _wobbly_poses(n=7):
    rng = np.random.default_rng(3)
    out = [np.eye(4)]
    for _ in range(n - 1):
        q = rng.normal(size=4)
        out.append(pose_from_rt(rotmat_from_quat_wxyz(q), rng.normal(size=3)))
    return np.stack(out)


def test_trajectory_files_round_trip(tmp_path):
    poses = _wobbly_poses()
    write_trajectory(tmp_path, poses, np.ones(len(poses)), fps=16.0, kind="user")
    assert np.allclose(load_trajectory(tmp_path), poses, atol=1e-12)
    assert np.allclose(load_trajectory(tmp_path / "trajectory.tum"), poses, atol=1e-8)
    lines = (tmp_path / "trajectory.tum").read_text().splitlines()
    assert lines[2].split()[0] == f"{1 / 16:.6f}" and len(lines) == len(poses) + 1
    (tmp_path / "plain.json").write_text(json.dumps(poses.tolist()))
    assert np.allclose(read_trajectory_file(tmp_path / "plain.json"), poses)
    assert load_clips(tmp_path, len(poses)) == [list(range(len(poses)))]  # one path: one clip
    doc = read_trajectory_doc(tmp_path)
    assert doc["fps"] == 16.0 and doc["kind"] == "user" and np.allclose(doc["poses"], poses)
    assert read_trajectory_doc(tmp_path / "trajectory.tum") == {}  # TUM carries no metadata
    assert read_trajectory_doc(tmp_path / "nowhere", missing_ok=True) == {}
    (tmp_path / "trajectory.json").write_text('{"poses": [')
    with pytest.raises(TrajectoryFileError, match=r"trajectory\.json"):
        read_trajectory_doc(tmp_path)


def test_clips_are_the_paths_with_their_predecessor(tmp_path):
    poses = _wobbly_poses()[:7]
    paths = [{"sector": 0, "start": 1, "stop": 4, "from": 0}, {"sector": 3, "start": 4, "stop": 7, "from": 0}]
    write_trajectory(tmp_path, poses, np.ones(7), fps=16.0, kind="explore", paths=paths)
    assert load_clips(tmp_path, 7) == [[0, 1, 2, 3], [0, 4, 5, 6]]
    write_trajectory(tmp_path, poses, np.ones(7), fps=16.0, kind="explore", paths=paths[:1])
    with pytest.raises(ValueError, match="do not cover the 7 poses"):
        load_clips(tmp_path, 7)


@pytest.mark.parametrize(
    "name, text, match",
    [
        ("a.json", '{"frames": []}', "without a 'poses' list"),
        ("b.json", "[[1, 0], [0, 1]]", "expected \\(N, 4, 4\\)"),
        ("c.json", json.dumps([np.eye(4).tolist(), (2 * np.eye(4)).tolist()]), "pose 1 is not a rigid"),
        ("d.tum", "0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n", "d.tum:2: 7 values"),
        ("e.tum", "0 0 0 0 0 0 0 2\n", "norm 2.0000"),
        ("f.json", "{oops", "invalid JSON"),
    ],
)
def test_bad_trajectory_files_are_named(tmp_path, name, text, match):
    (tmp_path / name).write_text(text)
    with pytest.raises(TrajectoryFileError, match=match):
        read_trajectory_file(tmp_path / name)


@pytest.fixture(scope="module")
def artifacts(tmp_path_factory):
    from stages import navmesh

    root = tmp_path_factory.mktemp("traj")
    mesh_dir = _make_mesh_artifact(root, erp_depth(box_room(), 128))
    assert navmesh.main(["--mesh", str(mesh_dir), "--out", str(root / "nav")]) == 0
    return root, mesh_dir, root / "nav"


def test_stage_plans_a_valid_trajectory(artifacts):
    from stages import trajectory as stage

    root, mesh_dir, nav_dir = artifacts
    out = root / "ring"
    args = ["--navmesh", str(nav_dir), "--mesh", str(mesh_dir), "--out", str(out), "--kind", "ring", "--yaw", "forward"]
    assert stage.main(args) == 0
    poses = load_trajectory(out)
    assert poses.shape == (81, 4, 4) and np.array_equal(poses[0], np.eye(4))
    assert np.allclose(load_trajectory(out / "trajectory.tum"), poses, atol=1e-8)
    doc = json.loads((out / "trajectory.json").read_text())
    assert doc["kind"] == "ring" and doc["frame"] == "canonical (pose 0 = identity)" and len(doc["clearance_m"]) == 81
    info = json.loads((out / "manifest.json").read_text())["info"]
    assert info["invalid_poses"] == [] and info["min_clearance_m"] >= 0.25 and info["step_cv"] <= 0.1
    assert info["closure_m"] <= max(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)) + 1e-9


def _through_wall(n=12, step=0.3):
    # Along +x from the camera: the wall is at x = 2.5 (the NavMesh ends about 0.3 m before it).
    return poses_from_positions(np.stack([np.arange(n) * step, np.zeros(n)], 1))


def test_stage_rejects_a_user_trajectory_through_a_wall(artifacts, capsys):
    from stages import trajectory as stage

    root, mesh_dir, nav_dir = artifacts
    user = root / "through_wall.json"
    user.write_text(json.dumps({"poses": _through_wall().tolist()}))
    base = ["--navmesh", str(nav_dir), "--mesh", str(mesh_dir), "--user-trajectory", str(user)]
    assert stage.main([*base, "--out", str(root / "bad")]) == 2
    err = capsys.readouterr().err
    assert "4 of 12 poses are invalid" in err
    assert "outside the walkable NavMesh: poses 8-11" in err and "too close to the mesh: poses 8-9" in err
    assert not (root / "bad").exists()

    # The same poses as TUM text, reported instead of rejected.
    from panoworld.io.trajectory import write_tum

    write_tum(root / "through_wall.tum", _through_wall(), 16.0)
    out = root / "reported"
    tum = ["--navmesh", str(nav_dir), "--mesh", str(mesh_dir), "--user-trajectory", str(root / "through_wall.tum")]
    assert stage.main([*tum, "--out", str(out), "--on-invalid", "report"]) == 0
    info = json.loads((out / "manifest.json").read_text())["info"]
    assert [p["index"] for p in info["invalid_poses"]] == [8, 9, 10, 11] and info["kind"] == "user"
    assert np.allclose(load_trajectory(out), _through_wall(), atol=1e-8)


def test_stage_requires_pose_zero_at_the_camera(artifacts, capsys):
    from stages import trajectory as stage

    root, mesh_dir, nav_dir = artifacts
    shifted = _through_wall(5)
    shifted[:, 0, 3] -= 0.5
    user = root / "shifted.json"
    user.write_text(json.dumps({"poses": shifted.tolist()}))
    base = ["--navmesh", str(nav_dir), "--mesh", str(mesh_dir), "--user-trajectory", str(user)]
    assert stage.main([*base, "--out", str(root / "s1")]) == 2
    assert "pose 0 is not the identity" in capsys.readouterr().err
    assert stage.main([*base, "--out", str(root / "s2"), "--reanchor", "true"]) == 0
    assert np.allclose(load_trajectory(root / "s2"), _through_wall(5))


def test_bad_params_are_clear_errors(artifacts, capsys):
    from stages import trajectory as stage

    root, mesh_dir, nav_dir = artifacts
    base = ["--navmesh", str(nav_dir), "--mesh", str(mesh_dir), "--out", str(root / "p")]
    assert stage.main([*base, "--stride", "3"]) == 2
    assert "stride=3" in capsys.readouterr().err
    assert TrajectoryParams().yaw == YawMode.FIXED


def test_sector_decisions_reachable_covered_and_ring_closure():
    # docs/real_inputs.md: sectors are centred on the camera; reachable = floor in the sector that one out-and-back
    # leg reaches within the budget; a plan from a camera on the NavMesh covers every reachable sector.
    from panoworld.trajectory import MIN_SECTOR_DIST_M, planning_hub, sector_of, sector_reachability
    from tests.test_navmesh import nav_of

    nav = nav_of(box_room(cam_xz=(1.5, 0.0), obstacles=()), 96)  # the camera 1 m from the +x wall
    start = np.zeros(2)
    hub, off = planning_hub(nav, start)
    pts = nav.sample_points(4000, 0)
    pts = pts[np.linalg.norm(pts, axis=1) >= MIN_SECTOR_DIST_M + 0.05]
    has_floor = np.zeros(8, bool)
    has_floor[np.unique(sector_of(pts, start, 8))] = True
    assert np.array_equal(sector_reachability(nav, start, hub, 8, 100.0)["reachable"], has_floor)
    tight = sector_reachability(nav, start, hub, 8, 0.5)  # legs of 0.25 m: every sector still has floor that near
    assert tight["reachable"].all() and np.all(tight["entry_m"] <= 0.25)
    none = sector_reachability(nav, start, hub, 8, 0.1)  # a 5 cm leg cannot get 0.1 m from the camera
    assert not none["reachable"].any()
    plan = plan_path(nav, TrajectoryParams())
    covered = sector_coverage(plan.positions, start, 8, MIN_SECTOR_DIST_M)
    assert plan.info["sectors_reachable"] == 8 and covered.all() and plan.info["sectors_covered"] == 8
    for s in (1, 4):  # ring paths close: the last pose is one step before the first
        ring = plan_path(nav, TrajectoryParams(kind=PathKind.RING, stride=s))
        gap = np.linalg.norm(ring.positions[-1] - ring.positions[0])
        assert gap == pytest.approx(ring.step_m, rel=0.05)
