"""A panorama taken off level: gravity read from its vertical lines, the depth stage levelling it (checked by the
depth's floor), given poses and the runner's note following."""

from __future__ import annotations

import json

import numpy as np
import pytest

from panoworld.geometry.level import angle_deg, floor_down, levelled, levelled_depth
from panoworld.geometry.verticals import gravity_from_image
from tests.test_register_level import layout_home, tilt_from_level

UP = np.array([0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def layout():
    """The layout home of test_register_level at 384 rows: (names, poses, panoramas, layout depths)."""
    return layout_home(384)


def test_gravity_is_read_from_the_vertical_lines(layout):
    """Each panorama of a synthetic home, level and turned by 2, 5 and 20 deg about a horizontal axis: the gravity
    its lines give is within 0.25 deg of the truth (beyond REFINE_DEG found again on the panorama levelled by the
    first reading); a panorama under MIN_ROWS rows is not read."""
    import cv2

    _, _, rgbs, _ = layout
    for k, rgb in enumerate(rgbs.values()):
        for deg, az in ((0.0, 0.0), (2.0, 0.3 + k), (5.0, 2.5 + k), (20.0, 4.0 + k)):
            X = tilt_from_level(deg, az)  # level camera -> tilted camera
            g = gravity_from_image(levelled(rgb, X))
            assert g is not None and g.verticals >= 20
            assert angle_deg(g.down_cam, X @ UP) < 0.25, (k, deg, g.tilt_deg)
    small = cv2.resize(next(iter(rgbs.values())), (384, 192), interpolation=cv2.INTER_AREA)
    assert gravity_from_image(small) is None


def _scene(tmp_path, rgb, depth, name="scene"):
    import cv2

    scene = tmp_path / name
    scene.mkdir()
    cv2.imwrite(str(scene / "panorama.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    np.save(scene / "depth.npy", depth.astype(np.float32))
    return scene


def _depth_stage(scene, out, **params):
    from stages import depth as stage

    out.mkdir()
    info = stage.run({"panorama": scene / "panorama.png", "depth": scene / "depth.npy"}, stage.Params(**params), out)
    return info, np.load(out / "depth.npy")


def test_the_depth_stage_levels_a_panorama_taken_off_level(layout, tmp_path):
    """One panorama and its depth taken 3 deg off level: the depth stage levels both (gravity within 0.1 deg, its
    floor then level within 0.1 deg, panorama and depth as the level capture's: PSNR > 30 dB away from the poles,
    depth within 0.1 % at the median), records the rotation and says so; the level capture is left as taken (the
    same bytes as with level=false); a tilted photo over a depth drawn level is left as taken, with a note saying
    why."""
    import cv2

    _, _, rgbs, depths = layout
    rgb, depth = rgbs["pano_01"], depths["pano_01"]
    X = tilt_from_level(3.0, 1.3)
    info, out = _depth_stage(_scene(tmp_path, levelled(rgb, X), levelled_depth(depth, X), "tilted"),
                             tmp_path / "out_tilted")
    lev = info["level"]
    assert abs(lev["tilt_deg"] - 3.0) < 0.1 and lev["floor_residual_deg"] < 0.5
    R = np.asarray(lev["level_from_cam"])
    assert angle_deg(R.T @ UP, X @ UP) < 0.1  # the levelled camera's down is gravity
    assert angle_deg(floor_down(out), UP) < 0.1
    assert any(f"taken {lev['tilt_deg']:.1f}° from level" in d and "levelled" in d for d in info["decisions"])

    info, level_out = _depth_stage(_scene(tmp_path, rgb, depth, "level"), tmp_path / "out_level")
    assert "level_from_cam" not in info["level"] and info["level"]["image_tilt_deg"] < 0.3
    a, b = (cv2.imread(str(tmp_path / d / "panorama.png")).astype(np.float64) for d in ("out_tilted", "out_level"))
    rows = slice(a.shape[0] // 8, a.shape[0] - a.shape[0] // 8)
    assert 10 * np.log10(255.0**2 / np.mean((a[rows] - b[rows]) ** 2)) > 30.0
    both = (out > 0) & (level_out > 0)
    assert np.median(np.abs(out[both] - level_out[both]) / level_out[both]) < 1e-3
    _, out_as_taken = _depth_stage(tmp_path / "level", tmp_path / "out_level_off", level=False)
    assert np.array_equal(level_out, out_as_taken)
    for f in ("panorama.png", "valid.png"):
        assert (tmp_path / "out_level" / f).read_bytes() == (tmp_path / "out_level_off" / f).read_bytes()

    for deg in (3.0, 30.0):  # 30: the floor, levelled by the lines, is too steep to be seen as one; as taken it is level
        tilted = levelled(rgb, tilt_from_level(deg, 1.3))
        info, _ = _depth_stage(_scene(tmp_path, tilted, depth, f"photo_only_{deg}"), tmp_path / f"out_photo_only_{deg}")
        assert "level_from_cam" not in info["level"] and info["level"]["floor_residual_deg"] > 1.0
        assert any("left as taken" in d for d in info["decisions"])


def test_a_home_taken_off_level_is_built_level_and_its_given_poses_follow(home_dir, tmp_path):
    """A home whose pano_01 was taken 2 deg off level, through `runner.py run --until register`: the depth stage
    levels it, registration then has nothing to level, the note under the table and `status` name it; with a
    poses.json of the cameras as taken, pano_01's registered pose is its levelled camera's (the level truth within
    0.2 deg), and `runner.py eval`'s registration scores against true poses of the cameras as taken compare it as
    levelled; with depth.level=false the registration levels it for itself and says so."""
    import shutil

    import cv2

    from panoworld.core.conventions import invert_pose, pose_from_rt
    from panoworld.tools.eval.home import registration_metrics
    from tests.test_runner import cli

    scene = tmp_path / "home"
    shutil.copytree(home_dir, scene, ignore=shutil.ignore_patterns("gt"))
    X = tilt_from_level(2.0, 0.7)
    rgb = cv2.imread(str(scene / "panoramas" / "pano_01.png"))
    cv2.imwrite(str(scene / "panoramas" / "pano_01.png"), levelled(rgb, X))
    depth = np.load(scene / "depths" / "pano_01.npy")
    np.save(scene / "depths" / "pano_01.npy", levelled_depth(depth, X))

    out = cli("run", str(scene), "--until", "register")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "note: taken off level: pano_01 2.0°; levelled, the scene is built level" in out.stdout
    depth_info = json.loads((scene / "artifacts" / "depth" / "manifest.json").read_text())["info"]
    assert list(n for n, i in depth_info["home"]["panoramas"].items() if "level_from_cam" in i["level"]) == ["pano_01"]
    info = json.loads((scene / "artifacts" / "register" / "manifest.json").read_text())["info"]
    assert info["num_registered"] == 3 and "levelled_tilt_deg" not in info
    assert "taken off level: pano_01" in cli("status", str(scene)).stdout

    truth = json.loads((home_dir / "gt" / "poses.json").read_text())
    truth = {n: np.asarray(T, np.float64) for n, T in truth.items()}
    as_taken = dict(truth, pano_01=truth["pano_01"] @ invert_pose(pose_from_rt(X, np.zeros(3))))
    (scene / "gt").mkdir()  # the true poses of the cameras as taken: the eval scores the levelled one against its own
    (scene / "gt" / "poses.json").write_text(json.dumps({n: T.tolist() for n, T in as_taken.items()}))
    scores = registration_metrics(scene / "artifacts" / "register", scene)
    assert scores["registered"] == 3 and scores["misplaced"] == 0 and scores["rot_deg_max"] < 0.5, scores
    (scene / "poses.json").write_text(json.dumps({n: T.tolist() for n, T in as_taken.items()}))
    out = cli("run", str(scene), "--until", "register")
    assert out.returncode == 0, out.stderr[-2000:]
    placed = json.loads((scene / "artifacts" / "register" / "panoramas.json").read_text())
    placed = {n: np.asarray(T) for n, T in placed.items()}
    rel = invert_pose(placed["pano_00"]) @ placed["pano_01"]
    rel_truth = invert_pose(truth["pano_00"]) @ truth["pano_01"]
    turn = rel[:3, :3].T @ rel_truth[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(turn) - 1) / 2, -1, 1))) < 0.2
    assert np.allclose(rel[:3, 3], rel_truth[:3, 3], atol=1e-6)

    (scene / "poses.json").unlink()
    out = cli("run", str(scene), "--until", "register", "--set", "depth.level=false")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "note: home: taken with the camera not level: pano_01 2.0°; levelled for registration" in out.stdout
    assert "taken off level" not in out.stdout


def test_a_levelled_depth_keeps_its_planes_flat_and_its_edges_sharp():
    """A box room's depth turned 2 deg: levelled_depth keeps the floor a plane (rms off it under 0.1 mm, nearest
    sampling leaves ~3 mm terraces) and never blends across a depth edge (every sample is one of the surfaces)."""
    import cv2

    from panoworld.core.conventions import erp_dirs64

    dirs = erp_dirs64(256, 512)
    t = np.full(dirs.shape[:2], np.inf)
    for axis, at in ((1, 1.5), (1, -1.2), (0, 3.0), (0, -3.5), (2, 3.2), (2, -3.0)):
        with np.errstate(divide="ignore"):
            hit = at / dirs[..., axis]
        t = np.where((hit > 0) & (hit < t), hit, t)
    depth = t.astype(np.float32)
    depth[100:110, 200:230] = 0.0  # a dropout: no depth made up beside it
    R = cv2.Rodrigues(np.array([0.3, 0.0, 0.9]) / np.linalg.norm([0.3, 0.0, 0.9]) * np.radians(2.0))[0]

    def floor_rms(d):
        sel = (dirs[..., 1] > np.sin(np.radians(30))) & (dirs[..., 1] < np.sin(np.radians(60))) & (d > 0)
        pts = dirs[sel] * d[sel][:, None]
        return float(np.sqrt(np.mean(((pts - pts.mean(0)) @ np.linalg.svd(pts - pts.mean(0), full_matrices=False)[2][2]) ** 2)))

    out, nearest = levelled_depth(depth, R), levelled(depth, R, nearest=True)
    assert floor_rms(out) < 1e-4 < 1e-3 < floor_rms(nearest)
    assert np.array_equal(out > 0, nearest > 0)
    # a pixel between two surfaces takes one of them: within 10 % of its nearest sample's depth
    both = (out > 0) & (nearest > 0)
    assert np.all(np.abs(out[both] - nearest[both]) <= 0.1 * nearest[both] + 1e-6)
