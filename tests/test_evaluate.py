"""`runner.py eval`: metrics against synthetic ground truth, analytic checks, missing artifacts, CLI and LPIPS."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from panoworld.core.conventions import invert_pose, points_from_depth, transform_points
from panoworld.framework import pipeline as pl
from panoworld.models.lpips import LPIPS
from panoworld.models.weights import MissingWeightsError
from panoworld.tools.eval.cli import (
    EvalParams,
    GroundTruth,
    depth_errors,
    evaluate,
    is_unavailable,
    main,
    true_disocclusion,
)

COND_H, VIDEO_H = 32, 64
OFFSET = 10  # every pixel of the test conditions is off by exactly this: PSNR = 20 log10(255 / 10)
VIDEO_OFFSET = 20


def _manifest(d: Path, info: dict | None = None) -> None:
    (d / "manifest.json").write_text(json.dumps({"info": info or {}}))


def _offset(img: np.ndarray, k: int) -> np.ndarray:
    """img (uint8) moved by exactly +-k at every pixel (down where it would clip)."""
    i = img.astype(np.int32)
    return np.where(i <= 255 - k, i + k, i - k).astype(np.uint8)


def _gt_track(gt: GroundTruth) -> np.ndarray:
    """Track 0 of the synthetic scene in the canonical frame (pose 0 = identity): collision-free ground truth."""
    return invert_pose(gt.world_from_canonical)[None] @ gt.scene.tracks[0].world_from_cam


def _write_conditions(d: Path, gt: GroundTruth, poses: np.ndarray, tol: float) -> list[np.ndarray]:
    """Conditions with rgb = ground truth off by OFFSET and mask = the true visibility; returns the true holes."""
    for sub in ("rgb", "mask", "depth"):
        (d / sub).mkdir(parents=True)
    frames, holes = [], []
    for k, pose in enumerate(poses):
        rgb, depth = gt.render(pose, COND_H, 2 * COND_H)
        hole = true_disocclusion(gt, np.eye(4), pose, COND_H, 2 * COND_H, tol)
        names = {s: f"{s}/{k:06d}.png" for s in ("rgb", "mask", "depth")}
        cv2.imwrite(str(d / names["rgb"]), _offset(rgb, OFFSET)[..., ::-1])
        cv2.imwrite(str(d / names["mask"]), (~hole).astype(np.uint8) * 255)
        cv2.imwrite(str(d / names["depth"]), np.rint(np.where(hole, 0, depth) * 1000).astype(np.uint16))
        frames.append(names)
        holes.append(hole)
    doc = {"height": COND_H, "width": 2 * COND_H, "num_frames": len(poses), "depth_scale": 0.001, "frames": frames,
           "poses": poses.tolist()}
    (d / "conditions.json").write_text(json.dumps(doc))
    _manifest(d)
    return holes


@pytest.fixture(scope="module")
def scene(synth_scene, tmp_path_factory):
    """A copy of the ci-tiny synthetic scene: depth and mesh from the pipeline; trajectory, conditions, video and
    poses written directly along the ground-truth track (so their metrics are known exactly)."""
    from panoworld.io.trajectory import write_trajectory
    from panoworld.io.video_writer import write_video

    root = tmp_path_factory.mktemp("eval") / "scene"
    shutil.copytree(synth_scene, root, ignore=shutil.ignore_patterns("artifacts"))
    report = pl.run(root, preset="ci-tiny", until="mesh")
    assert report.ok, report.table()
    art = root / "artifacts"
    gt = GroundTruth(root / "gt")
    poses = _gt_track(gt)
    (art / "trajectory").mkdir()
    write_trajectory(art / "trajectory", poses, np.zeros(len(poses)), fps=16.0)
    _manifest(art / "trajectory")
    holes = _write_conditions(art / "conditions", gt, poses, EvalParams().disocclusion_tol)
    renders = [gt.render(p, VIDEO_H, 2 * VIDEO_H) for p in poses]
    write_video(art / "video", np.stack([_offset(r, VIDEO_OFFSET) for r, _ in renders]),
                np.stack([d for _, d in renders]), poses, fps=16.0, preview=False, mcap=False)
    _manifest(art / "video")
    (art / "poses").mkdir()
    frames = [{"rgb": f"../video/frames/{k:06d}.png", "depth": None} for k in range(len(poses))]
    (art / "poses" / "poses.json").write_text(json.dumps({
        "backend": "planned", "height": VIDEO_H, "width": 2 * VIDEO_H, "poses": poses.tolist(),
        "registered": [True] * len(poses), "frames": frames}))
    _manifest(art / "poses")
    return {"root": root, "poses": poses, "holes": holes}


@pytest.fixture(scope="module")
def report(scene):
    rep, errors = evaluate(scene["root"], EvalParams(max_frames=3))
    assert errors == [], {s: rep["stages"][s] for s in errors}
    return rep


def _metric_values(stages: dict):
    """Every metric value of a report's stages (a stage that did not run counts as one value)."""
    for metrics in stages.values():
        yield from [metrics] if is_unavailable(metrics) else metrics.values()


# ---------------------------------------------------------------- metric helpers


def test_depth_errors_analytic():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.5, 5.0, (16, 32)).astype(np.float32)
    m = depth_errors(1.1 * gt, gt)
    assert m["abs_rel"] == pytest.approx(0.1, rel=1e-5)
    assert m["rmse_m"] == pytest.approx(0.1 * np.sqrt(np.mean(gt.astype(np.float64) ** 2)), rel=1e-5)
    assert m["delta1"] == 1.0 and m["scale_median"] == pytest.approx(1 / 1.1, rel=1e-5)
    assert depth_errors(1.3 * gt, gt)["delta1"] == 0.0
    mask = np.zeros(gt.shape, bool)
    mask[:, :8] = True
    pred = gt.copy()
    pred[:, 8:] *= 3.0  # outside the mask: must not count
    assert depth_errors(pred, gt, mask)["abs_rel"] == pytest.approx(0.0, abs=1e-7)


# ---------------------------------------------------------------- stages against ground truth


def test_depth_and_mesh_of_exact_input_depth_are_near_perfect(report):
    d = report["stages"]["depth"]
    assert d["abs_rel"] < 1e-3 and d["delta1"] == 1.0 and d["valid_fraction"] > 0.99
    m = report["stages"]["mesh"]
    assert m["surface_error_median_m"] < 1e-4 and m["coverage_pose0"] > 0.9
    assert m["psnr_pose0"] == "inf" or m["psnr_pose0"] > 40


def test_scaled_depth_gives_the_analytic_abs_rel(scene, tmp_path):
    root = tmp_path / "scaled"
    shutil.copytree(scene["root"], root)
    d = root / "artifacts" / "depth" / "depth.npy"
    np.save(d, np.load(d) * np.float32(1.2))
    rep, _ = evaluate(root, stages=["depth"])
    assert rep["stages"]["depth"]["abs_rel"] == pytest.approx(0.2, rel=1e-4)
    assert rep["stages"]["depth"]["scale_median"] == pytest.approx(1 / 1.2, rel=1e-4)
    assert list(rep["stages"]) == ["depth"]


def test_trajectory_along_the_gt_track_is_collision_free(report, scene):
    t = report["stages"]["trajectory"]
    clearance_gt = json.loads((scene["root"] / "gt" / "gt.json").read_text())["clearance_m"]
    assert t["min_clearance_m"] >= clearance_gt - 1e-3
    assert t["clear_fraction"] == 1.0 and t["path_collisions"] == 0
    assert t["num_poses"] == len(scene["poses"])
    c = scene["poses"][:, :3, 3]
    assert t["loop_closure_m"] == pytest.approx(np.linalg.norm(c[-1] - c[0]), abs=1e-9)
    assert report["targets"]["trajectory"]["path_collisions"]["met"] is True


def test_trajectory_through_a_wall_is_caught(scene, tmp_path):
    from panoworld.io.trajectory import write_trajectory

    root = tmp_path / "wall"
    shutil.copytree(scene["root"], root)
    poses = scene["poses"].copy()
    poses[-1, 0, 3] += 30.0  # far outside the (ci-tiny) room
    write_trajectory(root / "artifacts" / "trajectory", poses, np.zeros(len(poses)), fps=16.0)
    t = evaluate(root, stages=["trajectory"])[0]["stages"]["trajectory"]
    assert t["path_collisions"] >= 1


def test_trajectory_jump_between_paths_is_not_walked(scene, tmp_path):
    from panoworld.io.trajectory import write_trajectory

    root = tmp_path / "cut"
    shutil.copytree(scene["root"], root)
    poses = scene["poses"].copy()
    n = len(poses)
    poses[-1, 0, 3] += 30.0  # the last pose starts a path of its own (a cut), far outside the room
    paths = [{"start": 0, "stop": n - 1}, {"start": n - 1, "stop": n, "from": n - 1}]
    write_trajectory(root / "artifacts" / "trajectory", poses, np.zeros(len(poses)), fps=16.0, paths=paths)
    t = evaluate(root, stages=["trajectory"])[0]["stages"]["trajectory"]
    c = poses[:, :3, 3]
    assert t["num_paths"] == 2 and t["path_collisions"] == 0
    assert t["path_length_m"] == pytest.approx(np.linalg.norm(np.diff(c[:-1], axis=0), axis=1).sum(), rel=1e-9)


def test_conditions_psnr_and_mask_iou(report, scene):
    c = report["stages"]["conditions"]
    assert c["frames_evaluated"] == 3
    assert c["psnr_valid"] == pytest.approx(20 * math.log10(255 / OFFSET), abs=1e-9)
    assert any(h.any() for h in scene["holes"][1:]), "the test track should disocclude something"
    assert c["mask_iou"] == 1.0
    assert c["depth_abs_rel"] < 2e-3  # millimetre quantisation only


def test_video_metrics_all_and_disoccluded(report):
    v = report["stages"]["video"]
    expected = 20 * math.log10(255 / VIDEO_OFFSET)
    assert v["psnr"] == pytest.approx(expected, abs=1e-9)
    assert v["ws_psnr"] == pytest.approx(expected, abs=1e-9)
    assert v["psnr_disoccluded"] == pytest.approx(expected, abs=1e-9)
    assert 0.0 < v["ssim"] < 1.0
    assert v["depth_abs_rel"] < 2e-3


def test_identical_poses_give_zero_ate(report):
    p = report["stages"]["poses"]
    for k in ("ate", "ate_rmse", "rpe_t", "rte"):
        assert p[k] == pytest.approx(0.0, abs=1e-9), k
    for k in ("rpe_r", "rre"):  # degrees through arccos: float noise near 0 is ~1e-6
        assert p[k] == pytest.approx(0.0, abs=1e-4), k
    assert p["registered_fraction"] == 1.0 and p["ground_truth"] == "video.json poses"
    assert report["targets"]["poses"]["ate_over_path"]["met"] is True


def test_sim3_moved_poses_still_give_zero_ate_and_too_few_registered_is_unavailable(scene, tmp_path):
    from scipy.spatial.transform import Rotation

    root = tmp_path / "sim3"
    shutil.copytree(scene["root"], root)
    path = root / "artifacts" / "poses" / "poses.json"
    doc = json.loads(path.read_text())
    T = np.eye(4)
    T[:3, :3] = 2.0 * Rotation.from_euler("xyz", [10, 40, -5], degrees=True).as_matrix()
    T[:3, 3] = [1.0, -2.0, 0.5]
    moved = np.asarray(doc["poses"])
    moved[:, :3, 3] = transform_points(T, moved[:, :3, 3])
    moved[:, :3, :3] = (T[:3, :3] / 2.0) @ moved[:, :3, :3]
    doc["poses"] = moved.tolist()
    path.write_text(json.dumps(doc))
    p = evaluate(root, stages=["poses"])[0]["stages"]["poses"]
    assert p["ate"] < 1e-6 and p["rre"] < 1e-4 and p["scale"] == pytest.approx(0.5, rel=1e-6)

    doc["registered"] = [True] + [False] * (len(moved) - 1)
    path.write_text(json.dumps(doc))
    p = evaluate(root, stages=["poses"])[0]["stages"]["poses"]
    assert is_unavailable(p["ate"]) and "registered" in p["ate"]["reason"]


def test_gaussians_context_and_novel_views(scene, tmp_path):
    from panoworld.io.gaussian_set import Gaussians, rgb_to_sh_dc
    from panoworld.io.splat_ply import write_gaussians_ply

    root = tmp_path / "gs"
    shutil.copytree(scene["root"], root)
    gt = GroundTruth(root / "gt")
    rgb, depth = gt.render(np.eye(4), 32, 64)
    pts = points_from_depth(depth).reshape(-1, 3)
    n = len(pts)
    g = Gaussians(means=pts.astype(np.float32), scales=np.full((n, 3), 0.05, np.float32),
                  quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), opacities=np.full(n, 0.9, np.float32),
                  sh_dc=rgb_to_sh_dc(rgb.reshape(-1, 3) / 255.0).astype(np.float32))
    d = root / "artifacts" / "gaussians"
    d.mkdir()
    write_gaussians_ply(d / "gaussians.ply", g)
    used = [0, 2, 4, 6]
    _manifest(d, {"frames": used})
    params = EvalParams(views=2, gs_height=16)
    out = evaluate(root, params, stages=["gaussians"])[0]["stages"]["gaussians"]
    assert out["setting"] == "2@2" and out["context_frames"] == [0, 6]
    assert "held-out frames" in out["novel_protocol"] and "[1, 7]" in out["novel_protocol"]
    assert 5.0 < out["context_psnr"] < 60.0 and 0.0 < out["context_coverage"] <= 1.0
    assert math.isfinite(out["novel_psnr"]) and is_unavailable(out["context_lpips"])

    _manifest(d, {"frames": list(range(len(scene["poses"])))})
    out = evaluate(root, params, stages=["gaussians"])[0]["stages"]["gaussians"]
    assert "midpoints" in out["novel_protocol"] and out["setting"] == "2@2"


# ---------------------------------------------------------------- robustness, CLI, JSON


def test_missing_artifacts_are_reported_not_run(synth_scene, capsys):
    assert main([str(synth_scene), "--json", "--only", "video", "--only", "gaussians"]) == 0
    rep = json.loads(capsys.readouterr().out)
    for stage in ("video", "gaussians"):
        assert is_unavailable(rep["stages"][stage]) and rep["stages"][stage]["reason"].startswith("not run")
    assert rep["targets"]["gaussians"]["novel_psnr"]["met"] is None


def test_scene_without_gt_or_artifacts_exits_2(tmp_path, capsys):
    (tmp_path / "panorama.png").write_bytes(b"")
    assert main([str(tmp_path)]) == 2
    assert "has no gt/gt.json and no artifacts/: nothing to evaluate" in capsys.readouterr().err


def test_json_structure_and_unavailable_never_zero(report, scene, capsys):
    assert set(report) >= {"scene", "stages", "targets"}
    assert list(report["stages"]) == ["depth", "register", "mesh", "navmesh", "trajectory", "conditions", "video", "loop",
                                      "poses", "gaussians", "roam"]
    assert report["reference"] == "synthetic"
    assert is_unavailable(report["stages"]["navmesh"]) and is_unavailable(report["stages"]["gaussians"])
    assert is_unavailable(report["stages"]["roam"]) and "gaussians" in report["stages"]["roam"]["reason"]
    for v in ("lpips", "fid", "fvd"):
        assert is_unavailable(report["stages"]["video"][v]) and report["stages"]["video"][v]["reason"]
    for value in _metric_values(report["stages"]):
        if isinstance(value, dict):
            assert value == {"available": False, "reason": value["reason"]} and value["reason"]
    assert main([str(scene["root"]), "--json", "--only", "poses"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert list(out["stages"]) == ["poses"] and out["stages"]["poses"]["ate"] < 1e-6
    assert main([str(scene["root"]), "--only", "poses"]) == 0
    table = capsys.readouterr().out
    assert "poses" in table and "ate_over_path" in table and "<= 0.005" in table


def test_corrupt_artifact_is_an_error_entry_and_exit_1(scene, tmp_path, capsys):
    root = tmp_path / "corrupt"
    shutil.copytree(scene["root"], root)
    (root / "artifacts" / "depth" / "depth.npy").write_bytes(b"not numpy")
    assert main([str(root), "--json", "--only", "depth", "--only", "poses"]) == 1
    rep = json.loads(capsys.readouterr().out)
    assert rep["stages"]["depth"]["reason"].startswith("error:")
    assert rep["stages"]["poses"]["ate"] < 1e-6


# ---------------------------------------------------------------- LPIPS


def _random_lpips(net: str) -> LPIPS:
    torch.manual_seed(0)
    m = LPIPS(net).eval()
    for lin in m.lins:
        lin.weight.data.abs_()
    return m


def _save_official_layout(m: LPIPS, tmp_path: Path) -> tuple[Path, Path]:
    bb, lin = tmp_path / f"{m.net}_backbone.pth", tmp_path / f"{m.net}_lin.pth"
    state = {f"features.{k}": v for k, v in m.features.state_dict().items()}
    state["classifier.1.weight"] = torch.zeros(4, 4)  # torchvision files carry the classifier too
    torch.save(state, bb)
    torch.save({f"lin{k}.model.1.weight": lin.weight.data.clone() for k, lin in enumerate(m.lins)}, lin)
    return bb, lin


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_identity_symmetry_and_file_round_trip(net, tmp_path):
    m = _random_lpips(net)
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (48, 96, 3), dtype=np.uint8)
    b = _offset(a, 30)
    assert m.distance_uint8(a, a) == 0.0
    d_ab, d_ba = m.distance_uint8(a, b), m.distance_uint8(b, a)
    assert d_ab > 0 and d_ab == pytest.approx(d_ba, rel=1e-6)
    loaded = LPIPS.from_files(*_save_official_layout(m, tmp_path), net=net)
    assert loaded.distance_uint8(a, b) == pytest.approx(d_ab, rel=1e-6)


def test_lpips_weights_errors_name_the_flag(tmp_path):
    with pytest.raises(MissingWeightsError, match="--lpips-weights"):
        LPIPS.from_files(tmp_path / "none.pth", tmp_path / "none_lin.pth")
    bb, lin = _save_official_layout(_random_lpips("vgg"), tmp_path)
    with pytest.raises(MissingWeightsError, match="must be the torchvision AlexNet"):
        LPIPS.from_files(bb, lin, net="alex")


def test_eval_reports_lpips_with_weights(scene, tmp_path, capsys):
    bb, lin = _save_official_layout(_random_lpips("alex"), tmp_path)
    args = [str(scene["root"]), "--json", "--only", "video", "--max-frames", "2", "--video-height", "32"]
    assert main(args + ["--lpips-weights", str(bb), "--lpips-lin-weights", str(lin)]) == 0
    v = json.loads(capsys.readouterr().out)["stages"]["video"]
    assert isinstance(v["lpips"], float) and v["lpips"] > 0
    assert v["resolution"] == "32x64" and v["frames_evaluated"] == 2 and v["psnr"] > 15
    assert main(args + ["--lpips-weights", str(bb)]) == 2
    assert main(args + ["--lpips-weights", str(tmp_path / "x.pth"), "--lpips-lin-weights", str(lin)]) == 2
    assert "--lpips-weights" in capsys.readouterr().err


# ---------------------------------------------------------------- real-dataset modes: frames + poses, plan only


def _planned_poses_artifact(art: Path, poses: np.ndarray, height: int) -> None:
    (art / "poses").mkdir(parents=True)
    frames = [{"rgb": f"../video/frames/{k:06d}.png", "depth": None} for k in range(len(poses))]
    (art / "poses" / "poses.json").write_text(json.dumps({
        "backend": "planned", "height": height, "width": 2 * height, "poses": poses.tolist(),
        "registered": [True] * len(poses), "frames": frames}))
    _manifest(art / "poses")


def test_frames_and_poses_scene_without_a_mesh(synth_scene, tmp_path):
    """An InteriorGS-like scene (ground-truth frames + poses, no mesh) made with the converter from a synthetic
    track: the video is scored against the ground-truth frame at each pose; mesh metrics say why they are missing."""
    from panoworld.io.trajectory import write_trajectory
    from panoworld.io.video_writer import write_video
    from panoworld.tools.eval.convert import convert_frames_scene

    root = convert_frames_scene(synth_scene / "gt" / "tracks" / "track_00.json", tmp_path / "frames_scene",
                                "../frames/track_00/rgb/{:06d}.png", "../frames/track_00/depth/{:06d}.npy", stride=2)
    assert not (root / "gt" / "scene.glb").exists()
    poses = np.asarray(json.loads((root / "trajectory.json").read_text())["poses"])
    track_frames = json.loads((root / "trajectory.json").read_text())["track_frames"]
    assert track_frames == list(range(0, 8, 2)) and np.allclose(poses[0], np.eye(4))
    art = root / "artifacts"
    (art / "trajectory").mkdir(parents=True)
    write_trajectory(art / "trajectory", poses, np.zeros(len(poses)), fps=16.0)
    _manifest(art / "trajectory")
    gt_frames = [cv2.imread(str(root / "gt" / "frames" / "track_00" / "rgb" / f"{i:06d}.png"))[..., ::-1]
                 for i in track_frames]
    write_video(art / "video", np.stack([_offset(f, VIDEO_OFFSET) for f in gt_frames]), None, poses, fps=16.0,
                preview=False, mcap=False)
    _manifest(art / "video")
    _planned_poses_artifact(art, poses, gt_frames[0].shape[0])
    rep, errors = evaluate(root, EvalParams(max_frames=0))
    assert errors == [] and rep["reference"] == "frames"
    v = rep["stages"]["video"]
    assert v["frames_evaluated"] == len(poses) - 1
    assert v["psnr"] == pytest.approx(20 * math.log10(255 / VIDEO_OFFSET), abs=1e-9)
    assert rep["stages"]["poses"]["ate"] == pytest.approx(0.0, abs=1e-9)
    traj = rep["stages"]["trajectory"]
    assert traj["num_poses"] == len(poses) and "ground-truth mesh" in traj["min_clearance_m"]["reason"]
    assert rep["stages"]["loop"]["reason"].startswith("not a closed path")
    # A pose off the ground-truth track has no reference frame: named, never scored against a wrong frame.
    shifted = poses.copy()
    shifted[:, 0, 3] += 0.05
    (art / "video" / "video.json").write_text(json.dumps(
        {**json.loads((art / "video" / "video.json").read_text()), "poses": shifted.tolist()}))
    rep, _ = evaluate(root, EvalParams(max_frames=0), stages=["video"])
    assert "no ground-truth frame at the pose" in rep["stages"]["video"]["reason"]


def _ring(n: int, radius: float = 0.5) -> np.ndarray:
    """n upright poses on a circle through the origin, the last one step before the first (a ring trajectory)."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = radius * np.sin(a)
    poses[:, 2, 3] = radius * (1 - np.cos(a))
    return poses


def test_plan_only_scene_scores_poses_against_the_plan_and_the_loop(tmp_path, capsys):
    """A RealSee3D-like scene: a panorama, no ground truth; a ring trajectory, a video whose last frame is the first
    yawed by k columns, recovered poses with one camera turned in place."""
    from scipy.ndimage import gaussian_filter
    from scipy.spatial.transform import Rotation

    from panoworld.io.trajectory import write_trajectory
    from panoworld.io.video_writer import write_video

    root = tmp_path / "plan_scene"
    art = root / "artifacts"
    rng = np.random.default_rng(0)
    x = gaussian_filter(rng.random((32, 64, 3)), (2, 2, 0), mode="wrap")
    pano = ((x - x.min()) / (x.max() - x.min()) * 255).astype(np.uint8)
    art.mkdir(parents=True)
    cv2.imwrite(str(root / "panorama.png"), pano[..., ::-1])
    n, theta = 12, 4.0
    plan = _ring(n)
    (art / "trajectory").mkdir()
    write_trajectory(art / "trajectory", plan, np.zeros(n), fps=16.0)
    _manifest(art / "trajectory")
    results = {}
    for k in (0, 2):
        frames = np.stack([np.roll(pano, k * t // (n - 1), axis=1) for t in range(n)])
        shutil.rmtree(art / "video", ignore_errors=True)
        write_video(art / "video", frames, None, plan, fps=16.0, preview=False, mcap=False)
        _manifest(art / "video")
        shutil.rmtree(art / "poses", ignore_errors=True)
        est = plan.copy()
        est[5, :3, :3] = Rotation.from_euler("y", theta, degrees=True).as_matrix()
        _planned_poses_artifact(art, est, 32)
        assert main([str(root), "--json"]) == 0
        results[k] = json.loads(capsys.readouterr().out)
    rep = results[0]
    assert rep["reference"] == "plan-only"
    assert rep["stages"]["loop"]["loop_flow_deg"] == 0.0 and rep["stages"]["loop"]["loop_psnr"] == "inf"
    assert results[2]["stages"]["loop"]["loop_flow_deg"] == pytest.approx(2 * 360 / 64, rel=0.02)
    assert rep["stages"]["loop"]["loop_gap_m"] < 1.5 * np.linalg.norm(plan[1, :3, 3] - plan[0, :3, 3])
    assert "plan-only" in rep["stages"]["loop"]["loop_flow_deg_reference"]["reason"]
    p = rep["stages"]["poses"]
    assert p["ground_truth"] == "video.json poses" and p["ate"] == pytest.approx(0.0, abs=1e-12)
    assert p["rre"] == pytest.approx(2 * theta / (n - 1), rel=1e-9)  # pairs (4, 5) and (5, 6)
    assert rep["stages"]["video"]["reason"].startswith("no ground truth in this scene")
    assert rep["stages"]["depth"]["reason"].startswith("not run")


@pytest.mark.slow
def test_dataset_fid_and_fvd_with_local_feature_networks(scene, tmp_path):
    """FID/FVD over scenes with randomly initialised networks saved in the reference file layouts: the whole path
    from artifacts to a table cell runs; without weights each says which file to pass."""
    from panoworld.models.inception import FIDInceptionV3
    from panoworld.tools.eval.distribution import distribution_metrics
    from panoworld.tools.eval.tables import build_tables, group_key

    units = [(scene["root"], None), (scene["root"], None)]  # FVD needs two clips; FID runs on the first unit only
    none = distribution_metrics(units, EvalParams())
    assert "pt_inception-2015-12-05" in none["fid"]["reason"] and "i3d_torchscript" in none["fvd"]["reason"]
    torch.manual_seed(0)
    torch.save(FIDInceptionV3().state_dict(), tmp_path / "pt_inception.pth")

    class MeanI3D(torch.nn.Module):  # stands in for the exported I3D: same call, 3 features per clip
        def forward(self, x: torch.Tensor, rescale: bool = False, resize: bool = False, return_features: bool = True):
            return x.mean(dim=(3, 4))[:, :, :3].reshape(x.shape[0], -1)

    torch.jit.script(MeanI3D()).save(str(tmp_path / "i3d_torchscript.pt"))
    fid = distribution_metrics(units[:1], EvalParams(fid_weights=str(tmp_path / "pt_inception.pth")), height=32)
    n = len(scene["poses"])
    assert fid["fid_frames"] == [n, n] and fid["fid_reference"] == ["ground truth at the video's poses"]
    assert math.isfinite(fid["fid"]) and fid["fid"] > -1e-6 and "i3d_torchscript" in fid["fvd"]["reason"]
    fvd = distribution_metrics(units, EvalParams(fvd_weights=str(tmp_path / "i3d_torchscript.pt")), height=32)
    assert fvd["fvd"] > 0  # the video is the ground truth off by 20 grey levels: the mean features differ
    d = {**fid, "fvd": fvd["fvd"]}
    rep, _ = evaluate(scene["root"], EvalParams(max_frames=2), stages=["video", "poses", "trajectory"])
    table = build_tables([{**rep, "unit": "scene"}], {"gt": {group_key(rep): d}})[0]
    row = next(cells for label, cells in table.rows if label.startswith("ours"))
    fid = row[table.columns.index("FID")]
    assert fid.mean == pytest.approx(d["fid"]) and fid.n == 1
