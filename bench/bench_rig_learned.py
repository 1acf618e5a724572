"""The learned rig detector: train the rig U-Net on synthetic scenes, compare it with the heuristic on held-out seeds.

    python bench/bench_rig_learned.py --quick --out /tmp/rig-unet [--json]
    python bench/bench_rig_learned.py --weights /tmp/rig-unet           # evaluate saved weights only

Training seeds 200-215 (--quick, 400 steps) or 200-263 (--full); held-out test seeds 116-131 (never used for training or
tuning). Per case (tripod, tripod with a soft shadow; no rig, rug, stool as controls): the ERP IoU of each detector's
mask with the rig's own pixels (ray hits the rig), the 15-degree nadir-cap PSNR after removal against the rig-free
render, and detections on the controls (must be 0). The weights go to --out (config.json + model.safetensors), to
be used with --set depth.rig_detector=learned --set depth.rig_weights=DIR.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.bench_rig import parse_seeds
from panoworld.depth.rig import detect as rig
from panoworld.depth.rig import remove as rig_remove
from panoworld.depth.rig.learned import detect_rig_learned

CASES = ("tripod", "tripod-shadow", "none", "rug", "stool")


def evaluate(seeds: list[int], weights: Path, height: int) -> list[dict]:
    from panoworld.tools.synth import generate_scene
    from panoworld.tools.synth.rig import FloorObject, render_with_rig, with_floor_object

    rows = []
    for seed in seeds:
        scene = generate_scene(seed, "ci-tiny")
        clean, cdepth = scene.render(scene.world_from_canonical, height, 2 * height)
        for case in CASES:
            if case in ("rug", "stool"):
                s = with_floor_object(scene, FloorObject(case))
                rgb, depth = s.render(s.world_from_canonical, height, 2 * height)
                geom = np.zeros(depth.shape, bool)
            else:
                rgb, depth, _ = render_with_rig(scene, case, height)
                geom = depth < cdepth - 1e-3
            valid = np.isfinite(depth) & (depth > 0)
            floor_m = scene.tracks[0].camera_height
            for name, det in (("heuristic", rig.detect_rig(rgb, depth, valid, floor_m)),
                              ("learned", detect_rig_learned(rgb, depth, valid, floor_m, weights=weights))):
                r = {"seed": seed, "case": case, "detector": name, "found": det.found}
                if geom.any():
                    m = det.mask if det.found else np.zeros_like(geom)
                    r["iou"] = float((m & geom).sum() / max((m | geom).sum(), 1))
                    r["psnr_after"] = rig_remove.nadir_cap_psnr(rig_remove.remove_rig(rgb, det) if det.found else rgb, clean)
                rows.append(r)
        print(f"seed {seed} done", file=sys.stderr, flush=True)
    return rows


def cached_samples(seeds, height: int, cache: Path) -> list:
    """rig_samples of every seed, rendered once and kept in cache/seed_N_H.npz."""
    from panoworld.tools.train.rig import RigSample, rig_samples

    out = []
    cache.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        f = cache / f"seed_{seed}_{height}.npz"
        if not f.is_file():
            ss = rig_samples(seed, height)
            np.savez_compressed(f, faces=np.stack([s.face for s in ss]), targets=np.stack([s.target for s in ss]),
                                cases=np.array([s.case for s in ss]))
        d = np.load(f)
        out += [RigSample(fa, t, str(c), seed) for fa, t, c in zip(d["faces"], d["targets"], d["cases"])]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="train on seeds 200-215, 400 steps (default)")
    mode.add_argument("--full", action="store_true", help="train on seeds 200-263, 3000 steps")
    mode.add_argument("--weights", type=Path, help="evaluate these weights, no training")
    ap.add_argument("--out", type=Path, default=Path("/tmp/panoworld_rig_unet"), help="where the trained weights go")
    ap.add_argument("--seeds", default="116-131", help="held-out test seeds (default 116-131)")
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/panoworld_rig_samples"),
                    help="rendered training faces are kept here (one .npz per seed)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(2)
    info: dict = {}
    weights = args.weights
    if weights is None:
        from panoworld.models.rig_unet import RigUNetConfig
        from panoworld.tools.train.rig import train_rig_unet

        train_seeds, steps = (range(200, 264), 3000) if args.full else (range(200, 216), 400)
        t0 = time.perf_counter()
        samples = cached_samples(train_seeds, args.height, args.cache)
        t1 = time.perf_counter()
        net = train_rig_unet(samples, RigUNetConfig(), steps=steps, batch=6, log=lambda m: print(m, file=sys.stderr, flush=True))
        weights = net.save(args.out)
        info = {"train_seeds": f"{train_seeds.start}-{train_seeds.stop - 1}", "steps": steps,
                "data_s": t1 - t0, "train_s": time.perf_counter() - t1, "weights": str(weights)}
    rows = evaluate(parse_seeds(args.seeds), weights, args.height)
    summary = []
    for case in CASES:
        for name in ("heuristic", "learned"):
            rs = [r for r in rows if r["case"] == case and r["detector"] == name]
            s = {"case": case, "detector": name, "scenes": len(rs), "found": sum(r["found"] for r in rs)}
            if "iou" in rs[0]:
                s.update(iou=float(np.mean([r["iou"] for r in rs])), psnr_mean=float(np.mean([r["psnr_after"] for r in rs])),
                         psnr_min=float(min(r["psnr_after"] for r in rs)), ge25=sum(r["psnr_after"] >= 25 for r in rs))
            summary.append(s)
    if args.json:
        print(json.dumps({"info": info, "summary": summary, "rows": rows}, indent=1, default=lambda v: v.item()))
        return 0
    print(f"\n{info}\nheld-out seeds {args.seeds}, {args.height}x{2 * args.height}\n")
    print("| case | detector | found | IoU with the rig (mean) | PSNR15 after (mean / min) | >= 25 dB |\n|---|---|---|---|---|---|")
    for s in summary:
        if "iou" in s:
            print(f"| {s['case']} | {s['detector']} | {s['found']}/{s['scenes']} | {s['iou']:.3f} | "
                  f"{s['psnr_mean']:.2f} / {s['psnr_min']:.2f} | {s['ge25']}/{s['scenes']} |")
        else:
            print(f"| {s['case']} | {s['detector']} | {s['found']}/{s['scenes']} (must be 0) | - | - | - |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
