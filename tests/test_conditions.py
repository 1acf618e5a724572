"""Conditions: silhouette splitting, ground-truth disocclusion, warp quality on synthetic scenes, storage and the stage."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from panoworld.conditions.warp import (
    MeshReference,
    render_conditions,
    split_stretched_faces,
    true_disocclusion,
    warp_quality,
    write_conditions,
)
from panoworld.core.conventions import invert_pose, points_from_depth, pose_from_rt, transform_points
from panoworld.framework.stage import StageInputError, execute_stage, load_stage
from panoworld.framework.stage_params import params_from_dict
from panoworld.geometry.erp_mesh import erp_mesh_from_depth, save_erp_mesh
from panoworld.geometry.raycast import Raycaster
from panoworld.io.conditions import load_conditions
from panoworld.io.trajectory import write_trajectory
from panoworld.render.metrics import psnr
from panoworld.render.rasterize import ErpRasterizer

H, W = 48, 96


def room_with_objects() -> trimesh.Trimesh:
    """A closed 5 x 2.8 x 6 m room with two boxes in it (depth discontinuities in every direction)."""
    parts = [trimesh.creation.box(extents=[5.0, 2.8, 6.0])]
    for centre, size in (([1.0, 0.4, 1.5], [0.8, 1.2, 0.6]), ([-1.2, 0.6, -1.0], [0.5, 0.8, 1.0])):
        parts.append(trimesh.creation.box(extents=size).apply_translation(centre))
    return trimesh.util.concatenate(parts)


def gt_render(scene: trimesh.Trimesh, pose: np.ndarray, h: int, w: int):
    """Exact depth (H, W) and a position-coded colour (H, W, 3) uint8 of the scene at pose."""
    rc = Raycaster(scene.vertices, scene.faces)
    hits = rc.render_erp(pose, h, w)
    pts = transform_points(pose, points_from_depth(hits.distance.astype(np.float64)))
    rgb = (127.5 + 127.5 * np.sin(pts * [2.1, 1.7, 2.9])).astype(np.uint8)
    return hits.distance, rgb


@pytest.fixture(scope="module")
def room_mesh():
    scene = room_with_objects()
    depth, rgb = gt_render(scene, np.eye(4), 256, 512)
    return scene, depth, rgb, erp_mesh_from_depth(depth, rgb)


def test_split_keeps_the_source_view_and_stays_watertight(room_mesh):
    _, depth, rgb, mesh = room_mesh
    split = split_stretched_faces(mesh)
    assert len(split.faces) > len(mesh.faces) and (~split.face_valid).any()
    # From the source pose the curtains are edge-on: the split mesh reproduces the panorama exactly.
    src = ErpRasterizer(split.vertices, split.faces, split.colors, split.face_valid).render(np.eye(4), 256, 512)
    assert src.mask.all()
    np.testing.assert_array_equal(src.rgb, rgb)
    np.testing.assert_allclose(src.depth, depth, rtol=1e-5)
    # From novel poses the cut edges leave no cracks: no more uncovered pixels than the unsplit mesh.
    for t in ([0.4, 0.0, 0.0], [-0.2, 0.3, 0.4]):
        pose = pose_from_rt(np.eye(3), t)
        a = ErpRasterizer(mesh.vertices, mesh.faces).render_erp(pose, 256, 512)
        b = ErpRasterizer(split.vertices, split.faces).render_erp(pose, 256, 512)
        assert (b.face < 0).sum() <= (a.face < 0).sum()


def test_true_disocclusion_matches_an_independent_ray_tracer(room_mesh):
    scene, _, _, _ = room_mesh
    tgt = pose_from_rt(np.eye(3), [0.5, 0.1, -0.3])
    h = 48
    hole = true_disocclusion(MeshReference(scene.vertices, scene.faces), np.eye(4), tgt, h, 2 * h)
    # Oracle: brute-force ray / triangle intersection over all faces (Moller-Trumbore in numpy), not our Embree caster.
    tri = scene.vertices[scene.faces].astype(np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]

    def first_hit(origins, dirs):
        p = np.cross(dirs[:, None], e2[None])
        det = np.einsum("fk,nfk->nf", e1, p)
        s = origins[:, None] - tri[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.einsum("nfk,nfk->nf", s, p) / det
            q = np.cross(s, e1[None])
            v = np.einsum("nk,nfk->nf", dirs, q) / det
            t = np.einsum("fk,nfk->nf", e2, q) / det
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        return np.where(ok, t, np.inf).min(axis=1)

    dirs = transform_points(tgt, points_from_depth(np.ones((h, 2 * h)))).reshape(-1, 3) - tgt[:3, 3]
    pts = tgt[:3, 3] + dirs * first_hit(np.repeat(tgt[None, :3, 3], len(dirs), 0), dirs)[:, None]
    dist = np.linalg.norm(pts, axis=1)
    hidden = (first_hit(np.zeros_like(pts), pts / dist[:, None]) < dist * (1 - 0.02)).reshape(h, 2 * h)
    assert 0.005 < hidden.mean() < 0.3
    assert (hole == hidden).mean() > 0.995  # rays grazing an edge may differ between the two tracers
    assert not true_disocclusion(MeshReference(scene.vertices, scene.faces), tgt, tgt, h, 2 * h).any()


def test_true_disocclusion_is_the_shadow_of_an_occluder():
    """A 1 m cube 2 m in front of the source camera, a wall at z = 5: a camera 0.7 m to the side sees exactly two
    regions the source cannot see: the wall in the cube's shadow (cast from the source) and the cube's +x side."""
    room = trimesh.creation.box(extents=(12.0, 12.0, 10.0))  # inner walls at |x|, |y| = 6, z = +-5
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.apply_translation((0.0, 0.0, 2.5))  # |x|, |y| <= 0.5, 2 <= z <= 3
    mesh = trimesh.util.concatenate([room, cube])
    box = MeshReference(mesh.vertices, mesh.faces)
    pose = np.eye(4)
    pose[0, 3] = 0.7
    h = 96
    hole = true_disocclusion(box, np.eye(4), pose, h, 2 * h, 0.015)
    pts = points_from_depth(box.depth(pose, h, 2 * h), pose)
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    wall = np.abs(z - 5.0) < 1e-4
    side = (np.abs(x - 0.5) < 1e-4) & (z > 2.0) & (z < 3.0)
    # The source's shadow of the cube's front face (|x|, |y| <= 0.5 at z = 2) on the wall z = 5 is 5 / 2 times larger.
    expected = (wall & (np.maximum(np.abs(x), np.abs(y)) < 1.25)) | side
    # Within a pixel or the tolerance of an edge either answer is right.
    edge = (wall & (np.abs(np.maximum(np.abs(x), np.abs(y)) - 1.25) < 0.1)) | (side & (z < 2.1))
    assert (wall & expected).sum() > 20 and side.sum() > 5
    assert np.array_equal(hole & ~edge, expected & ~edge)
    assert not true_disocclusion(box, np.eye(4), np.eye(4), h, 2 * h, 0.015).any()


def test_warp_iou_and_psnr_on_a_room(room_mesh):
    scene, depth, _, mesh = room_mesh
    tgt = pose_from_rt(np.eye(3), [0.5, 0.1, -0.3])
    d1, rgb1 = gt_render(scene, tgt, 256, 512)
    hole = true_disocclusion(MeshReference(scene.vertices, scene.faces), np.eye(4), tgt, 256, 512)
    (plain,) = render_conditions(mesh, tgt[None], 256, 512, split_silhouettes=False)
    (split,) = render_conditions(mesh, tgt[None], 256, 512)
    q_plain, q_split = warp_quality(plain, rgb1, hole), warp_quality(split, rgb1, hole)
    assert q_split.iou > q_plain.iou + 0.02 and q_split.iou > 0.85
    assert q_split.psnr > 35.0  # a smooth position-coded texture
    # Hole pixels are black and have no depth; valid ones carry the warped depth of the right surface.
    assert (split.rgb[~split.mask] == 0).all() and (split.depth[~split.mask] == 0).all()
    ok = split.mask & ~hole
    assert np.median(np.abs(split.depth[ok] - d1[ok]) / d1[ok]) < 0.01


@pytest.mark.slow
def test_warp_quality_on_synthetic_scenes():
    """The issue's target: 0.5 m from the source, PSNR >= 28 dB on valid & visible pixels and IoU >= 0.75 of the
    'must be generated' sets (mask == 0 vs true disocclusion), averaged over 10 seeds at 512 x 1024."""
    from panoworld.tools.synth import generate_scene

    h = 512
    scores = []
    for seed in range(10):
        scene = generate_scene(seed, "default")
        poses = scene.tracks[0].world_from_cam
        k = int(np.argmax(np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1) >= 0.5))
        rgb0, d0 = scene.render(poses[0], h, 2 * h)
        rgb1, d1 = scene.render(poses[k], h, 2 * h)
        rel = invert_pose(poses[0]) @ poses[k]
        (frame,) = render_conditions(erp_mesh_from_depth(d0, rgb0), rel[None], h, 2 * h)
        hole = true_disocclusion(MeshReference(scene.vertices, scene.faces), poses[0], poses[k], h, 2 * h)
        q = warp_quality(frame, rgb1, hole)
        scores.append((q.psnr, q.iou))
    psnr, iou = np.asarray(scores).T
    assert psnr.mean() >= 28.0 and psnr.min() >= 27.0, psnr
    assert iou.mean() >= 0.75 and iou.min() >= 0.4, iou


def test_write_and_load_roundtrip(room_mesh, tmp_path):
    _, _, _, mesh = room_mesh
    poses = np.stack([pose_from_rt(np.eye(3), [0.1 * k, 0.0, 0.05 * k]) for k in range(3)])
    frames = render_conditions(mesh, poses, H, W)
    info = write_conditions(tmp_path / "c", frames, poses, preview_mp4=True)
    assert info["num_frames"] == 3 and (info["height"], info["width"]) == (H, W)
    doc = json.loads((tmp_path / "c/conditions.json").read_text())
    assert doc["frames"][2] == {"rgb": "rgb/000002.png", "mask": "mask/000002.png", "depth": "depth/000002.png"}
    assert doc["depth_scale"] == 0.001 and np.allclose(doc["poses"], poses)
    assert (tmp_path / "c/preview.mp4").stat().st_size > 0
    c = load_conditions(tmp_path / "c")
    assert len(c) == 3 and c.rgb.shape == (3, H, W, 3) and c.mask.shape == (3, H, W)
    np.testing.assert_array_equal(np.asarray(c.rgb), np.stack([f.rgb for f in frames]))
    np.testing.assert_array_equal(c.mask[1:], np.stack([f.mask for f in frames[1:]]))
    assert c.mask.dtype == bool and c.depth[0].dtype == np.float32
    for k, f in enumerate(frames):
        assert np.abs(c.depth[k] - f.depth).max() <= 0.0005 + 1e-6
        assert (c.depth[k][~f.mask] == 0).all()
    np.testing.assert_allclose(c.poses, poses)
    for ahead in (1, 2, 5):  # read ahead by a thread: the same frames, in order
        got = list(c.iter_frames(ahead=ahead))
        assert len(got) == 3
        for k, (rgb, mask, depth) in enumerate(got):
            for a, b in ((rgb, c.rgb[k]), (mask, c.mask[k]), (depth, c.depth[k])):
                np.testing.assert_array_equal(a, b)
    # Without depth: no depth files, and the reader says so.
    write_conditions(tmp_path / "n", frames, poses, write_depth=False)
    assert not (tmp_path / "n/depth").exists() and load_conditions(tmp_path / "n/conditions.json").depth is None
    assert all(d is None for _, _, d in load_conditions(tmp_path / "n").iter_frames())


def test_writer_and_reader_reject_bad_input(room_mesh, tmp_path):
    _, _, _, mesh = room_mesh
    poses = np.stack([np.eye(4)] * 2)
    frames = render_conditions(mesh, poses, H, W)
    with pytest.raises(ValueError, match="one frame per pose"):
        write_conditions(tmp_path / "a", frames, poses[:1])
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        render_conditions(mesh, np.eye(4)[:3], H, W)
    with pytest.raises(ValueError, match="2:1"):
        render_conditions(mesh, poses, H, H)
    write_conditions(tmp_path / "b", frames, poses)
    (tmp_path / "b/mask/000001.png").write_bytes(b"not a png")
    c = load_conditions(tmp_path / "b")
    c.mask[0]
    with pytest.raises(ValueError, match="000001.png"):
        c.mask[1]


STAGE = load_stage("conditions")


def _inputs(tmp_path, mesh, poses):
    (tmp_path / "mesh").mkdir()
    save_erp_mesh(mesh, tmp_path / "mesh/mesh.ply")
    (tmp_path / "traj").mkdir()
    write_trajectory(tmp_path / "traj", poses, np.ones(len(poses)), fps=16.0)
    return {"mesh": tmp_path / "mesh", "trajectory": tmp_path / "traj"}


def _run(inputs, out, **params):
    params = params_from_dict(STAGE.params_cls, {"height": H, "width": W, **params})
    return execute_stage(STAGE, inputs, params, out, input_digests={"mesh": "0" * 64, "trajectory": "1" * 64})


def test_stage_writes_a_valid_artifact(room_mesh, tmp_path):
    _, _, _, mesh = room_mesh
    poses = np.stack([pose_from_rt(np.eye(3), [0.1 * k, 0.0, 0.0]) for k in range(4)])
    inputs = _inputs(tmp_path, mesh, poses)
    manifest = _run(inputs, tmp_path / "out", preview_mp4=True)
    assert manifest["info"]["num_frames"] == 4 and manifest["info"]["backend"] == "raster"
    assert {"conditions.json", "rgb/000003.jpg", "mask/000003.png", "depth/000003.png", "preview.mp4"} <= set(
        manifest["files"]
    )
    _run(inputs, tmp_path / "ref", backend="raycast")
    a, b = load_conditions(tmp_path / "out"), load_conditions(tmp_path / "ref")
    assert (np.asarray(a.mask) == np.asarray(b.mask)).mean() > 0.995
    _run(inputs, tmp_path / "png", rgb_format="png")  # lossless on request; JPEG 93 close (4:2:0 chroma on 48x96)
    exact = load_conditions(tmp_path / "png")
    assert exact.rgb.paths[0] == "rgb/000000.png" and psnr(np.concatenate(a.rgb[:]), np.concatenate(exact.rgb[:])) > 25
    assert np.array_equal(np.asarray(a.mask), np.asarray(exact.mask))


def test_stage_rejects_bad_input_and_writes_nothing(room_mesh, tmp_path):
    _, _, _, mesh = room_mesh
    inputs = _inputs(tmp_path, mesh, np.stack([np.eye(4)] * 2))
    with pytest.raises(StageInputError, match="2:1"):
        _run(inputs, tmp_path / "o1", height=64, width=100)
    (tmp_path / "traj/trajectory.json").write_text(json.dumps({"poses": [[[1, 0, 0], [0, 1, 0], [0, 0, 1]]]}))
    with pytest.raises(StageInputError, match="trajectory"):
        _run(inputs, tmp_path / "o2")
    (tmp_path / "traj/trajectory.json").write_text(json.dumps({"poses": np.stack([np.eye(4)] * 2).tolist()}))
    (tmp_path / "mesh/mesh.ply").write_bytes(b"ply\nbroken")
    with pytest.raises(StageInputError, match="mesh.ply"):
        _run(inputs, tmp_path / "o3")
    assert not any(p.name.startswith(("o1", "o2", "o3", ".tmp")) for p in tmp_path.iterdir())
