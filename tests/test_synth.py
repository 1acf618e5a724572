"""Tests of the procedural scene generator: determinism, exact depth, tracks, on-disk format and bad input."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import cv2
import jsonschema
import numpy as np
import pytest
import trimesh

from panoworld.core.conventions import (
    erp_dirs,
    erp_pixel_from_dir,
    invert_pose,
    points_from_depth,
    quat_wxyz_from_xyzw,
    rotmat_from_quat_wxyz,
    transform_points,
)
from panoworld.tools.synth import Preset, SceneGenerationError, SynthScene, generate_scene, params_for
from panoworld.tools.synth.cli import main

ROOT = Path(__file__).resolve().parents[1]
ARTIFACTS = ROOT / "tests" / "artifacts"


def _digests(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*")) if p.is_file()
    }


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "scene"
    assert main([str(out), "--seed", "7", "--preset", "ci-tiny"]) == 0
    return out


@pytest.fixture(scope="module")
def scene(scene_dir) -> SynthScene:
    return SynthScene.load(scene_dir / "gt")


def test_same_seed_is_byte_identical_and_seeds_differ(scene_dir, tmp_path):
    again = tmp_path / "again"
    assert main([str(again), "--seed", "7", "--preset", "ci-tiny"]) == 0
    a, b = _digests(scene_dir), _digests(again)
    assert a == b
    assert "gt/scene.glb" in a and "panorama.png" in a and "gt/frames/track_01/depth/000007.npy" in a
    other = tmp_path / "other"
    assert main([str(other), "--seed", "8", "--preset", "ci-tiny"]) == 0
    c = _digests(other)
    for name in ("gt/scene.glb", "gt/floorplan.npz", "panorama.png", "depth.npy"):
        assert a[name] != c[name], name
    # The in-memory generator is deterministic too, and independent of any global RNG state.
    np.random.seed(123)
    s1 = generate_scene(3, Preset.CI_TINY)
    np.random.seed(456)
    s2 = generate_scene(3, Preset.CI_TINY)
    assert np.array_equal(s1.vertices, s2.vertices) and np.array_equal(s1.faces, s2.faces)
    assert np.array_equal(s1.tracks[1].world_from_cam, s2.tracks[1].world_from_cam)


def test_contact_sheet_of_eight_seeds():
    tiles = []
    for seed in range(8):
        s = generate_scene(seed, Preset.DEFAULT, frames=2)
        rgb, depth = s.render(s.world_from_canonical, 256, 512)
        assert np.isfinite(depth).all(), f"seed {seed}: rays escaped the building"
        assert rgb.std() > 20, f"seed {seed}: panorama is nearly flat"
        tiles.append(cv2.putText(rgb.copy(), f"seed {seed}", (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 0), 2))
    sheet = np.concatenate([np.concatenate(tiles[k : k + 2], 1) for k in range(0, 8, 2)], 0)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(ARTIFACTS / "synth_contact_sheet.png"), sheet[..., ::-1])


def _plane_distance(scene: SynthScene, pose: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Analytic ray-plane distance of every pixel (H, W) onto the plane of its hit face."""
    h, w = face.shape
    d = erp_dirs(h, w, np.float64) @ pose[:3, :3].T
    n = scene.face_normals[face]
    v0 = scene.vertices.astype(np.float64)[scene.faces[face, 0]]
    return np.einsum("hwk,hwk->hw", n, v0 - pose[:3, 3]) / np.einsum("hwk,hwk->hw", n, d)


def test_depth_is_exact_on_floor_walls_and_ceiling(scene):
    h = 192
    for pose in (scene.world_from_canonical, scene.tracks[1].world_from_cam[-1]):
        _, depth = scene.render(pose, h, 2 * h)
        face = scene.raycaster.render_erp(pose, h, 2 * h).face
        assert (face >= 0).all() and np.isfinite(depth).all()
        analytic = _plane_distance(scene, pose, face)
        for kind in ("floor", "walls", "ceiling"):
            sel = np.isin(face, scene.node_faces(kind=kind))
            assert sel.sum() > 100, kind
            err = np.abs(depth[sel] - analytic[sel])
            assert err.max() < 1e-4, f"{kind}: max depth error {err.max():.2e} m"
        # The floor is the plane y = 0, so its depth is also camera height / sin(latitude) below the horizon.
        floor = np.isin(face, scene.node_faces(kind="floor"))
        d = erp_dirs(h, 2 * h, np.float64) @ pose[:3, :3].T
        assert np.abs(depth[floor] - (-pose[1, 3]) / d[floor][:, 1]).max() < 1e-4


def test_camera_height_from_floor_depth(scene_dir, scene):
    index = json.loads((scene_dir / "gt" / "gt.json").read_text())
    depth = np.load(scene_dir / "depth.npy")
    assert depth.dtype == np.float32 and depth.shape == (128, 256)
    h, w = depth.shape
    face = scene.raycaster.render_erp(scene.world_from_canonical, h, w).face
    below = np.arange(h)[:, None] >= h // 2
    floor = below & np.isin(face, scene.node_faces(kind="floor"))
    assert floor.sum() > 0.2 * h * w / 2
    pts = points_from_depth(depth)
    heights = pts[floor][:, 1]
    assert np.abs(heights - index["camera_height_m"]).max() < 1e-4
    assert index["floor_y_canonical"] == index["camera_height_m"] == scene.tracks[0].camera_height
    assert 1.4 <= index["camera_height_m"] <= 1.7


def test_tracks_are_smooth_upright_and_keep_clearance(scene):
    mesh = trimesh.Trimesh(scene.vertices, scene.faces, process=False)
    p = params_for(Preset.CI_TINY).tracks
    assert len(scene.tracks) == p.n_tracks
    for tr in scene.tracks:
        T = tr.world_from_cam
        assert T.shape == (p.frames, 4, 4)
        _, dist, _ = trimesh.proximity.closest_point_naive(mesh, T[:, :3, 3])
        assert dist.min() >= scene.clearance, f"track comes {dist.min():.3f} m close to the geometry"
        assert np.allclose(T[:, :3, 1], [0.0, 1.0, 0.0]), "cameras must be upright (yaw only)"
        assert np.allclose(T[:, :3, :3] @ T[:, :3, :3].transpose(0, 2, 1), np.eye(3))
        assert np.allclose(T[:, 1, 3], -tr.camera_height)
        steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
        assert np.abs(steps - p.step_m).max() < 0.05 * p.step_m
        yaw = np.unwrap(np.arctan2(T[:, 0, 2], T[:, 2, 2]))
        assert np.abs(np.diff(yaw)).max() < p.step_m / 0.4 + 1e-9


def test_default_tracks_keep_clearance():
    s = generate_scene(5, Preset.DEFAULT)
    mesh = trimesh.Trimesh(s.vertices, s.faces, process=False)
    assert s.meta["n_rooms"] >= 2 and len(s.tracks) == 3
    for tr in s.tracks:
        assert len(tr.world_from_cam) == 121
        _, dist, _ = trimesh.proximity.closest_point_naive(mesh, tr.world_from_cam[::4, :3, 3])
        assert dist.min() >= s.clearance


def test_files_schema_glb_and_tum(scene_dir, scene):
    gt = scene_dir / "gt"
    index = json.loads((gt / "gt.json").read_text())
    schema = json.loads((ROOT / "artifacts_schema" / "gt.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(index, schema, cls=jsonschema.Draft202012Validator)
    loaded = trimesh.load(gt / index["glb"], force="scene")
    assert sum(len(g.faces) for g in loaded.geometry.values()) == index["n_triangles"] == len(scene.faces)
    assert {n.name for n in scene.nodes} == set(loaded.geometry)
    assert np.allclose(np.asarray(index["world_from_canonical"]), scene.tracks[0].world_from_cam[0])
    for k, entry in enumerate(index["tracks"]):
        poses = np.asarray(json.loads((gt / entry["poses"]).read_text())["world_from_cam"])
        assert np.array_equal(poses, scene.tracks[k].world_from_cam)
        tum = np.loadtxt(gt / entry["tum"])
        assert tum.shape == (entry["n_frames"], 8)
        R = rotmat_from_quat_wxyz(quat_wxyz_from_xyzw(tum[:, 4:]))
        assert np.allclose(R, poses[:, :3, :3], atol=1e-7) and np.allclose(tum[:, 1:4], poses[:, :3, 3], atol=1e-8)
        assert np.allclose(np.diff(tum[:, 0]), 1.0 / entry["fps"])
        frames = entry["frames"]
        rgb = cv2.imread(str(gt / frames["rgb"].format(3)))[..., ::-1]
        depth = np.load(gt / frames["depth"].format(3))
        rgb2, depth2 = scene.render_frame(k, 3, frames["height"])
        assert np.array_equal(rgb, rgb2) and np.array_equal(depth, depth2)
    pano = cv2.imread(str(scene_dir / "panorama.png"))[..., ::-1]
    rgb, depth = scene.render(scene.world_from_canonical, *pano.shape[:2])
    assert np.array_equal(pano, rgb) and np.array_equal(np.load(scene_dir / "depth.npy"), depth)


def test_views_are_consistent_and_supersampling_keeps_depth(scene):
    h = 256
    pa, pb = scene.tracks[0].world_from_cam[0], scene.tracks[0].world_from_cam[5]
    rgb_a, depth_a = scene.render(pa, h, 2 * h)
    rgb_b, depth_b = scene.render(pb, h, 2 * h)
    # Warp view B into view A through B's depth; where A sees the same surface the colours must agree.
    pts = transform_points(invert_pose(pa), points_from_depth(depth_b.astype(np.float64), pb))
    u, v = erp_pixel_from_dir(pts, h, 2 * h)
    ia, ja = np.clip(v.astype(int), 0, h - 1), np.clip(u.astype(int), 0, 2 * h - 1)
    same = np.abs(depth_a[ia, ja] - np.linalg.norm(pts, axis=-1)) < 0.01
    assert same.mean() > 0.8
    diff = np.abs(rgb_a[ia, ja].astype(int) - rgb_b.astype(int))[same]
    assert np.median(diff) <= 4, f"median colour difference {np.median(diff)} between views"
    rgb_ss, depth_ss = scene.render(pa, h, 2 * h, supersample=2)
    assert rgb_ss.shape == rgb_a.shape and rgb_ss.dtype == np.uint8
    assert np.array_equal(depth_ss, depth_a)
    assert np.abs(rgb_ss.astype(int) - rgb_a.astype(int)).mean() < 12


def test_render_checks_shapes(scene):
    with pytest.raises(ValueError, match="shape"):
        scene.render(np.eye(3), 64, 128)
    with pytest.raises(ValueError, match="2:1"):
        scene.render(np.eye(4), 64, 100)


def test_bad_input_writes_nothing(tmp_path, monkeypatch, capsys):
    out = tmp_path / "scene"
    with pytest.raises(SystemExit) as e:
        main([str(out), "--seed", "1", "--preset", "huge"])
    assert e.value.code == 2 and "invalid choice" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(out), "--seed", "-1"])
    with pytest.raises(ValueError, match="unknown preset"):
        generate_scene(1, "huge")
    with pytest.raises(ValueError, match="seed"):
        generate_scene(-3, Preset.CI_TINY)
    # A clearance no room can offer: bounded retries with derived seeds, then a clear error and no files.
    p = params_for(Preset.CI_TINY)
    impossible = replace(p, tracks=replace(p.tracks, clearance_m=3.0), max_scene_attempts=3)
    with pytest.raises(SceneGenerationError, match="no walkable scene in 3 attempts"):
        generate_scene(1, Preset.CI_TINY, params=impossible)
    monkeypatch.setattr("panoworld.tools.synth.cli.params_for", lambda *a, **k: impossible)
    assert main([str(out), "--seed", "1", "--preset", "ci-tiny"]) == 1
    assert "no walkable scene" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_dataset_mode_derives_seeds_and_resumes(tmp_path):
    root = tmp_path / "data"
    assert main([str(root), "--seed", "4", "--scenes", "2", "--preset", "ci-tiny", "--frames", "2"]) == 0
    names = sorted(p.name for p in root.iterdir())
    assert names == ["scene_0000", "scene_0001"]
    idx = [json.loads((root / n / "gt" / "gt.json").read_text()) for n in names]
    assert idx[0]["seed"] != idx[1]["seed"] and all(i["tracks"][0]["n_frames"] == 2 for i in idx)
    before = _digests(root)
    assert main([str(root), "--seed", "4", "--scenes", "2", "--preset", "ci-tiny", "--frames", "2"]) == 0
    assert _digests(root) == before
