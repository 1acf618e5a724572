"""Trained PanoVGGT vs its random init on a train / val / test split by scene that the bench builds from seeds.

    python bench/bench_train_recon.py --quick --out WORK [--json recon.json] [--resume]     # <= 15 min on 2 cores
    python bench/bench_train_recon.py --medium --out WORK [--json recon.json] [--resume]    # quick + 2 warm restarts
    python bench/bench_train_recon.py --full --out WORK [--json recon.json] [--resume]
    python bench/bench_train_recon.py --data DATASET_DIR --held-out 4 --stage1 RUN1/export/weights \
        [--stage2 RUN2/export/weights] [--colmap-scenes 2]                                 # evaluate given exports

--quick / --full: `synth` writes WORK/train, WORK/val and WORK/test from three seeds (the scene seeds are checked to be
disjoint), WORK/trainval links train then val (the trainer's val split = the last val_scenes by name), `train recon`
runs stage 1 and stage 2 on it, and both exports and their random init are scored on the val and the test split.
Tuning happens on val only; the headline is the paper's feed-forward model (refine_iters 0) on test; the
depth-consistency refinement (refine_iters > 0) is an option that is not in the paper. Rows: model trained | init,
refine_iters, split -> ATE, RPE_t (m), RPE_r (deg) after Sim(3) alignment, depth AbsRel, novel-view PSNR (stage 2's
head on predicted geometry; the refinement does not change it).

Given exports (--data/--stage1): stage 1 per scene and track on --frames frames evenly spaced -> the metrics above for
the trained model and its random init, with and without refinement, an image-blind straight-ahead prior and COLMAP
(first --colmap-scenes scenes rendered exactly at --colmap-height), also with every track turned by a random yaw;
stage 2: N@N = --views context frames and the frames midway as novel views, PSNR/SSIM of ERP renders for the trained
head, its init and voxel-fusion, on ground-truth and predicted geometry.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.geometry.align import trajectory_metrics
from panoworld.models.panovggt import PanoVGGT
from panoworld.models.panovggt_config import PanoVGGTConfig
from panoworld.render.erp import render_erp
from panoworld.render.metrics import psnr, ssim
from panoworld.tools.dataset import DatasetScene
from panoworld.tools.eval.cli import depth_errors
from panoworld.tools.train.recon.data import SceneFrames, list_scenes, roll_yaw


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

    from panoworld.poses.estimate import colmap_estimate
    from panoworld.tools.synth import SynthScene

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
    from panoworld.gaussians.fusion import voxel_fusion
    from panoworld.gaussians.fusion_params import FusionParams

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


MODES = {
    # scenes per split, the synth seed of each split (test: a seed no earlier run has seen), stage steps
    "quick": {"train": 60, "val": 6, "test": 8, "seeds": (7, 8, 2026), "steps1": 3000, "steps2": 50, "s2_scenes": 4},
    # medium: quick's data and first stage-1 run, then `restarts` more runs of steps1 from the previous export
    # (a warm restart: fresh AdamW, warm-up and cosine, the next batch seed); quick's run1 is reused with --resume.
    # restarts 2 picked on val (val ATE ratio: 0 -> 2.63x, 1 -> 2.87x, 2 -> 3.27x)
    "medium": {"train": 60, "val": 6, "test": 8, "seeds": (7, 8, 2026), "steps1": 3000, "restarts": 2, "steps2": 50,
               "s2_scenes": 4},
    "full": {"train": 168, "val": 12, "test": 24, "seeds": (7, 8, 2026), "steps1": 12000, "steps2": 500,
             "s2_scenes": 8},
}
SYNTH_FRAMES = 24
REFINE = 20


def scene_seeds(seed: int, n: int) -> list[int]:
    from panoworld.tools.synth.generate import derive_seed

    return [derive_seed(seed, 1, k) for k in range(n)]


def build_split(work: Path, mode: dict, resume: bool) -> dict[str, list[int]]:
    """WORK/{train,val,test} from seeds and WORK/trainval (train, then val, by name); the scene seeds per split."""
    from panoworld.tools.synth.cli import main as synth

    seeds = {split: scene_seeds(s, mode[split]) for split, s in zip(("train", "val", "test"), mode["seeds"])}
    for a, b in (("train", "val"), ("train", "test"), ("val", "test")):
        if set(seeds[a]) & set(seeds[b]):
            raise SystemExit(f"scene seeds of {a} and {b} overlap; pick other split seeds")
    for split, s in zip(("train", "val", "test"), mode["seeds"]):
        d = work / split
        done = resume and len(list_scenes_or_none(d)) == mode[split]
        args = [str(d), "--seed", str(s), "--scenes", str(mode[split]), "--preset", "ci-tiny",
                "--frames", str(SYNTH_FRAMES)]
        if not done and synth(args) != 0:
            raise SystemExit(f"synth {d} failed")
    tv = work / "trainval"
    tv.mkdir(parents=True, exist_ok=True)
    for split in ("train", "val"):
        for k, scene in enumerate(sorted((work / split).glob("scene_*"))):
            link = tv / f"{split}_{k:04d}"  # "train_" sorts before "val_": the val scenes are the last by name
            if not link.exists():
                link.symlink_to(scene.resolve(), target_is_directory=True)
    return seeds


def list_scenes_or_none(d: Path) -> list[Path]:
    return sorted(p for p in d.glob("scene_*") if (p / "gt" / "gt.json").is_file()) if d.is_dir() else []


def train(work: Path, mode: dict, resume: bool) -> tuple[Path, Path]:
    from panoworld.tools.train.recon.cli import main as train_recon
    from panoworld.tools.train.recon.data import split_scenes

    tv = work / "trainval"
    _, val = split_scenes(list_scenes(tv), mode["val"])
    assert all(p.name.startswith("val_") for p in val), "the trainer's validation scenes must be the val split"
    sets = ["--set", f"val_scenes={mode['val']}", "--set", "num_threads=1"]
    run1, run2 = work / "run1", work / "run2"
    init: list[str] = []
    for k in range(1 + mode.get("restarts", 0)):
        run = run1 if k == 0 else work / f"run1_restart{k}"
        if not (resume and (run / "export" / "weights").is_dir()):
            args = ["--stage", "1", "--data", str(tv), "--out", str(run), "--no-progress", *sets, *init,
                    "--set", f"steps={mode['steps1']}", "--set", f"seed={k}"]
            if train_recon(args + (["--resume"] if (run / "config.yaml").is_file() else [])) != 0:
                raise SystemExit(f"train recon --stage 1 failed ({run})")
        init = ["--init", str(run / "export" / "weights")]
    run1 = run
    if mode["steps2"] and not (resume and (run2 / "export" / "weights").is_dir()):
        args = ["--stage", "2", "--data", str(tv), "--out", str(run2), "--init", str(run1 / "export" / "weights"),
                "--no-progress", *sets, "--set", f"steps={mode['steps2']}"]
        if train_recon(args + (["--resume"] if (run2 / "config.yaml").is_file() else [])) != 0:
            raise SystemExit("train recon --stage 2 failed")
    return run1 / "export" / "weights", run2 / "export" / "weights"


@torch.no_grad()
def novel_psnr(model: PanoVGGT, data: SceneFrames, views: int) -> float:
    """Mean PSNR of the head's Gaussians (predicted geometry, as trained) rendered at the views midway between
    `views` evenly spaced context frames, against the ground-truth frames."""
    out = []
    for s, scene in enumerate(data.scenes):
        for track in range(scene.n_tracks):
            ctx = evenly(scene.n_frames(track), views)
            nov = np.setdiff1d(np.unique((ctx[:-1] + ctx[1:]) // 2), ctx)
            poses = data.poses(s, track)
            rel = np.linalg.inv(poses[ctx[0]]) @ poses
            c_rgb = np.stack([data.frame(s, track, int(i))[0] for i in ctx])
            n_rgb = np.stack([data.frame(s, track, int(i))[0] for i in nov])
            g = model.gaussians(torch.from_numpy(c_rgb).permute(0, 3, 1, 2).float() / 255)["gaussians"].numpy()
            out.append(_scores(g, rel[nov], n_rgb, c_rgb.shape[1])[0])
    return float(np.mean(out))


def split_rows(models: dict[str, PanoVGGT], heads: dict[str, PanoVGGT | None], data: SceneFrames, split: str,
               frames: int, s2_scenes: int, views: int, refine: int = REFINE) -> list[dict]:
    """One row per (model, refine_iters) on one split (refine_iters 0 and `refine`, unless that is 0): metrics
    averaged over every track."""
    iters = (0, refine) if refine else (0,)
    variants = {f"{m}|{r}": with_refinement(model, r) for m, model in models.items() for r in iters}
    per_track = stage1_rows(variants, data, frames, colmap_scenes=0, colmap_height=0)
    sub = SceneFrames([sc.root for sc in data.scenes[:s2_scenes]], data.height)
    rows = []
    for m in models:
        nv = novel_psnr(heads[m], sub, views) if heads.get(m) is not None else None
        for r in iters:
            sel = [x for x in per_track if x["method"] == f"{m}|{r}"]
            rows.append({"model": m, "refine_iters": r, "split": split, "in_paper": r == 0,
                         **{k: float(np.mean([x[k] for x in sel])) for k in ("ate", "rpe_t", "rpe_r", "abs_rel")},
                         "novel_psnr": nv, "tracks": len(sel)})
    return rows


def bench(mode_name: str, work: Path, resume: bool, seed: int, frames: int, views: int,
          stage2: bool = True, refine: int = REFINE) -> dict:
    mode = dict(MODES[mode_name], **({} if stage2 else {"steps2": 0}))
    t0, c0 = time.perf_counter(), time.process_time()
    seeds = build_split(work, mode, resume)
    w1, w2 = train(work, mode, resume)
    trained1 = PanoVGGT.from_pretrained(w1, flag="--stage1")
    trained2 = PanoVGGT.from_pretrained(w2, flag="--stage2") if mode["steps2"] else None
    models = {"trained": trained1, "init": random_init(trained1, seed, False)}
    heads = {"trained": trained2, "init": random_init(trained2, seed, False) if trained2 is not None else None}
    rows = []
    for split in ("val", "test"):
        data = SceneFrames(list_scenes(work / split), trained1.cfg.image_height)
        rows += split_rows(models, heads, data, split, frames, mode["s2_scenes"], views, refine)
    return {"mode": mode_name, "rows": rows, "train_scenes": seeds["train"], "val_scenes": seeds["val"],
            "test_scenes": seeds["test"], "split_seeds": dict(zip(("train", "val", "test"), mode["seeds"])),
            "steps": {"stage1": mode["steps1"], "stage1_restarts": mode.get("restarts", 0), "stage2": mode["steps2"]},
            "wall_s": round(time.perf_counter() - t0, 1), "cpu_s": round(time.process_time() - c0, 1)}


def print_rows(result: dict) -> None:
    print(f"\n{result['mode']}: {len(result['train_scenes'])} train / {len(result['val_scenes'])} val / "
          f"{len(result['test_scenes'])} test scenes; {result['wall_s']:.0f} s wall, {result['cpu_s']:.0f} s CPU")
    print("| split | model | refine_iters | ATE (m) | RPE_t (m) | RPE_r (deg) | AbsRel | novel PSNR (dB) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in result["rows"]:
        nv = "-" if r["novel_psnr"] is None else f"{r['novel_psnr']:.2f}"
        print(f"| {r['split']} | {r['model']} | {r['refine_iters']} | {r['ate']:.4f} | {r['rpe_t']:.4f} | "
              f"{r['rpe_r']:.2f} | {r['abs_rel']:.3f} | {nv} |")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--quick", action="store_true", help="build, train and score the quick split (<= 15 min)")
    g.add_argument("--medium", action="store_true",
                   help="quick's split, stage 1 3000 steps + two 3000-step warm restarts (about 2x quick's CPU)")
    g.add_argument("--full", action="store_true", help="build, train and score the full split")
    g.add_argument("--data", type=Path, help="evaluate given exports on the last --held-out scenes of this dataset")
    p.add_argument("--out", type=Path, help="--quick/--full: the work directory (data, runs)")
    p.add_argument("--resume", action="store_true", help="--quick/--full: reuse finished data and runs in --out")
    p.add_argument("--no-stage2", action="store_true", help="--quick/--full: stage 1 only (novel PSNR not scored)")
    p.add_argument("--held-out", type=int, default=4, help="the last K scenes of --data (a run's val split)")
    p.add_argument("--stage1", type=Path, help="stage-1 export (weights dir)")
    p.add_argument("--stage2", type=Path, help="stage-2 export (weights dir)")
    p.add_argument("--seed", type=int, default=0, help="the training runs' seed (their random init)")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--views", type=int, default=3, help="N of N@N")
    p.add_argument("--colmap-scenes", type=int, default=2)
    p.add_argument("--colmap-height", type=int, default=256, help="ERP height COLMAP gets (rendered exactly)")
    p.add_argument("--stage2-scenes", type=int, default=0, help="stage 2 on the first K held-out scenes only (0 = all)")
    p.add_argument("--skip-stage1", action="store_true", help="stage 2 only (stage 1 still loads --stage1)")
    p.add_argument("--refine-iters", type=int, default=REFINE,
                   help="depth-consistency pose refinement steps of the '+ refinement' rows (0 = no such rows; "
                        "--quick/--full too)")
    p.add_argument("--json", type=Path, help="also write every row here")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    if args.quick or args.medium or args.full:
        if args.out is None:
            p.error("--quick/--medium/--full need --out WORK_DIR")
        result = bench("quick" if args.quick else "medium" if args.medium else "full", args.out, args.resume, args.seed, args.frames, args.views,
                       stage2=not args.no_stage2, refine=args.refine_iters)
        print_rows(result)
        if args.json:
            args.json.write_text(json.dumps(result, indent=1))
        return 0
    if args.stage1 is None:
        p.error("--data needs --stage1 RUN1/export/weights")
    return evaluate_exports(args)


def evaluate_exports(args) -> int:
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
