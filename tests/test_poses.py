import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from panoworld.core.conventions import erp_dirs, erp_pixel_from_dir, invert_pose, pose_from_rt, transform_points
from panoworld.framework.stage import StageInputError, execute_stage, load_stage
from panoworld.framework.stage_params import params_from_dict
from panoworld.geometry.raycast import Raycaster
from panoworld.io import video_writer
from panoworld.io.depth_png import read_depth_png, write_depth_png
from panoworld.poses.estimate import colmap_estimate, load_poses, poses_from_reconstruction, poses_from_transforms
from panoworld.poses.options import ColmapOptions, RenderType

STAGE = load_stage("poses")


class TexturedRoom:
    """A 6 x 3 x 5 m room with five boxes, coloured by a sum of random 3D sinusoids (blobs SIFT can match)."""

    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        room = trimesh.creation.box(extents=(6.0, 3.0, 5.0))
        room.invert()
        parts = [room]
        for _ in range(5):
            b = trimesh.creation.box(extents=rng.uniform(0.3, 0.8, 3))
            b.apply_translation([rng.uniform(-2.5, 2.5), rng.uniform(0.0, 1.2), rng.uniform(-2.0, 2.0)])
            parts.append(b)
        mesh = trimesh.util.concatenate(parts)
        self.rc = Raycaster(mesh.vertices, mesh.faces)
        self.k = rng.normal(size=(24, 3)) * rng.choice([2.0, 5.0, 12.0, 25.0], size=(24, 1))
        self.phase = rng.uniform(0, 2 * np.pi, 24)
        self.amp = rng.normal(size=(24, 3)) * 25.0

    def render(self, world_from_cam: np.ndarray, h: int) -> tuple[np.ndarray, np.ndarray]:
        hits = self.rc.render_erp(world_from_cam, h, 2 * h)
        dirs = erp_dirs(h, 2 * h, np.float64) @ world_from_cam[:3, :3].T
        pts = world_from_cam[:3, 3] + dirs * hits.distance[..., None]
        rgb = np.clip(127.0 + np.sin(pts @ self.k.T + self.phase) @ self.amp, 0, 255).astype(np.uint8)
        return rgb, hits.distance


def curved_track(n: int, step: float = 0.12) -> np.ndarray:
    poses = []
    for i in range(n):
        yaw = Rotation.from_euler("y", 9.0 * i / max(n - 1, 1), degrees=True).as_matrix()
        poses.append(pose_from_rt(yaw, [step * i, 0.3 + 0.01 * i, 0.4 * step * i]))
    poses = np.stack(poses)
    return np.einsum("ij,njk->nik", invert_pose(poses[0]), poses)  # canonical: pose 0 = identity


def write_video(root: Path, room: TexturedRoom, poses: np.ndarray, h: int, *, depth: bool = True, blank=()) -> Path:
    """A video artifact directory written by the video stage's writer (video.json, frames/, depth/)."""
    rgb, dist = zip(*(room.render(T, h) for T in poses))
    rgb = np.stack(rgb)
    rgb[list(blank)] = 128
    video_writer.write_video(root, rgb, np.stack(dist) if depth else None, poses, fps=10.0, preview=False, mcap=False)
    return root


def write_trajectory(root: Path, poses: np.ndarray) -> Path:
    root.mkdir(parents=True)
    (root / "trajectory.json").write_text(json.dumps({"poses": poses.tolist()}))
    return root


def run_stage(tmp: Path, video: Path, traj: Path | None, name: str = "poses", **params) -> dict:
    p = params_from_dict(STAGE.params_cls, params)
    digests = {"video": "0" * 64, "trajectory": None if traj is None else "1" * 64}
    return execute_stage(STAGE, {"video": video, "trajectory": traj}, p, tmp / name, input_digests=digests)


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    R = np.swapaxes(a[:, :3, :3], 1, 2) @ b[:, :3, :3]
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))


@pytest.fixture(scope="module")
def room():
    return TexturedRoom()


@pytest.fixture(scope="module")
def colmap_run(tmp_path_factory, room):
    tmp = tmp_path_factory.mktemp("colmap")
    gt = curved_track(10)
    video = write_video(tmp / "video", room, gt, 128)
    traj = write_trajectory(tmp / "trajectory", gt)
    manifest = run_stage(tmp, video, traj, backend="colmap")
    return tmp, gt, manifest


def test_colmap_registers_every_frame_and_recovers_metric_canonical_poses(colmap_run):
    tmp, gt, manifest = colmap_run
    info = manifest["info"]
    assert info["num_registered"] == len(gt) and info["unregistered"] == []
    m = info["metrics_vs_planned"]
    assert m["ate_over_path"] < 0.005, m  # ATE under 0.5 % of the path length
    art = load_poses(tmp / "poses")
    assert art.registered.all() and art.backend == "colmap"
    np.testing.assert_allclose(art.world_from_cam[:, :3, 3], gt[:, :3, 3], atol=0.01)
    assert rotation_error_deg(art.world_from_cam, gt).max() < 0.5
    doc = json.loads((tmp / "poses" / "poses.json").read_text())
    assert 0 < doc["sim3"]["scale"] and np.allclose(np.linalg.det(doc["sim3"]["R"]), 1.0)


def test_colmap_model_is_canonical_and_its_points_lie_on_the_true_surfaces(colmap_run, room):
    import pycolmap

    tmp, gt, _ = colmap_run
    rec = pycolmap.Reconstruction(tmp / "poses" / "sparse" / "0")
    cam = next(iter(rec.cameras.values()))
    assert cam.model == pycolmap.CameraModelId.EQUIRECTANGULAR and (cam.width, cam.height) == (256, 128)
    ours = load_poses(tmp / "poses")
    for name, T in poses_from_reconstruction(rec).items():
        np.testing.assert_allclose(T, ours.world_from_cam[int(Path(name).stem)], atol=1e-6)
    # Triangulated points, moved into the canonical frame, sit at the ground-truth depth seen from camera 0.
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    assert len(xyz) > 100
    d_cam = transform_points(invert_pose(gt[0]), xyz)
    u, v = erp_pixel_from_dir(d_cam, 128, 256)
    _, depth = room.render(gt[0], 128)
    true = depth[np.clip(v.astype(int), 0, 127), np.clip(u.astype(int), 0, 255)]
    rel = np.abs(np.linalg.norm(d_cam, axis=1) - true) / true
    assert np.median(rel) < 0.02


def test_exports_reference_video_frames_and_round_trip(colmap_run):
    tmp, gt, manifest = colmap_run
    out = tmp / "poses"
    for f in ("poses.json", "transforms.json", "sparse/0/cameras.bin", "sparse/0/images.bin",
              "sparse/0/points3D.bin", "points3D.ply"):
        assert f in manifest["files"], f
    assert not (out / "depth").exists()  # the video's depth is referenced, not copied
    tf = json.loads((out / "transforms.json").read_text())
    assert tf["camera_model"] == "EQUIRECTANGULAR" and (tf["w"], tf["h"]) == (256, 128)
    assert tf["frames"][3]["file_path"] == "../video/frames/000003.png"
    assert (out / tf["frames"][3]["file_path"]).is_file()
    np.testing.assert_allclose(poses_from_transforms(tf), load_poses(out).world_from_cam, atol=1e-12)
    assert tf["frames"][3]["depth_file_path"] == "../video/depth/000003.png"
    assert load_poses(out).depth[4].resolve() == (tmp / "video/depth/000004.png").resolve()


def test_transforms_json_reproduces_our_rays_under_nerfstudio_equirectangular_model(tmp_path, room):
    gt = curved_track(3)
    video = write_video(tmp_path / "video", room, gt, 16, depth=False)
    run_stage(tmp_path, video, None, backend="planned")
    tf = json.loads((tmp_path / "poses" / "transforms.json").read_text())
    h, w = tf["h"], tf["w"]
    # nerfstudio Cameras: pixel centres (+0.5), coord = ((x - cx) / fx, -(y - cy) / fy), theta = -pi coord_x,
    # phi = pi (0.5 - coord_y), dir = (-sin theta sin phi, cos phi, -cos theta sin phi) in the OpenGL camera.
    y, x = np.mgrid[0:h, 0:w] + 0.5
    cx, cy = (x - tf["cx"]) / tf["fl_x"], -(y - tf["cy"]) / tf["fl_y"]
    theta, phi = -np.pi * cx, np.pi * (0.5 - cy)
    d_gl = np.stack([-np.sin(theta) * np.sin(phi), np.cos(phi), -np.cos(theta) * np.sin(phi)], -1)
    for f, T in zip(tf["frames"], gt):
        M = np.asarray(f["transform_matrix"])
        np.testing.assert_allclose(d_gl @ M[:3, :3].T, erp_dirs(h, w, np.float64) @ T[:3, :3].T, atol=1e-12)
        np.testing.assert_allclose(M[:3, 3], T[:3, 3])


def test_planned_backend_writes_a_colmap_model_that_opens(tmp_path, room):
    import pycolmap

    gt = curved_track(4)
    video = write_video(tmp_path / "video", room, gt, 16, depth=False)
    traj = write_trajectory(tmp_path / "trajectory", gt)
    manifest = run_stage(tmp_path, video, traj, backend="planned", copy_frames=True)
    assert manifest["info"]["metrics_vs_planned"]["ate"] < 1e-12 and not manifest["info"]["has_depth"]
    rec = pycolmap.Reconstruction(tmp_path / "poses" / "sparse" / "0")
    assert rec.num_reg_images() == 4 and rec.num_points3D() == 0
    for name, T in poses_from_reconstruction(rec).items():
        np.testing.assert_allclose(T, gt[int(Path(name).stem)], atol=1e-12)
    tf = json.loads((tmp_path / "poses" / "transforms.json").read_text())
    assert tf["frames"][0]["file_path"] == "images/000000.png" and "images/000000.png" in manifest["files"]
    assert "depth_file_path" not in tf["frames"][0]


def test_features_at_a_bounded_size_keep_the_model_in_the_video_pixel_coordinates(tmp_path, room):
    import pycolmap

    gt = curved_track(8)
    video = write_video(tmp_path / "video", room, gt, 256, depth=False)
    manifest = run_stage(tmp_path, video, write_trajectory(tmp_path / "trajectory", gt), backend="colmap",
                         max_image_size=256, max_features=1024)  # SIFT on 128x256 copies of 256x512 frames
    assert manifest["info"]["num_registered"] == len(gt)
    assert manifest["info"]["metrics_vs_planned"]["ate_over_path"] < 0.005
    rec = pycolmap.Reconstruction(tmp_path / "poses" / "sparse" / "0")
    cam = next(iter(rec.cameras.values()))
    assert (cam.width, cam.height) == (512, 256)
    xy = np.array([p.xy for img in rec.images.values() for p in img.points2D])
    assert xy[:, 0].max() > 400 and xy[:, 1].max() > 200  # keypoints span the stored frame, not the 256-wide copy
    assert rec.compute_mean_reprojection_error() < 2.0  # pixels of the stored frames
    # The point colours (from the frames decoded for the thumbnails) are those COLMAP extracts from the frames.
    ref = pycolmap.Reconstruction(rec)
    ref.extract_colors_for_all_images(str(tmp_path / "video" / "frames"))
    colors = np.array([rec.points3D[i].color for i in sorted(rec.point3D_ids())])
    assert colors.max(axis=1).min() > 0
    np.testing.assert_array_equal(colors, [ref.points3D[i].color for i in sorted(ref.point3D_ids())])


def test_blank_frames_give_a_clear_error_not_a_crash(tmp_path, room):
    gt = curved_track(6)
    video = write_video(tmp_path / "video", room, gt, 64, depth=False, blank=range(6))
    with pytest.raises(StageInputError, match=r"COLMAP registered 0 of 6 frames .*at least 3"):
        run_stage(tmp_path, video, None, backend="colmap")
    assert not (tmp_path / "poses").exists()


def test_unregistered_frames_are_flagged_and_filled_from_the_plan(tmp_path, room):
    gt = curved_track(10)
    video = write_video(tmp_path / "video", room, gt, 128, blank=(8, 9))
    manifest = run_stage(tmp_path, video, None, backend="colmap")
    assert manifest["info"]["unregistered"] == [8, 9]
    art = load_poses(tmp_path / "poses")
    assert art.registered.tolist() == [True] * 8 + [False] * 2
    np.testing.assert_array_equal(art.world_from_cam[8:], gt[8:])
    tf = json.loads((tmp_path / "poses" / "transforms.json").read_text())
    assert len(tf["frames"]) == 8


@pytest.mark.slow
def test_colmap_perspective_rig_fallback(tmp_path, room):
    gt = curved_track(8)
    video = write_video(tmp_path / "video", room, gt, 256, depth=False)  # 128x128 virtual views
    est = colmap_estimate([video / f"frames/{i:06d}.png" for i in range(8)], gt,
                          ColmapOptions(render_type=RenderType.PERSPECTIVE_OVERLAPPING))
    assert est.registered.all()
    np.testing.assert_allclose(est.world_from_cam[:, :3, 3], gt[:, :3, 3], atol=0.02)


def test_vggt_backend_needs_weights_and_runs_a_real_model_when_given_them(tmp_path, room):
    import torch

    from panoworld.models.panovggt import PanoVGGT
    from panoworld.models.panovggt_config import PanoVGGTConfig

    torch.set_num_threads(1)
    gt = curved_track(3)
    video = write_video(tmp_path / "video", room, gt, 32, depth=False)
    with pytest.raises(StageInputError, match="pass --vggt-weights DIR"):
        run_stage(tmp_path, video, None, backend="vggt")
    torch.manual_seed(0)
    cfg = PanoVGGTConfig(
        patch_size=8, embed_dim=32, depth=2, num_heads=2, num_register_tokens=1, coord_frequencies=2,
        camera_trunk_depth=1, camera_iterations=1, pose_correlation=4, dpt_layers=(0, 0, 1, 1), dpt_features=8,
        dpt_out_channels=(8, 8, 16, 16), image_height=16,
    )
    PanoVGGT(cfg).save_pretrained(tmp_path / "w")
    manifest = run_stage(tmp_path, video, None, backend="vggt", vggt={"weights": str(tmp_path / "w")}, align="none")
    assert manifest["info"]["depth_source"] == "backend" and manifest["info"]["input_height"] == 16
    art = load_poses(tmp_path / "poses")
    assert np.array_equal(art.world_from_cam[0], np.eye(4))
    d = read_depth_png(art.depth[1])
    assert d.shape == (32, 64) and np.isfinite(d).all() and (d > 0).all()
    # Aligned to the plan (video.json poses): poses move by the Sim(3), depth scales with it.
    manifest = run_stage(tmp_path, video, None, "aligned", backend="vggt", weights=str(tmp_path / "w"))
    s = manifest["info"]["sim3_scale"]
    aligned = json.loads((tmp_path / "aligned" / "poses.json").read_text())
    assert aligned["alignment"] == "sim3" and aligned["sim3"]["scale"] == s
    np.testing.assert_allclose(read_depth_png(tmp_path / "aligned" / "depth/000001.png"), s * d, atol=1e-3 + 1e-3 * s)
    # --refine-iters overrides the weights' pose_refine_iters (0 in this config): other poses, the same depth
    manifest = run_stage(tmp_path, video, None, "refined", backend="vggt", weights=str(tmp_path / "w"), align="none",
                         refine_iters=3)
    assert manifest["info"]["pose_refine_iters"] == 3
    refined = load_poses(tmp_path / "refined")
    assert not np.allclose(refined.world_from_cam[1:], art.world_from_cam[1:], atol=1e-4)
    np.testing.assert_array_equal(read_depth_png(refined.depth[1]), d)
    with pytest.raises(ValueError, match=r"\.vggt\.refine_iters=-2: must be >= 0$"):
        run_stage(tmp_path, video, None, "bad", backend="vggt", weights=str(tmp_path / "w"), refine_iters=-2)


def test_input_errors_are_one_line_and_actionable(tmp_path, room):
    gt = curved_track(4)
    video = write_video(tmp_path / "video", room, gt, 16, depth=False)
    traj = write_trajectory(tmp_path / "trajectory", gt[:3])
    with pytest.raises(StageInputError, match="3 poses but video.json lists 4 frames"):
        run_stage(tmp_path, video, traj, backend="planned")
    with pytest.raises(StageInputError, match="depth_source=video but video.json has no depth"):
        run_stage(tmp_path, video, None, backend="planned", depth_source="video")
    with pytest.raises(StageInputError, match="use --align sim3"):
        run_stage(tmp_path, video, None, backend="colmap", align="se3")
    (video / "frames/000002.png").unlink()
    with pytest.raises(StageInputError, match="frame files are missing"):
        run_stage(tmp_path, video, None, backend="planned")


def test_depth_png_round_trip(tmp_path):
    d = np.array([[0.0, 1.2345], [np.nan, 70.0]], np.float32)
    write_depth_png(tmp_path / "d.png", d)
    back = read_depth_png(tmp_path / "d.png")
    assert back[0, 0] == 0 and back[1, 0] == 0  # unknown stays 0 (panoworld/io/depth_png.py)
    assert back[0, 1] == pytest.approx(1.234, abs=1e-6) and back[1, 1] == pytest.approx(65.535, abs=1e-6)


def test_auto_takes_the_plan_for_a_rendered_video_and_recovers_poses_of_a_generated_one():
    from panoworld.poses.backends import choose_auto

    params = params_from_dict(STAGE.params_cls, {})
    assert params.backend == "auto"
    for video, want in (("warp-inpaint", "planned"), ("frame-inpaint", "planned"), ("wan-shortcut", "colmap"),
                        (None, "colmap")):
        assert choose_auto(video, params)[0].name == want, video
    with_weights = params_from_dict(STAGE.params_cls, {"vggt.weights": "/some/dir"})
    assert choose_auto("wan-shortcut", with_weights)[0].name == "vggt"
    assert choose_auto("warp-inpaint", with_weights)[0].name == "planned"


def test_auto_reads_the_video_backend_the_video_records(tmp_path, room):
    gt = curved_track(3)
    video = write_video(tmp_path / "video", room, gt, 16, depth=False)
    doc = json.loads((video / "video.json").read_text())
    (video / "video.json").write_text(json.dumps({**doc, "backend": "frame-inpaint"}))
    info = run_stage(tmp_path, video, None)["info"]
    assert info["backend"] == "planned" and info["backend_requested"] == "auto"
    assert info["decisions"] == ["backend auto: planned (video backend frame-inpaint renders every frame at its planned "
                                 "pose)"]
    np.testing.assert_allclose(load_poses(tmp_path / "poses").world_from_cam, gt, atol=1e-12)
