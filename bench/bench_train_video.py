"""Few-step video generation on a multimodal disocclusion toy: FM-only vs shortcut training at 1, 2, 4 and 20 steps.

    python bench/bench_train_video.py --quick [--json video.json]       # 2 seeds, <= 15 min on 2 idle cores
    python bench/bench_train_video.py --full [--json video.json]        # 3 seeds, longer training, more clips
    python bench/bench_train_video.py --quick --split val               # what tuning may look at (never test)
    python bench/bench_train_video.py --quick --split both              # the same models scored on val and test

The toy (panoworld/tools/train/video/toy.py): frame 0 is a scene's panorama in latent space, frame 1 the same scene turned
by a random yaw with a square disocclusion filled with one of `modes` plausible fills at random; the condition is frame
1 with the hole masked out. Per seed: a tiny Wan transformer pre-trained with flow matching (the frozen base), then
the paper's stage (LoRA + widened patch embedding + step-size embedding) trained twice on it at equal compute: the
shortcut model (rho = 0.75, EMA teacher) `steps` steps, FM only (rho = 1) the steps that cost the same network passes
(toy.equal_compute_steps: a self-consistency sample costs 5 forward equivalents, an FM sample 3, so 7/6 as many), both
through panoworld.models.wan_training. Scenes: train, val
and test from disjoint seed ranges. Metric: sliced Wasserstein distance between the generated hole contents and a
fresh draw of the true fills on the same test conditions (lower is better; the blurry mean of the fills is far from
every fill), plus PSNR of frame 1 against the drawn target (which rewards that mean) and the RMS distance to the
nearest fill. FM-only samples with plain Euler steps on a uniform grid; the shortcut model with the shortcut sampler at
1, 2 and 4 steps and, at 20 (not a power of two), with 20 plain flow steps.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from training_tables import targets  # bench/ is on sys.path when this file runs as a script

MODES = {  # steps: the shortcut model's stage steps (FM-only gets equal compute); sc_split: see ToyConfig
    "quick": {"seeds": (0, 1), "base_steps": 600, "steps": 3000, "sc_split": "batch", "train": 256, "eval_scenes": 64,
              "clips": 256},
    "full": {"seeds": (0, 1, 2), "base_steps": 2000, "steps": 4000, "sc_split": "batch", "train": 1024,
             "eval_scenes": 128, "clips": 512},
}
RHO = 0.75
STEPS = (1, 2, 4, 20)


def sampler_for(model: str, steps: int) -> str:
    return "shortcut" if model == "shortcut" and steps & (steps - 1) == 0 else "flow"


def run(mode_name: str, split: str, seeds: list[int] | None = None, steps: int | None = None) -> dict:
    """split: 'test', 'val' or 'both' (each model trained once, scored on val and on test; the headline is test);
    steps: the shortcut model's stage steps instead of the mode's (FM-only still gets equal compute)."""
    from panoworld.tools.train.video import toy

    mode = dict(MODES[mode_name], **({"steps": steps} if steps else {}))
    cfg = toy.ToyConfig(base_steps=mode["base_steps"], steps=mode["steps"], sc_split=mode["sc_split"])
    stage_steps = {"fm-only": toy.equal_compute_steps(cfg.steps, RHO), "shortcut": cfg.steps}
    rows, times = [], {}
    train_seeds = toy.scene_seeds("train", mode["train"])
    splits = ("val", "test") if split == "both" else (split,)
    eval_seeds = {sp: toy.scene_seeds(sp, mode["eval_scenes"]) for sp in splits}
    assert not any(set(train_seeds) & set(e) for e in eval_seeds.values())
    train, held = toy.ToyScenes(cfg, train_seeds), {sp: toy.ToyScenes(cfg, e) for sp, e in eval_seeds.items()}
    for seed in seeds or mode["seeds"]:
        c0 = time.process_time()
        base = toy.train_base(cfg, train, seed)
        times[seed] = {"base_cpu_s": round(time.process_time() - c0, 1)}
        models = {}
        for name, rho in (("fm-only", 1.0), ("shortcut", RHO)):
            c1 = time.process_time()
            models[name] = toy.train_stage(cfg, base, train, rho=rho, seed=seed, steps=stage_steps[name])
            times[seed][f"{name}_cpu_s"] = round(time.process_time() - c1, 1)
        for sp, (name, model), steps in itertools.product(splits, models.items(), STEPS):
            sampler = sampler_for(name, steps)
            r = toy.evaluate(cfg, model, held[sp], sampler=sampler, steps=steps, clips=mode["clips"], seed=seed)
            rows.append({"model": name, "steps": steps, "sampler": sampler, "value": r["swd"], "psnr": r["psnr"],
                         "mode_error": r["mode_error"], "seed": seed, "split": sp, "train_steps": stage_steps[name]})
            print(f"seed {seed} {sp} {name} {steps} steps ({sampler}): SWD {r['swd']:.4f}, PSNR {r['psnr']:.2f} dB, "
                  f"distance to the nearest fill {r['mode_error']:.3f}", flush=True)
        times[seed]["cpu_s"] = round(time.process_time() - c0, 1)
    return {"metric": "sliced Wasserstein distance of disoccluded content to the true fills", "higher_is_better": False,
            "mode": mode_name, "split": splits[-1], "splits": list(splits), "rows": rows, "train_scenes": train_seeds,
            **{f"{sp}_scenes": e for sp, e in eval_seeds.items()}, "clips": mode["clips"], "config": vars(cfg), "times": times,
            "stage_steps": stage_steps, "held_equal": "network passes per training sample x samples",
            "floor": toy.swd_floor(cfg, mode["clips"])}


def summary(result: dict, split: str) -> str:
    rows = [r for r in result["rows"] if r["split"] == split]
    out = ["| model | steps | sampler | SWD (lower = better) | PSNR (dB) | distance to nearest fill | seeds |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    for model in ("fm-only", "shortcut"):
        for steps in STEPS:
            sel = [r for r in rows if r["model"] == model and r["steps"] == steps]
            v = np.array([r["value"] for r in sel])
            out.append(f"| {model} | {steps} | {sel[0]['sampler']} | {v.mean():.4f} ± {v.std():.4f} | "
                       f"{np.mean([r['psnr'] for r in sel]):.2f} | {np.mean([r['mode_error'] for r in sel]):.3f} | "
                       f"{len(sel)} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--quick", action="store_true")
    g.add_argument("--full", action="store_true")
    ap.add_argument("--split", choices=("test", "val", "both"), default="test",
                    help="held-out scenes scored (both: the same models on val and test)")
    ap.add_argument("--seeds", type=int, nargs="+", help="these training seeds instead of the mode's (e.g. one per "
                    "process; bench/training_tables.py merges the JSON files of one mode)")
    ap.add_argument("--steps", type=int, help="the shortcut model's LoRA-stage steps instead of the mode's (FM-only "
                    "gets the steps of equal compute)")
    ap.add_argument("--json", type=Path, help="write the rows here")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0, c0 = time.perf_counter(), time.process_time()
    result = run("quick" if a.quick else "full", a.split, a.seeds, a.steps)
    result.update(wall_s=round(time.perf_counter() - t0, 1), cpu_s=round(time.process_time() - c0, 1))
    print(f"\n{result['mode']}: {result['wall_s']:.0f} s wall, {result['cpu_s']:.0f} s CPU; SWD of two draws of the "
          f"true fills (a perfect sampler): {result['floor']:.4f}")
    for sp in result["splits"]:  # the headline split (test) last, its targets under "targets"
        t = targets([r for r in result["rows"] if r["split"] == sp])
        result["targets" if sp == result["split"] else f"{sp}_targets"] = t
        print(f"\n{sp} split\n{summary(result, sp)}\n" + ", ".join(f"{k}: {'met' if ok else 'NOT met'}"
                                                                   for k, ok in t.items()))
    if a.json:
        a.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
