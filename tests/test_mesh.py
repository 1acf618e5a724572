"""Tests of the ERP mesh: exact vertices, self-render PSNR, closed seam, covered poles, discontinuities, I/O, stage."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from plyfile import PlyData
from scipy.spatial.transform import Rotation

from panoworld.core.conventions import erp_dirs, points_from_depth
from panoworld.geometry.erp_mesh import (
    ErpMesh,
    erp_mesh_from_depth,
    face_stretch,
    load_erp_mesh,
    quads_from_triangles,
    save_erp_mesh,
    save_erp_mesh_glb,
    triangles_from_quads,
)
from panoworld.geometry.raycast import Raycaster
from panoworld.render.metrics import psnr

CAMERA_HEIGHT = 1.45


class BoxRoom:
    """A 4.2 x 2.7 x 5.1 m room (floor CAMERA_HEIGHT below the camera) with an optional box inside, colour = a
    smooth 3D texture of the hit point. render(world_from_cam, H, W) -> (rgb uint8 (H, W, 3), depth (H, W))."""

    def __init__(self, with_box: bool = True):
        room = trimesh.creation.box((4.2, 2.7, 5.1))
        room.apply_translation([0.3, CAMERA_HEIGHT - 1.35, 0.2])
        parts = [room]
        if with_box:
            box = trimesh.creation.box((0.8, 0.9, 0.6))
            box.apply_translation([-0.9, CAMERA_HEIGHT - 0.45, 1.2])
            parts.append(box)
        self.mesh = trimesh.util.concatenate(parts)
        self.rc = Raycaster(self.mesh.vertices, self.mesh.faces)

    @staticmethod
    def texture(p: np.ndarray) -> np.ndarray:
        k = np.array([[1.1, 0.7, -0.9], [-0.6, 1.3, 0.8], [0.9, -1.0, 1.2]]) * 2.0 * np.pi / 1.5
        return np.clip(128.0 + 90.0 * np.sin(p @ k.T + np.array([0.0, 1.0, 2.0])), 0, 255)

    def render(self, world_from_cam: np.ndarray, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
        hits = self.rc.render_erp(world_from_cam, H, W)
        dirs = erp_dirs(H, W, dtype=np.float64) @ world_from_cam[:3, :3].T
        p = world_from_cam[:3, 3] + dirs * hits.distance[..., None]
        rgb = np.rint(self.texture(np.nan_to_num(p))).astype(np.uint8)
        return rgb, hits.distance.astype(np.float32)


@pytest.fixture(scope="module")
def room_64():
    scene = BoxRoom()
    rgb, depth = scene.render(np.eye(4), 64, 128)
    return scene, rgb, depth


def test_vertices_equal_points_from_depth(room_64):
    _, rgb, depth = room_64
    mesh = erp_mesh_from_depth(depth, rgb)
    H, W = depth.shape
    np.testing.assert_allclose(mesh.vertices[: H * W], points_from_depth(depth).reshape(-1, 3), rtol=0, atol=1e-5)
    np.testing.assert_array_equal(mesh.colors[: H * W], rgb.reshape(-1, 3))
    assert mesh.vertices.dtype == np.float32 and mesh.faces.dtype == np.int32 and mesh.colors.dtype == np.uint8
    # Every face faces the camera (counter-clockwise seen from the origin).
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.einsum("fk,fk->f", normals, tri.mean(axis=1)) < 0)


def assert_self_render(rgb: np.ndarray, depth: np.ndarray, min_psnr: float = 40.0) -> None:
    """The mesh of (rgb, depth) ray cast at its own pose (valid faces only) reproduces the panorama and the depth."""
    H, W = depth.shape
    mesh = erp_mesh_from_depth(depth, rgb)
    np.testing.assert_allclose(mesh.vertices[: H * W], points_from_depth(depth).reshape(-1, 3), atol=1e-5)
    valid_mesh = mesh.valid_only()
    rc = Raycaster(valid_mesh.vertices, valid_mesh.faces)
    # Rays through pixel centres pass exactly through vertices, where float32 Embree lets ~1% slip between the
    # incident faces; turn the camera by 1e-4 rad (< 1/100 pixel) so every ray lands inside a face.
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = Rotation.from_rotvec([1e-4, 0.6e-4, 0.3e-4]).as_matrix()
    hits = rc.render_erp(world_from_cam, H, W)
    hit = hits.face >= 0
    # Misses only on the rim of depth edges, where a ray may pass just outside the last valid face.
    rim = np.zeros(len(mesh.vertices), bool)
    rim[mesh.faces[~mesh.face_valid].ravel()] = True
    assert hit[~rim[: H * W].reshape(H, W)].all() and hit.mean() > 0.97
    rendered = np.clip(rc.interpolate(hits, valid_mesh.colors.astype(np.float64)), 0, 255)
    assert psnr(rendered, rgb.astype(np.float64), mask=hit, data_range=255.0) >= min_psnr
    np.testing.assert_allclose(hits.distance[hit], depth[hit], rtol=3e-3)


def test_self_render_reproduces_panorama():
    assert_self_render(*BoxRoom().render(np.eye(4), 128, 256))


def test_self_render_synth_scene(synth_scene):
    import cv2

    rgb = cv2.cvtColor(cv2.imread(str(synth_scene / "panorama.png")), cv2.COLOR_BGR2RGB)
    assert_self_render(rgb, np.load(synth_scene / "depth.npy"))


def test_seam_closed_and_poles_covered(room_64):
    _, rgb, depth = room_64
    mesh = erp_mesh_from_depth(depth, rgb)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    boundary = trimesh.grouping.group_rows(tm.edges_sorted, require_count=1)
    assert len(boundary) == 0
    assert tm.is_watertight and tm.is_winding_consistent
    valid = mesh.valid_only()
    hits = Raycaster(valid.vertices, valid.faces).cast(np.zeros((2, 3)), np.array([[0.0, -1, 0], [0, 1, 0]]))
    np.testing.assert_allclose(hits.distance, [2.7 - CAMERA_HEIGHT, CAMERA_HEIGHT], rtol=1e-5)


def test_discontinuities_flagged_only_at_depth_edges():
    rgb, depth = BoxRoom(with_box=False).render(np.eye(4), 96, 192)
    assert erp_mesh_from_depth(depth, rgb).face_valid.all()  # walls, floor, ceiling at every angle: no false flags
    rgb, depth = BoxRoom(with_box=True).render(np.eye(4), 96, 192)
    mesh = erp_mesh_from_depth(depth, rgb)
    stretched = mesh.faces[~mesh.face_valid]
    assert len(stretched) > 0
    d = np.linalg.norm(mesh.vertices[stretched], axis=-1)
    assert np.all(d.max(axis=1) / d.min(axis=1) > 1.3)  # each joins the box to the wall behind it


@pytest.mark.parametrize("ratio", [1.5, 3.0, 12.0])
def test_grid_stretch_matches_reference(room_64, ratio):
    _, rgb, depth = room_64
    mesh = erp_mesh_from_depth(depth, rgb, max_edge_ratio=ratio, stride=2)
    dist = np.linalg.norm(mesh.vertices.astype(np.float64), axis=1)
    dirs = mesh.vertices / np.maximum(dist, 1e-30)[:, None]
    ref = face_stretch(mesh.vertices, dirs.astype(np.float32), dist.astype(np.float32), mesh.faces)
    assert 0 < (ref > ratio).sum() < len(ref)
    tie = np.abs(ref - ratio) < 1e-4 * ratio
    np.testing.assert_array_equal(mesh.face_valid[~tie], ref[~tie] <= ratio)


def test_invalid_depth_is_not_meshed(room_64):
    _, rgb, depth = room_64
    H, W = depth.shape
    bad = depth.copy()
    bad[10:14, 20:30] = np.nan
    bad[30:33, 100:104] = np.inf
    bad[40:42, 0:3] = 0.0
    mask = np.ones_like(depth, bool)
    mask[50:52, 60:62] = False
    mesh = erp_mesh_from_depth(bad, rgb, mask)
    assert np.isfinite(mesh.vertices).all()
    invalid = ~(np.isfinite(bad) & (bad > 0) & mask).reshape(-1)
    used = np.zeros(len(mesh.vertices), bool)
    used[mesh.faces.ravel()] = True
    assert not np.any(used[: H * W] & invalid)
    assert used[: H * W][~invalid].all()


def test_stride_keeps_exact_points(room_64):
    _, rgb, depth = room_64
    mesh = erp_mesh_from_depth(depth, rgb, stride=4)
    pts = points_from_depth(depth)[2::4, 2::4]
    np.testing.assert_allclose(mesh.vertices[: pts.shape[0] * pts.shape[1]], pts.reshape(-1, 3), atol=1e-5)
    assert len(mesh.faces) == 2 * (16 - 1) * 32 + 2 * 32
    np.testing.assert_allclose(mesh.colors[0], rgb[:4, :4].reshape(-1, 3).mean(axis=0), atol=0.51)


def test_quads_round_trip_any_triangle_list():
    # Grid pairs, a fan, lone triangles, pairs of unlike validity and empty triangles (a, c, c) next to (a, b, c).
    faces = np.array([[0, 5, 6], [0, 6, 1], [1, 6, 7], [1, 7, 2], [9, 0, 1], [9, 1, 2], [9, 2, 3], [9, 3, 4],
                      [4, 8, 3], [2, 3, 3], [2, 3, 8], [2, 8, 8], [5, 6, 7], [5, 7, 8], [3, 4, 5]])
    valid = np.ones(len(faces), bool)
    valid[[12, 14]] = False  # (5, 6, 7) and (5, 7, 8) differ: two lone triangles
    quads, qvalid = quads_from_triangles(faces, valid)
    assert [list(q) for q in quads[:4]] == [[0, 5, 6, 1], [1, 6, 7, 2], [9, 0, 1, 2], [9, 2, 3, 4]]
    assert len(quads) == 10 and [list(q) for q in quads[4:7]] == [[4, 8, 3, 3], [2, 3, 3, 8], [2, 8, 8, 8]]
    back, bvalid = triangles_from_quads(quads, qvalid)
    np.testing.assert_array_equal(back, faces)
    np.testing.assert_array_equal(bvalid, valid)


def _triangle_set(faces: np.ndarray) -> np.ndarray:
    """Triangles (F, 3) each rolled to start at its smallest index (orientation kept), rows sorted."""
    f = np.asarray(faces)
    rolled = np.stack([np.roll(f, -k, axis=1) for k in range(3)], axis=1)[np.arange(len(f)), np.argmin(f, axis=1)]
    return rolled[np.lexsort(rolled.T[::-1])]


def test_ply_roundtrip_and_glb(room_64, tmp_path):
    _, rgb, depth = room_64
    mesh = erp_mesh_from_depth(depth, rgb)
    mesh.face_valid[::7] = False
    save_erp_mesh(mesh, tmp_path / "mesh.ply")
    for source in (tmp_path / "mesh.ply", tmp_path):
        back = load_erp_mesh(source)
        for name in ("vertices", "faces", "colors", "face_valid"):
            np.testing.assert_array_equal(getattr(back, name), getattr(mesh, name))
    # Any viewer's PLY reader sees the same triangles (the file's quads split, a lone triangle's empty half aside).
    tm = trimesh.load(tmp_path / "mesh.ply", process=False)
    seen = tm.faces[(tm.faces[:, 0] != tm.faces[:, 1]) & (tm.faces[:, 1] != tm.faces[:, 2]) & (tm.faces[:, 2] != tm.faces[:, 0])]
    assert len(seen) == len(mesh.faces) and len(tm.faces) < len(mesh.faces) * 1.3
    np.testing.assert_array_equal(_triangle_set(seen), _triangle_set(mesh.faces))
    np.testing.assert_array_equal(tm.vertices, mesh.vertices)
    assert "pixel" not in PlyData.read(str(tmp_path / "mesh.ply"))["vertex"].data.dtype.names  # every vertex written
    # Pixels without depth leave vertices out: `pixel` restores the grid layout.
    holed = depth.copy()
    holed[20:30, 40:60] = 0.0
    sparse = erp_mesh_from_depth(holed, rgb)
    save_erp_mesh(sparse, tmp_path / "sparse.ply")
    back = load_erp_mesh(tmp_path / "sparse.ply")
    used = np.unique(sparse.faces)
    assert len(PlyData.read(str(tmp_path / "sparse.ply"))["vertex"].data["pixel"]) == len(used) < len(sparse.vertices)
    for name in ("vertices", "faces", "face_valid"):
        np.testing.assert_array_equal(getattr(back, name), getattr(sparse, name))
    np.testing.assert_array_equal(back.colors[used], sparse.colors[used])
    box = trimesh.creation.box()
    box.export(tmp_path / "box.ply")  # any triangle PLY: no colours, no valid property
    other = load_erp_mesh(tmp_path / "box.ply")
    np.testing.assert_array_equal(other.faces, box.faces)
    assert other.face_valid.all() and other.colors.shape == (8, 3)
    save_erp_mesh_glb(mesh, tmp_path / "mesh.glb")
    glb = trimesh.load(tmp_path / "mesh.glb", force="mesh")
    assert len(glb.faces) == int(mesh.face_valid.sum())
    assert glb.vertices[:, 1].min() == pytest.approx(-CAMERA_HEIGHT, abs=1e-4)  # glTF is Y-up: floor below
    assert glb.vertices[:, 1].max() == pytest.approx(2.7 - CAMERA_HEIGHT, abs=1e-4)


def test_erp_mesh_checks_shapes(room_64):
    _, rgb, depth = room_64
    with pytest.raises(ValueError, match="rgb.shape"):
        erp_mesh_from_depth(depth, rgb[:, :-2])
    with pytest.raises(ValueError, match="2:1"):
        erp_mesh_from_depth(depth[:, :100], rgb[:, :100])
    with pytest.raises(ValueError, match="faces.shape"):
        ErpMesh(np.zeros((3, 3), np.float32), np.zeros((1, 4), np.int32), np.zeros((3, 3), np.uint8), np.ones(1, bool))


def _write_scene(tmp_path, rgb, depth):
    import cv2

    cv2.imwrite(str(tmp_path / "panorama.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    np.save(tmp_path / "depth.npy", depth)


def test_mesh_stage_cli(room_64, tmp_path):
    _, rgb, depth = room_64
    _write_scene(tmp_path, rgb, depth)
    run = lambda *a: subprocess.run([sys.executable, "-m", *a], capture_output=True, text=True)
    r = run("stages.depth", "--panorama", str(tmp_path / "panorama.png"), "--depth", str(tmp_path / "depth.npy"),
            "--out", str(tmp_path / "depth"))
    assert r.returncode == 0, r.stderr
    r = run("stages.mesh", "--depth", str(tmp_path / "depth"), "--out", str(tmp_path / "mesh"))
    assert r.returncode == 0, r.stderr
    manifest = json.loads((tmp_path / "mesh" / "manifest.json").read_text())
    assert "mesh.ply" in manifest["files"] and "mesh.glb" not in manifest["files"]  # one mesh file by default
    mesh = load_erp_mesh(tmp_path / "mesh")
    assert manifest["info"]["num_faces"] == len(mesh.faces)
    assert manifest["info"]["num_faces_stretched"] == int((~mesh.face_valid).sum()) > 0
    np.testing.assert_allclose(mesh.vertices[: depth.size], points_from_depth(depth).reshape(-1, 3), atol=1e-5)
    r = run("stages.mesh", "--depth", str(tmp_path / "depth"), "--out", str(tmp_path / "mesh_drop"),
            "--discontinuity", "drop", "--stride", "2", "--glb", "true")
    assert r.returncode == 0, r.stderr
    dropped = load_erp_mesh(tmp_path / "mesh_drop")
    assert dropped.face_valid.all() and (tmp_path / "mesh_drop" / "mesh.glb").is_file()  # glTF on request
    r = run("stages.mesh", "--depth", str(tmp_path / "nowhere"), "--out", str(tmp_path / "mesh_bad"))
    assert r.returncode == 2 and "run the stage that produces it" in r.stderr


def test_compact_faces_is_np_unique_with_inverse():
    """compact_faces (mark + prefix sum) equals np.unique(faces, return_inverse=True), unused vertices included."""
    from panoworld.geometry.erp_mesh import compact_faces

    rng = np.random.default_rng(3)
    faces = rng.integers(0, 500, (800, 3))
    faces[faces % 7 == 0] = 11  # vertices nobody references, one referenced many times
    used, inv = np.unique(faces, return_inverse=True)
    got_used, got_faces = compact_faces(faces, 520)
    np.testing.assert_array_equal(got_used, used)
    np.testing.assert_array_equal(got_faces, inv.reshape(-1, 3))
    np.testing.assert_array_equal(got_used[got_faces], faces)
    assert got_faces.dtype == np.intp
