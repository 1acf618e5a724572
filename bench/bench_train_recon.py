"""Trained PanoVGGT vs its random init (vs COLMAP, vs voxel-fusion) on held-out synthetic scenes (issue #14).

    python bench/bench_train_recon.py --data DATASET_DIR --held-out 4 --stage1 RUN1/export/weights \
        [--stage2 RUN2/export/weights] [--colmap-scenes 2] [--frames 8] [--views 3]

Held-out scenes are the last --held-out scenes of DATASET_DIR (a training run's val split never trains). Stage 1: per
scene and track, --frames frames evenly spaced along the track -> ATE, RPE_t (m), RPE_r (deg) after Sim(3) alignment
(align.trajectory_metrics) and depth AbsRel (evaluate.depth_errors), for the trained model and the same architecture
at its random init (the training seed), each with the camera head's poses alone and with --refine-iters steps of
depth-consistency refinement on the model's own depth (PanoVGGTConfig.pose_refine_iters), an image-blind straight-
ahead prior (equal steps along the first camera's axis: what "the track starts looking ahead" alone gives) and COLMAP
(first --colmap-scenes scenes, the same frames rendered exactly at --colmap-height: COLMAP registers nothing at the
models' 32x64); then again with every track's cameras turned by one random yaw, so the direction of travel must be
read from the images.
Stage 2: N@N = --views context frames evenly spaced and the --views frames midway between them as
novel views; PSNR/SSIM of ERP renders at the model's input size, for the trained Gaussian head, the same head at its
random init (on the trained backbone) and voxel-fusion at the same voxel size, all given the same geometry (the ground
truth's, and the frozen heads' predictions for the decoders).
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np
import torch

from panoworld.align import trajectory_metrics
from panoworld.dataset import DatasetScene
from panoworld.evaluate import depth_errors
from panoworld.metrics import psnr, ssim
from panoworld.models.panovggt import PanoVGGT, PanoVGGTConfig
from panoworld.render_gs import render_erp
from panoworld.train.recon.data import SceneFrames, list_scenes, roll_yaw


def random_init(trained: PanoVGGT, seed: int, keep_trained_backbone: bool) -> PanoVGGT:
    torch.manual_seed(seed)
    model = PanoVGGT(PanoVGGTConfig.from_json(trained.cfg.to_json()))
    if keep_trained_backbone:  # stage 2's init: the trained stage-1 model plus a fresh head
        state = {k: v for k, v in trained.state_dict().items() if not k.startswith("gaussian_head.")}
        model.load_state_dict(state, strict=False)
    return model.eval()


def with_refinement(model: PanoVGGT, iterations: int) -> PanoVGGT:
    """The same weights with PanoVGGTConfig.pose_refine_iters set (0 = the camera head's poses alone)."""
    out = copy.deepcopy(model)
    out.cfg.pose_refine_iters = iterations
    return out


def evenly(n: int, k: int) -> np.ndarray:
    return np.unique(np.round(np.linspace(0, n - 1, min(n, k))).astype(int))


def straight_ahead(n: int) -> np.ndarray:
    """The image-blind prior of the synthetic tracks (cameras start looking along the path): n upright poses equally
    spaced along the first camera's forward (+z) axis; Sim(3) alignment makes the spacing's scale irrelevant."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.linspace(0.0, 1.0, n)
    return poses


def stage1_rows(models: dict[str, PanoVGGT], data: SceneFrames, frames: int, colmap_scenes: int,
                colmap_height: int, turned: bool = False, seed: int = 0) -> list[dict]:
    """turned: every track's cameras turned by one random yaw (roll_yaw, as yaw_augment=shared), so the direction of
    travel in the first camera is no longer 'forward' and must be read from the images."""
    rows = []
    rng = np.random.default_rng([seed, 14])
    for s, scene in enumerate(data.scenes):
        for track in range(scene.n_tracks):
            idx = evenly(scene.n_frames(track), frames)
            poses = data.poses(s, track)[idx]
            rgb, depth = map(np.stack, zip(*(data.frame(s, track, int(i)) for i in idx)))
            if turned:
                k = int(rng.integers(rgb.shape[2]))
                rgb, depth, poses = map(np.stack, zip(*(roll_yaw(c, d, p, k) for c, d, p in zip(rgb, depth, poses))))
            gt = np.linalg.inv(poses[0]) @ poses
            tm = trajectory_metrics(straight_ahead(len(idx)), gt)
            rows.append({"method": "straight-ahead prior (no image)", "scene": scene.name, "track": track,
                         "ate": tm["ate"], "rpe_t": tm["rpe_t"], "rpe_r": tm["rpe_r"]})
            for name, model in models.items():
                t0 = time.process_time()
                pred = model.predict(rgb)
                tm = trajectory_metrics(pred["world_from_cam"], gt)
                absrel = float(np.mean([depth_errors(p, g)["abs_rel"] for p, g in zip(pred["depth"], depth)]))
                rows.append({"method": name, "scene": scene.name, "track": track, "ate": tm["ate"],
                             "rpe_t": tm["rpe_t"], "rpe_r": tm["rpe_r"], "abs_rel": absrel,
                             "cpu_s": time.process_time() - t0})
            if s < colmap_scenes and not turned:
                rows.append({"method": "colmap", "scene": scene.name, "track": track,
                             **colmap_row(scene, track, idx, gt, colmap_height)})
    return rows


def colmap_row(scene: DatasetScene, track: int, idx: np.ndarray, gt: np.ndarray, height: int) -> dict:
    """COLMAP (poses.colmap_estimate, spherical) on the track's frames rendered exactly at `height`."""
    import tempfile

    import cv2

    from panoworld.poses import colmap_estimate
    from panoworld.synth import SynthScene

    synth = SynthScene.load(scene.gt_dir)
    poses = scene.poses(track)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-colmap-") as tmp:
        paths = []
        for i in idx:
            rgb, _ = synth.render(poses[int(i)], height, 2 * height)
            paths.append(Path(tmp) / f"{int(i):06d}.png")
            cv2.imwrite(str(paths[-1]), rgb[..., ::-1])
        try:
            est = colmap_estimate(paths, gt)
        except Exception as e:  # report, do not hide, a failed baseline
            return {"error": f"{type(e).__name__}: {e}"[:200]}
    reg = np.asarray(est.registered, bool)
    tm = trajectory_metrics(est.raw[reg], gt[reg]) if reg.sum() >= 3 else {"ate": np.nan, "rpe_t": np.nan, "rpe_r": np.nan}
    return {"ate": tm["ate"], "rpe_t": tm["rpe_t"], "rpe_r": tm["rpe_r"], "registered": f"{int(reg.sum())}/{len(reg)}",
            "wall_s": time.perf_counter() - t0}


def _scores(g, poses: np.ndarray, rgb: np.ndarray, h: int) -> tuple[float, float]:
    p, s = [], []
    for pose, ref in zip(poses, rgb):
        img = (render_erp(g, pose, h, 2 * h).rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        p.append(psnr(img, ref))
        s.append(ssim(img, ref))
    return float(np.mean(p)), float(np.mean(s))


@torch.no_grad()
def stage2_rows(models: dict[str, PanoVGGT], data: SceneFrames, views: int, voxel_size: float) -> list[dict]:
    from panoworld.fusion_params import FusionParams
    from panoworld.gaussians import voxel_fusion

    rows = []
    for s, scene in enumerate(data.scenes):
        for track in range(scene.n_tracks):
            n = scene.n_frames(track)
            ctx = evenly(n, views)
            nov = np.unique((ctx[:-1] + ctx[1:]) // 2)
            nov = np.setdiff1d(nov, ctx)
            poses_all = data.poses(s, track)
            rel = np.linalg.inv(poses_all[ctx[0]]) @ poses_all
            rgb = {int(i): data.frame(s, track, int(i))[0] for i in np.concatenate([ctx, nov])}
            dep = {int(i): data.frame(s, track, int(i))[1] for i in ctx}
            c_rgb = np.stack([rgb[int(i)] for i in ctx])
            n_rgb = np.stack([rgb[int(i)] for i in nov])
            h = c_rgb.shape[1]
            img = torch.from_numpy(c_rgb).permute(0, 3, 1, 2).float() / 255
            gt_geo = (torch.from_numpy(np.stack([dep[int(i)] for i in ctx])), torch.from_numpy(rel[ctx]))
            methods = {}
            for name, model in models.items():
                methods[f"{name} (gt geometry)"] = lambda m=model, img=img, gt_geo=gt_geo: m.gaussians(img, *gt_geo)["gaussians"].numpy()
                methods[f"{name} (predicted geometry)"] = lambda m=model, img=img: m.gaussians(img)["gaussians"].numpy()
            methods["voxel-fusion (gt geometry)"] = lambda c_rgb=c_rgb, gt_geo=gt_geo, rel=rel, ctx=ctx: voxel_fusion(
                zip(c_rgb, gt_geo[0].numpy(), rel[ctx]), FusionParams(voxel_size=voxel_size)).gaussians
            for name, make in methods.items():
                t0 = time.process_time()
                g = make()
                pc, sc = _scores(g, rel[ctx], c_rgb, h)
                pn, sn = _scores(g, rel[nov], n_rgb, h)
                rows.append({"method": name, "scene": scene.name, "track": track, "psnr_context": pc,
                             "ssim_context": sc, "psnr_novel": pn, "ssim_novel": sn, "gaussians": len(g),
                             "cpu_s": time.process_time() - t0})
    return rows


def table(rows: list[dict], keys: list[str]) -> str:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    out = ["| method | n | " + " | ".join(keys) + " |", "|---" * (len(keys) + 2) + "|"]
    for m in methods:
        sel = [r for r in rows if r["method"] == m and "error" not in r]
        cols = [[r[k] for r in sel if np.isfinite(r.get(k, np.nan))] for k in keys]
        out.append(f"| {m} | {len(sel)} | " + " | ".join(f"{np.mean(c):.4g}" if c else "–" for c in cols) + " |")
    errors = [r for r in rows if "error" in r]
    out += [f"  {r['method']} {r['scene']} track {r['track']}: {r['error']}" for r in errors]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--held-out", type=int, default=4, help="the last K scenes of --data (a run's val split)")
    p.add_argument("--stage1", type=Path, required=True, help="stage-1 export (weights dir)")
    p.add_argument("--stage2", type=Path, help="stage-2 export (weights dir)")
    p.add_argument("--seed", type=int, default=0, help="the training runs' seed (their random init)")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--views", type=int, default=3, help="N of N@N")
    p.add_argument("--colmap-scenes", type=int, default=2)
    p.add_argument("--colmap-height", type=int, default=256, help="ERP height COLMAP gets (rendered exactly)")
    p.add_argument("--stage2-scenes", type=int, default=0, help="stage 2 on the first K held-out scenes only (0 = all)")
    p.add_argument("--skip-stage1", action="store_true", help="stage 2 only (stage 1 still loads --stage1)")
    p.add_argument("--refine-iters", type=int, default=20,
                   help="depth-consistency pose refinement steps of the '+ refinement' rows (0 = no such rows)")
    p.add_argument("--json", type=Path, help="also write every row here")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    trained1 = PanoVGGT.from_pretrained(args.stage1, flag="--stage1")
    data = SceneFrames(list_scenes(args.data)[-args.held_out:], trained1.cfg.image_height)
    print(f"held-out scenes: {[s.name for s in data.scenes]} at {trained1.cfg.image_height}x{2 * trained1.cfg.image_height}")
    rows = {}
    if not args.skip_stage1:
        init = random_init(trained1, args.seed, False)
        models = {"trained, camera head": with_refinement(trained1, 0), "random init": with_refinement(init, 0)}
        if args.refine_iters:
            models[f"trained + refinement ({args.refine_iters} steps)"] = with_refinement(trained1, args.refine_iters)
            models[f"random init + refinement ({args.refine_iters} steps)"] = with_refinement(init, args.refine_iters)
        for turned in (False, True):
            r1 = stage1_rows(models, data, args.frames, args.colmap_scenes, args.colmap_height, turned, args.seed)
            how = "each track turned by a random yaw" if turned else "tracks as rendered (cameras start looking ahead)"
            print(f"\nstage 1, {how}: {args.frames} frames per track, ATE / RPE_t in metres, RPE_r in degrees "
                  "(Sim(3)-aligned)")
            print(table(r1, ["ate", "rpe_t", "rpe_r", "abs_rel"]))
            rows["stage1_turned" if turned else "stage1"] = r1
    if args.stage2:
        trained2 = PanoVGGT.from_pretrained(args.stage2, flag="--stage2")
        vs = trained2.require_gaussian_head("--stage2").cfg.voxel_size
        if args.stage2_scenes:
            data.scenes = data.scenes[: args.stage2_scenes]
        r2 = stage2_rows({"decoder": trained2, "decoder init": random_init(trained2, args.seed, True)}, data,
                         args.views, vs)
        print(f"\nstage 2: {args.views}@{args.views} (context @ novel views), voxel size {vs} m, "
              f"renders at {trained2.cfg.image_height}x{2 * trained2.cfg.image_height}")
        print(table(r2, ["psnr_context", "ssim_context", "psnr_novel", "ssim_novel", "gaussians"]))
        rows["stage2"] = r2
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
