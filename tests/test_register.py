"""Multi-panorama homes (issue #27): synthetic ground truth and the register stage against it."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from panoworld.core.conventions import invert_pose
from panoworld.framework.stage import execute_stage, load_stage
from panoworld.framework.stage_params import params_from_dict
from panoworld.io.depth import read_panorama
from panoworld.register.options import RegisterOptions
from panoworld.register.pairwise import PairResult, consistency
from panoworld.register.solve import FEW_KEYPOINTS, register_panoramas
from panoworld.tools.synth.generate import generate_scene
from stages.register import main as register_main
from tests.conftest import HOME_HEIGHT as HEIGHT

ROOT = Path(__file__).resolve().parent.parent
TOL_CM, TOL_DEG = 5.0, 1.0

torch.set_num_threads(1)


def _errors(E: np.ndarray, G: np.ndarray) -> tuple[float, float]:
    cos = np.clip((np.trace(G[:3, :3].T @ E[:3, :3]) - 1) / 2, -1, 1)
    return float(np.linalg.norm(G[:3, 3] - E[:3, 3]) * 100), float(np.degrees(np.arccos(cos)))


def _gt(scene: Path) -> dict[str, np.ndarray]:
    return {n: np.asarray(T) for n, T in json.loads((scene / "gt" / "poses.json").read_text()).items()}


def _scene_copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("gt"))
    return dst


def test_home_ground_truth_layout_and_consistency(home_dir):
    names = ["pano_00", "pano_01", "pano_02"]
    assert sorted(p.stem for p in (home_dir / "panoramas").glob("*.png")) == names
    assert sorted(p.stem for p in (home_dir / "depths").glob("*.npy")) == names
    assert not (home_dir / "poses.json").exists() and not (home_dir / "panorama.png").exists()
    gt = _gt(home_dir)
    rooms = json.loads((home_dir / "gt" / "capture_rooms.json").read_text())
    assert len(set(rooms.values())) >= 3
    for T in gt.values():
        assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9) and np.allclose(T[3], [0, 0, 0, 1])
        assert np.allclose(T[:3, 1], [0, 1, 0])  # upright: camera y is world down
    # The renders agree with the poses: each panorama's depth lands on the other's surface where both see it.
    depth = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in names}
    overlap, cons, _ = consistency(invert_pose(gt["pano_00"]) @ gt["pano_01"], depth["pano_00"], depth["pano_01"])
    assert overlap > 0.02 and cons > 0.97
    shifted = invert_pose(gt["pano_00"]) @ gt["pano_01"]
    shifted[:3, 3] += [0.3, 0.0, 0.0]
    assert consistency(shifted, depth["pano_00"], depth["pano_01"])[1] < 0.9


def test_register_stage_within_tolerance(home_dir, tmp_path):
    spec = load_stage("register")
    out = tmp_path / "register"
    manifest = execute_stage(spec, {"scene": home_dir}, params_from_dict(spec.params_cls, {}), out)
    assert manifest["info"]["num_registered"] == 3 and manifest["info"]["unregistered"] == []
    est = {n: np.asarray(T) for n, T in json.loads((out / "panoramas.json").read_text()).items()}
    gt = _gt(home_dir)
    assert np.allclose(est["pano_00"], np.eye(4))
    for n, E in est.items():
        t_cm, r_deg = _errors(E, invert_pose(gt["pano_00"]) @ gt[n])
        assert t_cm <= TOL_CM and r_deg <= TOL_DEG, (n, t_cm, r_deg)
    reg = json.loads((out / "registration.json").read_text())
    assert all(p["source"] == "estimated" for p in reg["panoramas"].values())
    assert all(reg["panoramas"][n]["inliers"] >= 12 for n in ("pano_01", "pano_02"))


def test_given_poses_are_used_without_estimation(home_dir, tmp_path):
    scene = _scene_copy(home_dir, tmp_path / "scene")
    gt = _gt(home_dir)
    (scene / "poses.json").write_text(json.dumps({n: T.tolist() for n, T in gt.items()}))
    shutil.rmtree(scene / "depths")  # given poses need no depth
    spec = load_stage("register")
    out = tmp_path / "register"
    manifest = execute_stage(spec, {"scene": scene}, params_from_dict(spec.params_cls, {}), out)
    assert manifest["info"]["num_given"] == 3 and manifest["info"]["pairs_tried"] == 0
    est = json.loads((out / "panoramas.json").read_text())
    for n, T in gt.items():
        assert np.allclose(est[n], invert_pose(gt["pano_00"]) @ T, atol=1e-8)


@pytest.mark.parametrize("poses, needle", [
    ({"pano_00": np.diag([2.0, 2, 2, 1]).tolist()}, "not rigid"),
    ({"kitchen": np.eye(4).tolist()}, "no such panoramas"),
    ({"pano_00": [[1, 0, 0], [0, 1, 0]]}, "not a 4x4 matrix of numbers"),
    ([1, 2], "expected a JSON object"),
])
def test_bad_poses_file_exits_2_naming_it(home_dir, tmp_path, capsys, poses, needle):
    scene = _scene_copy(home_dir, tmp_path / "scene")
    (scene / "poses.json").write_text(json.dumps(poses))
    out = tmp_path / "register"
    assert register_main(["--scene", str(scene), "--out", str(out)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "poses.json" in lines[0] and needle in lines[0]
    assert not out.exists()


def test_missing_depth_exits_2(home_dir, tmp_path, capsys):
    scene = _scene_copy(home_dir, tmp_path / "scene")
    (scene / "depths" / "pano_01.npy").unlink()
    out = tmp_path / "register"
    assert register_main(["--scene", str(scene), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "pano_01" in err and "depths" in err and not out.exists()


def test_stage_cli_runs_as_a_module(home_dir, tmp_path):
    out = tmp_path / "register"
    proc = subprocess.run([sys.executable, "-m", "stages.register", "--scene", str(tmp_path / "nowhere"), "--out",
                           str(out)], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and "directory not found" in proc.stderr and not out.exists()


@pytest.mark.slow
def test_unrelated_panorama_is_reported_not_placed(home_dir):
    gt = _gt(home_dir)
    names = ["pano_00", "pano_01"]
    rgbs = {n: read_panorama(home_dir / "panoramas" / f"{n}.png") for n in names}
    depths = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in names}
    other = generate_scene(3, "ci-tiny")
    rgbs["other"], depths["other"] = other.render(other.world_from_canonical, HEIGHT, 2 * HEIGHT)
    reg = register_panoramas(["pano_00", "pano_01", "other"], rgbs, depths, options=RegisterOptions(height=HEIGHT))
    assert "other" not in reg.world_from_cam
    reason = reg.panoramas["other"]["reason"]
    assert reg.panoramas["other"]["registered"] is False and "no pair" in reason
    # the reason gives what the pairs across found: how many were tried and the best one's evidence
    assert "2 pair(s) tried with the registered panoramas, the best pano_0" in reason and "floor inliers" in reason
    t_cm, r_deg = _errors(reg.world_from_cam["pano_01"], invert_pose(gt["pano_00"]) @ gt["pano_01"])
    assert t_cm <= TOL_CM and r_deg <= TOL_DEG
    assert not any(p["accepted"] for p in reg.pairs if "other" in (p["a"], p["b"]))


def test_a_blank_panorama_is_reported_as_featureless(home_dir):
    names = ["pano_00", "pano_01"]
    rgbs = {n: read_panorama(home_dir / "panoramas" / f"{n}.png") for n in names}
    depths = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in names}
    rgbs["blank"], depths["blank"] = np.full_like(rgbs["pano_00"], 12), depths["pano_00"]  # a lens cap: dark grey
    reg = register_panoramas(["blank", *names], rgbs, depths, options=RegisterOptions(height=HEIGHT))
    assert sorted(reg.world_from_cam) == names  # the largest group, though "blank" comes first by name
    assert reg.panoramas["blank"]["keypoints"] == 0
    assert min(reg.panoramas[n]["keypoints"] for n in names) >= FEW_KEYPOINTS
    assert reg.panoramas["blank"]["reason"].endswith(
        "; 0 keypoints on the panorama: a blank, dark or blurred image has nothing to match")
    # nothing joins: of the single panoramas, the first by name that has keypoints makes the home, not the blank
    reg = register_panoramas(["blank", "pano_00"], {n: rgbs[n] for n in ("blank", "pano_00")},
                             {n: depths[n] for n in ("blank", "pano_00")}, options=RegisterOptions(height=HEIGHT))
    assert list(reg.world_from_cam) == ["pano_00"] and reg.panoramas["blank"]["registered"] is False


def test_texture_on_a_wall_through_the_camera_backs_no_depth_fit(home_dir):
    """A layout whose wall line passes 3 cm from the camera (a camera in a doorway): any match on that wall is within
    the 5 cm tolerance at any rotation, so two such panoramas, their walls turned 90 deg apart, agreed on a 90 deg
    turn in place (1,203 inliers). Keypoints that near carry no depth; the same texture 2 m away still does."""
    import cv2

    from panoworld.core.conventions import erp_dirs
    from panoworld.geometry.panoramas import erp_pixel_index
    from panoworld.register.pairwise import erp_features, register_pair

    h, w = HEIGHT, 2 * HEIGHT
    rng = np.random.default_rng(0)
    texture = cv2.resize((rng.random((h // 8, w // 8, 3)) * 255).astype(np.uint8), (w, h),
                         interpolation=cv2.INTER_NEAREST)
    x_dir = erp_dirs(h, w, np.float64)[..., 0]
    o = RegisterOptions(height=h)
    feats, depths = [], []
    for name, shift in (("pano_00", 0), ("pano_02", w // 4)):
        rgb = cv2.resize(read_panorama(home_dir / "panoramas" / f"{name}.png"), (w, h))
        depth = cv2.resize(np.load(home_dir / "depths" / f"{name}.npy"), (w, h), interpolation=cv2.INTER_NEAREST)
        x = np.roll(x_dir, shift, axis=1)
        wall = x > 0.1
        rgb[wall] = np.roll(texture, shift, axis=1)[wall]
        depths.append(np.where(wall, 0.03 / np.maximum(x, 1e-6), depth).astype(np.float32))
        feats.append(erp_features(rgb, depths[-1], max_features=o.max_features))
        far = erp_features(rgb, np.where(wall, 2.0 / np.maximum(x, 1e-6), depth), max_features=o.max_features)
        on_wall = wall[erp_pixel_index(far.bearings, h, w)]
        assert on_wall.sum() > 100 and (far.depth[on_wall] > 2.0).mean() > 0.7
        assert not (feats[-1].depth[wall[erp_pixel_index(feats[-1].bearings, h, w)]] > 0).any()
    p = register_pair(*feats, *depths, max_error_m=o.max_error_m, min_inliers=o.min_inliers,
                      refine_height=o.refine_height, refine_iterations=o.refine_iterations)
    assert p.inliers < o.min_inliers and p.i_from_j is None


def test_a_panorama_the_first_pairs_miss_is_joined_across_groups(home_dir, monkeypatch):
    import panoworld.register.solve as solve

    names = ["pano_00", "pano_01", "pano_02"]
    rgbs = {n: read_panorama(home_dir / "panoramas" / f"{n}.png") for n in names}
    depths = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in names}
    monkeypatch.setattr(solve, "candidate_pairs", lambda names, looks, **kw: [(0, 1)])  # a large home's sparse pairs
    reg = register_panoramas(names, rgbs, depths, options=RegisterOptions(height=HEIGHT, all_pairs_up_to=2))
    assert sorted((p["a"], p["b"]) for p in reg.pairs) == [("pano_00", "pano_01"), ("pano_00", "pano_02"),
                                                          ("pano_01", "pano_02")]
    gt = _gt(home_dir)
    for n in names:
        t_cm, r_deg = _errors(reg.world_from_cam[n], invert_pose(gt["pano_00"]) @ gt[n])
        assert t_cm <= TOL_CM and r_deg <= TOL_DEG, (n, t_cm, r_deg)


def test_synth_cli_panoramas_refuses_bad_counts(tmp_path):
    from panoworld.tools.synth.cli import main

    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "x"), "--seed", "1", "--panoramas", "33"])
    assert e.value.code == 2 and not (tmp_path / "x").exists()


def _home_sources(home_dir: Path) -> tuple[list[str], dict, dict, dict]:
    """(names, true poses in the first panorama's frame, panoramas, depths) of a synthetic home."""
    gt = _gt(home_dir)
    names = sorted(gt)
    poses = {n: invert_pose(gt[names[0]]) @ gt[n] for n in names}
    rgbs = {n: read_panorama(home_dir / "panoramas" / f"{n}.png") for n in names}
    depths = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in names}
    return names, poses, rgbs, depths


def test_fused_mesh_reproduces_every_view_and_navmesh_joins_the_rooms(home_dir):
    from panoworld.geometry.raycast import Raycaster
    from panoworld.mesh.fuse import fuse_meshes
    from panoworld.navmesh.home import home_navmesh

    names, poses, rgbs, depths = _home_sources(home_dir)
    mesh, source = fuse_meshes(names, rgbs, depths, poses)
    assert set(np.unique(source)) == {0, 1, 2}
    alone = [fuse_meshes([n], rgbs, depths, {n: poses[n]})[0] for n in names]

    def doubled(parts, n):
        """Fraction of panorama n's pixels whose surface two or more of the parts reproduce (a doubled wall)."""
        ref = depths[n][2::4, 2::4]
        hits = [np.abs(np.log(Raycaster(v, f).render_erp(poses[n], HEIGHT // 4, HEIGHT // 2).distance / ref)) < 0.02
                for v, f in parts]
        return float((np.sum(hits, axis=0) >= 2).mean())

    fused_parts = [(mesh.vertices, mesh.faces[source == k]) for k in range(3)]
    naive_parts = [(m.vertices, m.faces) for m in alone]
    for n in names:
        # Naively concatenated meshes double every surface two panoramas see; the fused one only its seams.
        assert doubled(fused_parts, n) < 0.25 * doubled(naive_parts, n), n
    rc = Raycaster(mesh.vertices, mesh.faces)
    for n in names:
        d = rc.render_erp(poses[n], HEIGHT // 4, HEIGHT // 2).distance
        ref = depths[n][2::4, 2::4]
        assert (np.abs(np.log(d / ref)) < 0.02).mean() > 0.97  # nothing missing ...
        assert (d < 0.98 * ref).mean() < 0.02  # ... and nothing in front of what the panorama saw
    _, on = home_navmesh(mesh, poses)
    assert all(on.values()), on


def test_a_panorama_given_twice_adds_nothing_to_the_fused_mesh_or_navmesh(home_dir):
    from panoworld.mesh.fuse import fuse_meshes
    from panoworld.navmesh.home import home_navmesh

    names, poses, rgbs, depths = _home_sources(home_dir)
    copy = names[1] + "_copy"  # a rotated pose off the origin: its ranges round differently through each way
    mesh, source = fuse_meshes(names, rgbs, depths, poses)
    rgbs[copy], depths[copy], poses[copy] = rgbs[names[1]], depths[names[1]].copy(), poses[names[1]].copy()
    both, source2 = fuse_meshes(names + [copy], rgbs, depths, poses)
    assert not (source2 == len(names)).any()  # the copy keeps no face: the first of the two keeps them all
    np.testing.assert_array_equal(both.faces, mesh.faces)
    _, on = home_navmesh(both, poses)
    assert all(on.values()), on


def test_runner_opens_a_home_and_refuses_a_mixed_layout(home_dir, tmp_path):
    from panoworld.core.errors import PipelineError
    from panoworld.framework.pipeline import Pipeline, open_scene

    scene = open_scene(home_dir, Pipeline.load())
    assert scene.files["panorama"] is None and scene.files["panoramas"] == home_dir / "panoramas"
    assert scene.files["depths"] == home_dir / "depths" and not (home_dir / "artifacts").exists()
    mixed = _scene_copy(home_dir, tmp_path / "mixed")
    shutil.copy(mixed / "panoramas" / "pano_00.png", mixed / "panorama.png")
    with pytest.raises(PipelineError, match="keep one layout") as e:
        open_scene(mixed, Pipeline.load())
    assert e.value.exit_code == 2 and not (mixed / "artifacts").exists()


def test_panoramas_and_pairs_on_several_threads_register_as_one_at_a_time(home_dir, monkeypatch):
    import panoworld.register.solve as solve

    names = ["pano_00", "pano_01", "pano_02"]
    rgbs = {n: read_panorama(home_dir / "panoramas" / f"{n}.png") for n in names}
    depths = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in names}
    seen = []
    out = {}
    for threads in (1, 3):
        monkeypatch.setattr(solve, "pair_threads", lambda n=threads: n)
        order = []
        reg = register_panoramas(names, rgbs, depths, options=RegisterOptions(height=HEIGHT),
                                 progress=lambda a, b, p, order=order: order.append((a, b)))
        seen.append(order)
        out[threads] = (json.dumps(reg.pairs, sort_keys=True), json.dumps(reg.panoramas, sort_keys=True),
                        {n: T.tobytes() for n, T in reg.world_from_cam.items()})
    assert seen[0] == seen[1] == [("pano_00", "pano_01"), ("pano_00", "pano_02"), ("pano_01", "pano_02")]
    assert out[1] == out[3]


def test_a_failing_pair_stops_registration_without_the_pairs_not_started(monkeypatch):
    import time

    import panoworld.register.solve as solve

    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("pair failed")
        time.sleep(1.0)  # long enough for the failure to reach the main thread first, even on a busy machine
        return PairResult(matches=0, inliers=0, i_from_j=None, overlap=0.0, consistency=0.0, residual=float("nan"))

    monkeypatch.setattr(solve, "register_pair", failing)
    monkeypatch.setattr(solve, "pair_threads", lambda: 2)
    rng = np.random.default_rng(0)
    names = [f"p{i}" for i in range(10)]
    rgbs = {n: (rng.random((64, 128, 3)) * 255).astype(np.uint8) for n in names}
    depths = {n: np.full((64, 128), 2.0, np.float32) for n in names}
    with pytest.raises(RuntimeError, match="pair failed"):
        register_panoramas(names, rgbs, depths, options=RegisterOptions(height=64))
    assert len(calls) <= 4  # of 45 pairs: those already running when the first failed, then no more
