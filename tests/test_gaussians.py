"""Voxel fusion: the paper's equations, surface-accurate Gaussians on ray-cast ground truth, pruning and errors, the stage."""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh

from panoworld.core.conventions import erp_dirs
from panoworld.gaussians.fusion import FusionParams, frame_observations, uniform_subset, voxel_fusion
from panoworld.geometry.raycast import Raycaster
from panoworld.geometry.voxels import FUSION_EPS, fuse_voxels, merge_voxel_sums, voxel_keys, voxel_sums
from panoworld.io.gaussian_set import SH_C0
from panoworld.render.erp import render_erp
from panoworld.render.metrics import psnr

torch.set_num_threads(1)

ROOM = np.array([4.0, 2.6, 5.0])  # box room extents (x, y, z) centred on the origin


def room_color(p: np.ndarray) -> np.ndarray:
    """Smooth albedo as a function of the world point (N..., 3) -> rgb in [0, 1]."""
    s = np.sin(p @ np.array([[2.0, 0.5, 0.3], [0.4, 2.5, 0.7], [1.1, 0.2, 1.9]]))
    return np.clip(0.5 + 0.3 * s, 0, 1)


def textured_color(p: np.ndarray) -> np.ndarray:
    """room_color plus horizontal bands of 0.4 m period on the walls (detail that 4 cm voxels blur)."""
    waves = 0.25 * np.sin(2 * np.pi * p[..., 1:2] / 0.4)
    return np.clip(room_color(p) + waves, 0, 1)


def _room_renderer(color):
    box = trimesh.creation.box(extents=ROOM)
    block = trimesh.creation.box(extents=[0.6, 0.8, 0.6])
    block.apply_translation([0.9, 0.9, 1.2])
    mesh = trimesh.util.concatenate([box, block])
    rc = Raycaster(mesh.vertices, mesh.faces)

    def render(pose, H=64, W=128):
        d = rc.render_erp(pose, H, W).distance.astype(np.float32)
        pts = erp_dirs(H, W, np.float64) * d[..., None] @ pose[:3, :3].T + pose[:3, 3]
        return (color(pts) * 255).round().astype(np.uint8), d

    return render


@pytest.fixture(scope="module")
def room():
    return _room_renderer(room_color)


def pose_at(x, y, z):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def test_fuse_voxels_is_the_papers_weighted_mean():
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.uniform(0, 0.5, (300, 3)))
    w = torch.from_numpy(rng.uniform(0, 1, 300))
    f = torch.from_numpy(rng.normal(size=(300, 4)))
    p, fv, sums, inverse = fuse_voxels(x, w, f, 0.1)
    groups = defaultdict(list)
    for i, key in enumerate(np.floor(x.numpy() / 0.1).astype(int)):
        groups[tuple(key)].append(i)
    assert len(groups) == len(p)
    for members in groups.values():
        j = int(inverse[members[0]])
        assert all(int(inverse[m]) == j for m in members)
        wm = w[members]
        assert torch.allclose(p[j], (wm[:, None] * x[members]).sum(0) / (wm.sum() + FUSION_EPS))
        assert torch.allclose(fv[j], (wm[:, None] * f[members]).sum(0) / (wm.sum() + FUSION_EPS))
        assert int(sums.count[j]) == len(members)


def test_fusion_is_differentiable_in_confidence():
    x = torch.tensor([[0.01, 0.01, 0.01], [0.05, 0.02, 0.03]], dtype=torch.float64)
    w = torch.tensor([1.0, 3.0], dtype=torch.float64, requires_grad=True)
    p, _, _, _ = fuse_voxels(x, w, torch.zeros(2, 1, dtype=torch.float64), 0.1)
    p[0, 0].backward()
    assert w.grad is not None and abs(float(w.grad[1])) > 0


def test_merging_per_frame_sums_equals_one_pass():
    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.uniform(-1, 1, (500, 3)))
    keys, _ = voxel_keys(x, 0.25)
    w = torch.from_numpy(rng.uniform(0.1, 1, 500))
    v = torch.from_numpy(rng.normal(size=(500, 2)))
    whole, _ = voxel_sums(keys, w, v)
    parts = [voxel_sums(keys[s : s + 120], w[s : s + 120], v[s : s + 120])[0] for s in range(0, 500, 120)]
    merged = merge_voxel_sums(parts[::-1])
    assert torch.equal(merged.keys, whole.keys) and torch.equal(merged.count, whole.count)
    assert torch.allclose(merged.fused(), whole.fused())


def test_fusion_streams_frames_and_bounds_its_accumulators(room, monkeypatch):
    """Frames are streamed (a lazy source has at most three alive) and the per-frame voxel sums are reduced
    every MERGE_EVERY frames, with the same result as fusing the frames held in a list."""
    import weakref

    from panoworld.gaussians import fusion as gs

    poses = [pose_at(0.05 * k, 0.0, -0.04 * k) for k in range(12)]
    cache = {i: room(p, 32, 64) for i, p in enumerate(poses)}
    alive, most = set(), [0]

    class Lazy:
        def __len__(self):
            return len(poses)

        def __iter__(self):
            for i, pose in enumerate(poses):
                rgb, d = (a.copy() for a in cache[i])
                alive.add(i)
                weakref.finalize(rgb, alive.discard, i)
                most[0] = max(most[0], len(alive))
                yield rgb, d, pose

    sizes = []
    merge = gs.merge_voxel_sums
    monkeypatch.setattr(gs, "merge_voxel_sums", lambda parts: sizes.append(len(parts)) or merge(parts))
    monkeypatch.setattr(gs, "MERGE_EVERY", 3)
    # one worker (map_ahead's count follows torch's threads, which numba's OpenMP layer resets to the core count
    # when a test before this one first runs a parallel numba kernel)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        lazy = gs.voxel_fusion(Lazy(), FusionParams(voxel_size=0.1, per_voxel=2))
    finally:
        torch.set_num_threads(threads)
    # at most the frame being fused, the one drawn ahead and the previous one while its worker thread lets go of it
    # (2 on an idle machine; 3 seen under load): streamed, never the 12 of the list
    assert most[0] <= 3 and max(sizes) <= 4
    whole = gs.voxel_fusion([(*cache[i], p) for i, p in enumerate(poses)], FusionParams(voxel_size=0.1, per_voxel=2))
    assert lazy.num_observations == whole.num_observations and len(lazy.gaussians) == len(whole.gaussians)
    np.testing.assert_allclose(lazy.gaussians.means, whole.gaussians.means, atol=1e-5)


def test_voxel_keys_reject_far_points():
    with pytest.raises(ValueError, match="increase voxel_size"):
        voxel_keys(torch.tensor([[1e6, 0.0, 0.0]]), 0.01)


def test_gaussians_lie_on_the_ground_truth_surfaces_with_their_colour(room):
    frames = [(*room(pose_at(*t)), pose_at(*t)) for t in [(0, 0, 0), (0.5, 0.1, -0.6), (-0.6, -0.1, 0.4)]]
    res = voxel_fusion(frames, FusionParams(voxel_size=0.05))
    g = res.gaussians
    assert res.num_observations > 0.9 * 3 * 64 * 128
    # Distance of every mean to the nearest box face (room walls or the block).
    half = ROOM / 2
    d_room = np.min(half - np.abs(g.means), axis=1)
    lo, hi = np.array([0.6, 0.5, 0.9]), np.array([1.2, 1.3, 1.5])
    outside = np.maximum(np.maximum(lo - g.means, g.means - hi), 0)
    d_block = np.where(np.all(outside == 0, 1), 0, np.linalg.norm(outside, axis=1))
    inside_block = np.all((g.means > lo) & (g.means < hi), 1)
    d_block[inside_block] = np.min(np.minimum(g.means - lo, hi - g.means)[inside_block], axis=1)
    dist = np.minimum(np.abs(d_room), d_block)
    assert np.median(dist) < 0.005 and np.quantile(dist, 0.99) < 0.03
    # Colours: the fused mean colour of each voxel is close to the albedo at its mean (smooth texture).
    err = np.abs(g.base_colors() - room_color(g.means.astype(np.float64)))
    assert np.median(err) < 0.02
    # Flat surfels: the thinnest axis is the clamp, the in-plane ones are a fraction of a voxel.
    s = np.sort(g.scales, 1)
    assert np.median(s[:, 0]) == pytest.approx(0.05 * 0.05, rel=0.01)
    assert 0.01 < np.median(s[:, 2]) <= 0.05
    assert np.allclose(g.opacities, 0.98) and np.allclose(g.sh_dc, (g.base_colors() - 0.5) / SH_C0, atol=1e-5)


def test_renders_match_ground_truth_at_context_and_novel_views(room):
    ctx = [pose_at(*t) for t in [(0, 0, 0), (0.6, 0.1, 0.5), (-0.5, -0.1, -0.6)]]
    frames = [(*room(p), p) for p in ctx]
    g = voxel_fusion(frames, FusionParams(voxel_size=0.04)).gaussians
    for pose, floor in [(ctx[0], 27.0), (pose_at(0.3, 0.05, -0.2), 25.0)]:
        gt, _ = room(pose)
        out = render_erp(g, pose, 64, 128)
        img = (out.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        assert psnr(img, gt) > floor
        assert float((out.alpha > 0.5).float().mean()) > 0.99 and float(out.alpha.mean()) > 0.96


def test_per_voxel_parts_split_each_voxel(room):
    frames = [(*room(pose_at(0, 0, 0)), pose_at(0, 0, 0))]
    one = voxel_fusion(frames, FusionParams(voxel_size=0.1))
    four = voxel_fusion(frames, FusionParams(voxel_size=0.1, per_voxel=4))
    assert one.num_voxels == four.num_voxels
    assert len(one.gaussians) < len(four.gaussians) <= 4 * len(one.gaussians)
    # Parts of a voxel are smaller than the whole voxel's Gaussian.
    assert np.median(four.gaussians.scales.max(1)) < np.median(one.gaussians.scales.max(1))


def test_empty_depth_and_over_pruning_raise():
    rgb = np.zeros((8, 16, 3), np.uint8)
    with pytest.raises(ValueError, match="no valid depth"):
        voxel_fusion([(rgb, np.full((8, 16), np.nan, np.float32), np.eye(4))], FusionParams())
    with pytest.raises(ValueError, match="all .* voxels were pruned"):
        voxel_fusion([(rgb, np.full((8, 16), 2.0, np.float32), np.eye(4))], FusionParams(min_points=10**6))
    with pytest.raises(ValueError, match="per_voxel"):
        FusionParams(per_voxel=3).check()
    with pytest.raises(ValueError, match="expected \\(8, 16, 3\\)"):
        voxel_fusion([(rgb[:, :8], np.ones((8, 16), np.float32), np.eye(4))], FusionParams())


def test_uniform_subset():
    assert uniform_subset(range(10), 4) == [0, 3, 6, 9]
    assert uniform_subset([2, 5], 0) == [2, 5]


# ---------------------------------------------------------------- stage


def write_inputs(tmp: Path, room, *, with_depth: bool = True) -> tuple[Path, Path]:
    video, poses = tmp / "video", tmp / "poses"
    (video / "frames").mkdir(parents=True)
    (video / "depth").mkdir()
    (poses / "depth").mkdir(parents=True)
    ts = [(0, 0, 0), (0.4, 0.0, 0.3), (-0.3, 0.05, -0.4)]
    frames, pose_list = [], []
    for i, t in enumerate(ts):
        rgb, d = room(pose_at(*t))
        cv2.imwrite(str(video / "frames" / f"{i:06d}.png"), rgb[..., ::-1])
        cv2.imwrite(str(video / "depth" / f"{i:06d}.png"), np.round(d * 1000).astype(np.uint16))
        frames.append({"rgb": f"frames/{i:06d}.png", "depth": f"depth/{i:06d}.png" if with_depth else None})
        pose_list.append(pose_at(*t).tolist())
    (video / "video.json").write_text(json.dumps({
        "height": 64, "width": 128, "num_frames": 3, "has_depth": with_depth, "depth_scale": 0.001,
        "frames": frames, "poses": pose_list,
    }))
    (poses / "poses.json").write_text(json.dumps({
        "poses": pose_list, "registered": [True, True, False],
        "frames": [{"rgb": f["rgb"], "depth": None} for f in frames], "depth_scale": 0.001,
    }))
    return video, poses


def _params(**values):
    """The gaussians stage's Params from flat names (voxel-fusion's options among them), as --set takes them."""
    from panoworld.framework.stage_params import params_from_dict
    from stages.gaussians import Params

    return params_from_dict(Params, values, "gaussians")


def test_stage_writes_a_valid_artifact(tmp_path, room):
    from panoworld.framework.stage import execute_stage, load_stage
    from panoworld.io.splat_ply import read_gaussians_ply
    from panoworld.io.splat_spz import read_gaussians_spz

    video, poses = write_inputs(tmp_path, room)
    spec = load_stage("gaussians")
    out = tmp_path / "out"
    manifest = execute_stage(spec, {"video": video, "poses": poses}, _params(voxel_size=0.05, eval_views=2),
                             out, input_digests={"video": "0" * 64, "poses": "1" * 64})
    info = manifest["info"]
    assert {"gaussians.ply", "gaussians.spz", "preview.png"} <= set(manifest["files"])
    assert "points.ply" not in manifest["files"]  # opt-in: points_ply
    assert info["frames"] == [0, 1] and info["depth_source"] == "video"  # frame 2 is unregistered
    g = read_gaussians_ply(out / "gaussians.ply")
    assert info["num_gaussians"] == len(g) > 1000 and info["sh_degree"] == g.sh_degree == 0  # no zero f_rest_*
    spz = read_gaussians_spz(out / "gaussians.spz")  # the same Gaussians, at SPZ's precision
    assert np.abs(spz.means - g.means).max() <= 2.0 ** -12 and np.abs(spz.sh_dc - g.sh_dc).max() < 0.015
    assert (out / "gaussians.spz").stat().st_size < (out / "gaussians.ply").stat().st_size / 3
    assert len(info["eval"]) == 2 and info["context_psnr"] > 25
    assert info["context_psnr_covered"] >= info["context_psnr"] - 0.5  # the room is covered: about the same score
    assert info["fusion_height"] == 64
    fit = info["color_fit"]  # on by default: the render at the capture point moved towards frame 0
    assert fit["iters"] == 10 and fit["height"] == 64 and fit["rmse_after"] < 0.9 * fit["rmse_before"], fit
    capped = execute_stage(spec, {"video": video, "poses": poses}, _params(voxel_size=0.05, eval_views=0, max_height=32,
                           source_height=32, fit_iters=0), tmp_path / "capped",
                           input_digests={"video": "0" * 64, "poses": "1" * 64})["info"]
    assert capped["fusion_height"] == 32 and capped["num_observations"] < 0.3 * info["num_observations"]
    assert capped["color_fit"] is None
    # source_scale sizes the per-pixel Gaussians of the source only (they come first in the .ply)
    from panoworld.gaussians.backends.voxel_fusion import VoxelFusionOptions

    wide = execute_stage(spec, {"video": video, "poses": poses},
                         _params(voxel_size=0.05, eval_views=0, source_scale=2 * VoxelFusionOptions().source_scale),
                         tmp_path / "wide", input_digests={"video": "0" * 64, "poses": "1" * 64})["info"]
    g0, g1 = read_gaussians_ply(out / "gaussians.ply"), read_gaussians_ply(tmp_path / "wide" / "gaussians.ply")
    n = info["num_source_gaussians"]
    assert wide["num_source_gaussians"] == n and 0 < n < len(g0)
    ratio = np.median(g1.scales[:n].max(1)) / np.median(g0.scales[:n].max(1))
    assert ratio == pytest.approx(2.0, rel=0.05)
    assert len(g1) == len(g0) and np.allclose(g1.scales[n:], g0.scales[n:])  # the voxel Gaussians are unchanged
    # unseen_voxel_size sizes the voxels of what the source does not see, and only those
    coarse = execute_stage(spec, {"video": video, "poses": poses}, _params(voxel_size=0.05, eval_views=0,
                           unseen_voxel_size=0.16), tmp_path / "coarse", input_digests={"video": "0" * 64, "poses": "1" * 64})
    g2 = read_gaussians_ply(tmp_path / "coarse" / "gaussians.ply")
    assert coarse["info"]["num_source_gaussians"] == n and np.allclose(g2.means[:n], g0.means[:n])
    assert coarse["info"]["voxel_size"] == 0.16 and 0 < len(g2) - n < len(g0) - n
    assert np.median(g2.scales[n:].max(1)) > 1.5 * np.median(g0.scales[n:].max(1))


def test_context_source_reads_ahead_and_yields_the_frames_in_order(tmp_path, room):
    from panoworld.gaussians.fusion import context_source

    video, poses = write_inputs(tmp_path, room)
    src = context_source(video, poses)
    frames = list(src)
    assert len(frames) == len(src) == 2
    for k, (rgb, depth, pose) in enumerate(frames):
        want = src.frame(k)
        assert np.array_equal(rgb, want[0]) and np.array_equal(depth, want[1], equal_nan=True)
        assert np.array_equal(pose, want[2])
    it = iter(src)  # a consumer that stops early leaves no thread behind
    next(it)
    it.close()
    assert [np.array_equal(a[0], b[0]) for a, b in zip(src, frames)] == [True, True]  # re-iterable


def test_stage_input_errors(tmp_path, room):
    from panoworld.framework.stage import StageInputError, execute_stage, load_stage
    from stages.gaussians import Params

    spec = load_stage("gaussians")
    digests = {"video": "0" * 64, "poses": "1" * 64}
    video, poses = write_inputs(tmp_path / "a", room, with_depth=False)
    with pytest.raises(StageInputError, match="needs per-frame depth: use video backend warp-inpaint or poses backend vggt"):
        execute_stage(spec, {"video": video, "poses": poses}, Params(), tmp_path / "o1", input_digests=digests)
    video, poses = write_inputs(tmp_path / "b", room)
    with pytest.raises(StageInputError, match="pass --decoder-weights"):
        execute_stage(spec, {"video": video, "poses": poses}, Params(backend="decoder"), tmp_path / "o2",
                      input_digests=digests)
    for p in (video / "depth").iterdir():
        cv2.imwrite(str(p), np.zeros((64, 128), np.uint16))
    with pytest.raises(StageInputError, match="no valid depth"):
        execute_stage(spec, {"video": video, "poses": poses}, Params(), tmp_path / "o3", input_digests=digests)
    with pytest.raises(StageInputError, match="per_voxel"):
        execute_stage(spec, {"video": video, "poses": poses}, _params(per_voxel=3), tmp_path / "o4", input_digests=digests)
    assert not any((tmp_path / f"o{i}").exists() for i in range(1, 5))


def test_a_scene_smaller_than_a_voxel_is_reported(tmp_path):
    from panoworld.gaussians.artifact import write_artifact
    from panoworld.io.gaussian_set import ContextFrames

    rgb = np.full((16, 32, 3), 200, np.uint8)
    depth = np.full((16, 32), 0.004, np.float32)  # a 4 mm sphere around the camera
    res = voxel_fusion([(rgb, depth, np.eye(4))], FusionParams(voxel_size=0.05))
    assert len(res.gaussians) <= 8
    frames = ContextFrames(rgb[None], depth[None], np.eye(4)[None], [0], "video")
    info = write_artifact(tmp_path, res, frames, eval_views=1, eval_height=16)
    assert info["warnings"] and "under two voxels" in info["warnings"][0]
    assert (tmp_path / "gaussians.ply").is_file() and (tmp_path / "preview.png").is_file()


def test_source_pixels_reproduce_the_input_at_the_capture_point():
    # The source view's per-pixel Gaussians (the stage's footprint, unfitted as for a home) give back its own
    # (textured) image within a PSNR bound of the anti-aliased reference, and the other frames still fill the room for
    # a view elsewhere.
    from panoworld.gaussians.backends.voxel_fusion import VoxelFusionOptions
    from panoworld.gaussians.pixel import SourceVisibility, merge_gaussians, pixel_gaussians

    room = _room_renderer(textured_color)
    ctx = [pose_at(*t) for t in [(0, 0, 0), (0.6, 0.1, 0.5), (-0.5, -0.1, -0.6)]]
    frames = [(*room(p, 128, 256), p) for p in ctx]
    fp = FusionParams(voxel_size=0.04)
    rgb0, d0, _ = frames[0]
    vis = SourceVisibility(d0, ctx[0], 0.03)
    voxels = voxel_fusion(frames[1:], fp, keep_points=lambda p: ~vis.explained(p)).gaussians
    g = merge_gaussians([pixel_gaussians(rgb0, d0, ctx[0], replace(fp, scale_factor=VoxelFusionOptions().source_scale)),
                         voxels])
    plain = voxel_fusion(frames, fp).gaussians

    def score(gs, pose, H):  # against an anti-aliased reference: 4x supersampled, area-downsampled
        gt = cv2.resize(room(pose, 4 * H, 8 * H)[0], (2 * H, H), interpolation=cv2.INTER_AREA)
        out = render_erp(gs, pose, H, 2 * H)
        return psnr((out.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8), gt), float(out.alpha.mean())

    at_source, cov = score(g, ctx[0], 64)
    plain_at_source = score(plain, ctx[0], 64)[0]
    # Bounded by the renderer (EWA 0.3 px dilation, cube faces resampled bilinearly), not by the Gaussians: no better
    # than 4 cm voxels on this texture at 64 rows (docs/evaluation.md: numbers on the demo scenes).
    assert at_source > 24.0 and at_source > plain_at_source - 1.0 and cov > 0.98, (at_source, plain_at_source)
    novel, cov = score(g, pose_at(0.3, 0.05, -0.2), 64)
    assert novel > score(plain, pose_at(0.3, 0.05, -0.2), 64)[0] - 1.0 and cov > 0.98
    # The other frames add only what the source does not see (behind the block), not a second copy of the room.
    assert len(voxels) < 0.2 * len(plain)


def test_source_visibility_keeps_only_what_the_source_cannot_see():
    from panoworld.gaussians.pixel import SourceVisibility

    depth = np.full((32, 64), 2.0, np.float32)  # a sphere of radius 2 around the camera
    depth[:, :8] = np.nan  # no depth in a band of longitudes
    vis = SourceVisibility(depth, pose_at(0, 0, 0), 0.03)
    d = erp_dirs(32, 64, np.float64)[16, 32]  # a direction with depth
    d_none = erp_dirs(32, 64, np.float64)[16, 3]  # one without
    pts = np.stack([d * 2.0, d * 2.05, d * 1.0, d * 2.5, d_none * 2.0])
    assert vis.explained(pts).tolist() == [True, True, True, False, False]
    moved = SourceVisibility(depth, pose_at(0, 0, 1.0), 0.03)  # the source's pose is honoured
    assert moved.explained(pts + [0, 0, 1.0]).tolist() == [True, True, True, False, False]
    # a splat behind the surface pokes through it when it reaches it (3 x its largest scale)
    from panoworld.io.gaussian_set import Gaussians

    means = np.stack([d * 2.05, d * 2.05, d * 2.2, d_none * 2.05]).astype(np.float32)
    scales = np.array([[0.03, 0.001, 0.001], [0.01, 0.01, 0.001], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1]], np.float32)
    g = Gaussians(means, scales, np.tile(np.float32([1, 0, 0, 0]), (4, 1)), np.ones(4, np.float32), np.zeros((4, 3), np.float32))
    assert vis.poking_through(g).tolist() == [True, False, True, False]


def test_source_lookup_kernel_matches_its_numpy_reference():
    from scipy.spatial.transform import Rotation

    from panoworld.gaussians.pixel import SourceVisibility

    rng = np.random.default_rng(3)
    depth = rng.uniform(1.0, 5.0, (90, 180))
    depth[rng.random(depth.shape) < 0.1] = np.nan
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [0.1, 0.5, -0.2]).as_matrix()
    pose[:3, 3] = [0.3, -0.1, 0.2]
    vis = SourceVisibility(depth, pose, 0.03)
    seam = pose[:3, 3] + np.einsum("ij,mj->mi", pose[:3, :3], [[0, 0, -1], [0, 1e-9, -1], [1e-12, 0.5, -1]])
    pts = np.concatenate([rng.normal(size=(200_000, 3)) * 3.0, seam])
    dist, d_src = vis._lookup(pts)
    dist0, d_src0 = vis._lookup_reference(pts)
    np.testing.assert_allclose(dist, dist0, rtol=1e-14)
    assert np.array_equal(d_src, d_src0, equal_nan=True)
    # exactly at a pole the longitude is rounding noise in either; the row is the pole's
    poles = pose[:3, 3] + np.einsum("ij,mj->mi", pose[:3, :3], [[0, -1, 0], [0, 1, 0]])
    top, bottom = vis._lookup(poles)[1]
    assert np.isin(top, depth[0]) and np.isin(bottom, depth[-1])
    bad = vis._lookup(np.array([[np.nan, 0.0, 1.0], [np.inf, 0.0, 0.0]]))[1]  # no pixel, no depth (not a wrapped index)
    assert np.isnan(bad).all()


def test_source_lookup_fast_atan_equals_libm_bitwise():
    # _source_lookup takes the pixel from a polynomial atan2 away from pixel edges and libm's near them: the same
    # pixels as _source_lookup_exact everywhere, also for points on the pixel edges, the seam, the poles and the centre
    from scipy.spatial.transform import Rotation

    from panoworld.gaussians.pixel import _source_lookup, _source_lookup_exact

    rng = np.random.default_rng(5)
    h, w = 96, 192
    depth = rng.uniform(1.0, 5.0, (h, w))
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3] = Rotation.from_euler("xyz", [0.2, -0.4, 1.1]).as_matrix()
    cam_from_world[:3, 3] = [0.1, 0.3, -0.2]
    lon = (np.arange(w + 1) / w - 0.5) * 2 * np.pi  # every column edge and row edge, and just beside them
    lat = (0.5 - np.arange(h + 1) / h) * np.pi
    lon, lat = (np.concatenate([a, np.nextafter(a, np.inf), np.nextafter(a, -np.inf), a + 1e-10, a - 1e-10])
                for a in (lon, lat))
    lo, la = np.meshgrid(lon, lat)
    dirs = np.stack([np.cos(la) * np.sin(lo), -np.sin(la), np.cos(la) * np.cos(lo)], -1).reshape(-1, 3)
    cam = np.concatenate([dirs * rng.uniform(0.5, 4.0, (len(dirs), 1)), rng.normal(size=(300_000, 3)) * 3.0,
                          [[0, 0, 0], [0, 1, 0], [0, -2, 0], [0, 0, -1], [-0.0, 0, -1], [1e-300, 0, 1], [0, 0, 1e-300]]])
    inv = np.linalg.inv(cam_from_world)
    pts = np.ascontiguousarray(np.einsum("ij,mj->mi", inv[:3, :3], cam) + inv[:3, 3])
    out = [(np.empty(len(pts)), np.empty(len(pts))) for _ in range(2)]
    _source_lookup(pts, cam_from_world, depth, *out[0])
    _source_lookup_exact(pts, cam_from_world, depth, *out[1])
    assert np.array_equal(out[0][0], out[1][0])
    assert np.array_equal(out[0][1], out[1][1], equal_nan=True)


def test_frame_observations_filtered_before_footprints_equal_those_filtered_after(room):
    # keep_points drops pixels before their footprints are computed: the same observations, bit for bit, as computing
    # all of them and subsetting (depth edges at the block, a band without depth, the seam and the poles included).
    from panoworld.gaussians.pixel import SourceVisibility

    rgb0, d0 = room(pose_at(0, 0, 0), 48, 96)
    vis = SourceVisibility(d0, pose_at(0, 0, 0), 0.03)
    pose = pose_at(0.5, 0.1, 0.4)
    rgb, d = room(pose, 48, 96)
    d[:, 40:44] = np.nan
    fp = FusionParams(voxel_size=0.04)
    every = frame_observations(rgb, d, pose, fp)
    after = every.subset(torch.from_numpy(~vis.explained(every.points.numpy())))
    before = frame_observations(rgb, d, pose, fp, keep_points=lambda p: ~vis.explained(p))
    assert 0 < len(before.points) < (d > 0).sum() / 2
    for f in ("points", "colors", "steps", "weights", "pixels"):
        assert torch.equal(getattr(before, f), getattr(after, f)), f


def test_pole_thinning_keeps_about_square_pixels():
    from panoworld.gaussians.pixel import pole_thinning

    keep = pole_thinning(256, 512)
    assert keep[128].all() and keep[:, 0].all()  # the equator row and the first column are whole
    assert keep[0].sum() == 512 // 64  # at most W / 8 columns dropped per kept one
    lat = (np.arange(256) + 0.5) / 256 * np.pi - np.pi / 2
    width = 512 / keep.sum(1) * np.cos(lat)  # a kept pixel's width on the sphere, in row heights
    assert np.all((width[8:-8] > 0.5) & (width[8:-8] <= 1.0 + 1e-9))
    assert 0.75 < keep.mean() < 0.8


def test_resize_depth_keeps_smooth_surfaces_evenly_sampled_and_edges_sharp(room):
    from panoworld.geometry.resize import DEPTH_EDGE_REL, resize_depth

    pose = pose_at(0.2, 0.1, -0.3)
    _, d720 = room(pose, 180, 360)  # stored frames 180 rows, fused at 128 (the 720 -> 512 ratio)
    d = d720.copy()
    d[60:70, 100:110] = np.nan  # a hole in the depth
    _, exact = room(pose, 128, 256)
    out = resize_depth(d, 128, 256)
    nearest = cv2.resize(d, (256, 128), interpolation=cv2.INTER_NEAREST)
    ok = np.isfinite(out)
    # no depth made up: NaN where the nearest source pixel has none, never between a surface and a hole
    assert np.array_equal(ok, np.isfinite(nearest))
    # every value is a surface's depth (area mean on smooth surfaces, a source value at edges), none in between
    rel = np.abs(out[ok] / exact[ok] - 1.0)
    assert np.quantile(rel, 0.95) < 0.005
    off = rel > 0.02  # at depth edges: the nearest source pixel's depth, or a mean across a step under edge_rel
    assert off.mean() < 0.01 and np.all((out[ok][off] == nearest[ok][off]) | (rel[off] <= DEPTH_EDGE_REL))
    # nearest sampling puts pixels of a smooth surface off their ray's depth (every third row/column skipped)
    rel_n = np.abs(nearest[ok] / exact[ok] - 1.0)
    assert np.quantile(rel_n, 0.9) > 5 * np.quantile(rel, 0.9)


def test_colour_fit_at_the_capture_point_sharpens_it_and_keeps_other_views():
    # The render at the source pose is linear in the colours: fitting them to the source frame brings the render at
    # that pose closer to the frame and to the anti-aliased reference, and a view 0.4 m away gains too.
    from panoworld.gaussians.pixel import fit_colors, pixel_gaussians

    room = _room_renderer(textured_color)
    src = pose_at(0, 0, 0)
    rgb0, d0 = room(src, 128, 256)
    g = pixel_gaussians(rgb0, d0, src, FusionParams(voxel_size=0.04, scale_factor=1.9))
    fitted, info = fit_colors(g, rgb0, src, iters=10)
    assert info["rmse_after"] < 0.8 * info["rmse_before"], info
    assert np.array_equal(fitted.means, g.means) and np.array_equal(fitted.scales, g.scales)
    # its last render is that of the fitted Gaussians (the stage's self-check of frame 0 reuses it)
    again = render_erp(fitted, src, 128, 256, supersample=1)
    rgb, alpha = info["render"]
    assert np.abs(rgb - again.rgb.numpy()).max() < 1e-4 and np.abs(alpha - again.alpha.numpy()).max() < 1e-4

    def score(gs, pose, H=64):  # against an anti-aliased reference: 4x supersampled, area-downsampled
        gt = cv2.resize(room(pose, 4 * H, 8 * H)[0], (2 * H, H), interpolation=cv2.INTER_AREA)
        return psnr((render_erp(gs, pose, H, 2 * H).rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8), gt)

    before, after = score(g, src), score(fitted, src)
    assert after > before + 3.0, (before, after)  # 30.3 -> 40.0 dB
    away = pose_at(0.3, 0.05, -0.25)
    assert score(fitted, away) > score(g, away) + 1.0  # 28.7 -> 32.8 dB: sharper colours, not overfitted to one view


def test_colour_fit_with_views_from_aside_fits_them_and_a_zero_weight_view_changes_nothing():
    # A second view 0.4 m away joins the fit: the render there gets closer to its frame than with the capture point
    # alone; the same view at weight 0 gives the capture-only fit exactly.
    from panoworld.gaussians.pixel import fit_colors, pixel_gaussians

    room = _room_renderer(textured_color)
    src, away = pose_at(0, 0, 0), pose_at(0.3, 0.05, -0.25)
    rgb0, d0 = room(src, 128, 256)
    rgb1 = room(away, 64, 128)[0]
    g = pixel_gaussians(rgb0, d0, src, FusionParams(voxel_size=0.04, scale_factor=1.9))
    alone, _ = fit_colors(g, rgb0, src, iters=10)
    both, _ = fit_colors(g, rgb0, src, iters=10, extra=[(rgb1, away, np.ones((64, 128), np.float32))])
    muted, _ = fit_colors(g, rgb0, src, iters=10, extra=[(rgb1, away, np.zeros((64, 128), np.float32))])
    assert np.allclose(muted.sh_dc, alone.sh_dc, atol=1e-6)

    def score(gs, pose, ref):
        img = (render_erp(gs, pose, ref.shape[0], ref.shape[1], supersample=1).rgb.clamp(0, 1).numpy() * 255)
        return psnr(img.round().astype(np.uint8), ref)

    assert score(both, away, rgb1) > score(alone, away, rgb1) + 0.5
    # the capture point gives some of its fit away (35.9 -> 34.3 dB) but keeps most of it over the unfitted colours
    assert score(both, src, rgb0) > score(g, src, rgb0) + 2.0


def test_spread_frames_picks_the_farthest_then_spreads():
    from panoworld.gaussians.pixel import spread_frames

    c = np.array([[0.5, 0, 0], [2.0, 0, 0], [1.9, 0, 0.1], [-1.5, 0, 0], [0, 0, 1.0]])
    assert spread_frames(c, 3) == [1, 3, 4]
    assert spread_frames(c, 9) == spread_frames(c, 5) and sorted(spread_frames(c, 5)) == [0, 1, 2, 3, 4]


def test_views_from_aside_weigh_what_the_source_saw_and_reach_the_stage(tmp_path, room):
    from panoworld.framework.stage import execute_stage, load_stage
    from panoworld.gaussians.fusion import context_source
    from panoworld.gaussians.pixel import SourceVisibility, view_targets

    video, poses = write_inputs(tmp_path, room)
    src = context_source(video, poses)
    _, d0, p0 = src.frame(0)
    rest = replace(src, rgb_paths=src.rgb_paths[1:], depth_paths=src.depth_paths[1:],
                   world_from_cam=src.world_from_cam[1:], indices=src.indices[1:])
    vis = SourceVisibility(d0, p0, 0.03)
    (img, pose, w), = view_targets(rest, vis, 3, 32)  # one other registered frame, 0.5 m away
    assert img.shape == (32, 64, 3) and w.shape == (32, 64) and np.array_equal(pose, rest.world_from_cam[0])
    _, d1, _ = replace(rest, height=32).frame(0)
    pts = (erp_dirs(32, 64, np.float64) * np.nan_to_num(d1)[..., None]).reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
    seen = (np.isfinite(d1) & (d1 > 0)).reshape(-1) & vis.explained(pts)
    assert np.array_equal(w.reshape(-1) > 0, seen) and 0.5 < w.mean() < 1.0  # the block hides some of the room
    assert view_targets(rest, vis, 3, 32, reach=0.4) == []
    info = execute_stage(load_stage("gaussians"), {"video": video, "poses": poses},
                         _params(voxel_size=0.05, eval_views=0, fit_views=2, fit_view_height=32, fit_sh_degree=1),
                         tmp_path / "out", input_digests={"video": "0" * 64, "poses": "1" * 64})["info"]
    assert info["color_fit"]["views_from_aside"] == 1 and info["color_fit"]["sh_degree"] == 1
    from panoworld.io.splat_ply import read_gaussians_ply

    g = read_gaussians_ply(tmp_path / "out" / "gaussians.ply")  # the view-dependent colours reach the .ply
    assert g.sh_degree == info["sh_degree"] == 1 and np.abs(g.sh_rest).max() > 0


def test_frames_that_add_nothing_leave_the_source_gaussians(tmp_path, room):
    # Every other frame's depth is unknown (0): nothing is left to fuse, and the source view's own Gaussians are the
    # scene (a valid .ply, no error).
    from panoworld.framework.stage import execute_stage, load_stage
    from panoworld.io.splat_ply import read_gaussians_ply

    video, poses = write_inputs(tmp_path, room)
    for p in sorted((video / "depth").iterdir())[1:]:
        cv2.imwrite(str(p), np.zeros((64, 128), np.uint16))
    out = tmp_path / "out"
    info = execute_stage(load_stage("gaussians"), {"video": video, "poses": poses},
                         _params(voxel_size=0.05, eval_views=1, fit_iters=0), out,
                         input_digests={"video": "0" * 64, "poses": "1" * 64})["info"]
    g = read_gaussians_ply(out / "gaussians.ply")
    assert info["num_gaussians"] == info["num_source_gaussians"] == len(g) > 1000
    assert info["context_psnr"] > 25


def test_a_home_whose_frames_the_panoramas_explain_fuses_no_voxel(room):
    # The frames stand where the panoramas stand and see only what they see: the home's Gaussians are the panoramas'
    # own, and frames with no depth at all add nothing either.
    from panoworld.gaussians.fusion_params import SourcePixelParams
    from panoworld.gaussians.home import home_anchored_fusion

    poses = [pose_at(0, 0, 0), pose_at(0.8, 0.1, -0.9)]
    sources = {f"p{k}": (*room(p), p) for k, p in enumerate(poses)}
    frames = [(*room(p), p) for p in poses]
    params = SourcePixelParams(voxel_size=0.05, unseen_voxel_size=0.05, source_height=0, capture_fit_iters=0)
    res = home_anchored_fusion(frames, sources, params)
    assert len(res.gaussians) == res.num_source > 1000 and res.num_voxels == 0
    blind = [(rgb, np.zeros_like(d), p) for rgb, d, p in frames]
    res2 = home_anchored_fusion(blind, sources, params)
    assert len(res2.gaussians) == len(res.gaussians) and np.array_equal(res2.gaussians.means, res.gaussians.means)
