"""End-to-end: held-out video PSNR (all / disoccluded) of the untrained init, FM-only (rho = 1)
and shortcut (rho = 0.75) in 4 steps, same training budget, on the tiny preset; plus data-loader throughput.

    python bench/bench_train_video_e2e.py --data COND_DIR --out BENCH_DIR [--clips 16] [--set KEY=VALUE]...

COND_DIR: a precompute output, e.g.
    python runner.py synth data --seed 100 --scenes 40 --preset ci-tiny --frames 49
    python runner.py precompute data --out cond --clips-per-scene 4 --frames 13 --height 64 --workers 1
Run A (`train video --preset tiny`, rho = 0.75) pre-trains the tiny base; run B trains the FM-only ablation (rho = 1)
on the same base (`--weights A/base --set base=wan`) with the same steps. Both are scored through their exports, i.e.
the files the video stage's wan-shortcut backend loads.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _run(args: list[str]) -> dict:
    from panoworld.tools.train.video.cli import main

    t0, c0 = time.perf_counter(), time.process_time()
    code = main([*args, "--json"])
    assert code == 0, f"train video {args} failed ({code})"
    return {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def _generator(export: Path | None, base: Path, sampler: str, steps: int, shift: float = 5.0):
    from panoworld.models.wan_shortcut import Sampler, WanShortcutConfig, WanShortcutGenerator

    cfg = WanShortcutConfig(
        weights=base, lora=export and export / "lora.safetensors", extra_weights=export and export / "extra.safetensors",
        prompt_embeds=base / "prompt_embeds.safetensors" if export is None else export / "prompt_embeds.safetensors",
        sampler=Sampler(sampler), steps=steps, shift=shift, device="cpu", dtype="float32", vae_tiling=False,
    )
    if export is not None:
        return WanShortcutGenerator.from_pretrained(cfg)
    from diffusers import AutoencoderKLWan, WanTransformer3DModel  # the untrained init: base + zero-init widening

    tr = WanTransformer3DModel.from_pretrained(base, subfolder="transformer", local_files_only=True)
    vae = AutoencoderKLWan.from_pretrained(base, subfolder="vae", local_files_only=True)
    return WanShortcutGenerator.from_components(tr, vae, cfg)


def _score(gen, items: list[dict]) -> tuple[float, float, float]:
    from panoworld.tools.train.video.trainer import _uint8, psnr

    alls, holes, t0 = [], [], time.process_time()
    for k, it in enumerate(items):
        gen.cfg.seed = k
        cond, mask, target = _uint8(it["cond"]), it["mask"][0].numpy() > 0, _uint8(it["target"])
        video, _ = gen.generate(cond, mask)
        alls.append(psnr(video[1:], target[1:]))
        holes.append(psnr(video[1:], target[1:], ~mask[1:]))
    return float(np.mean(alls)), float(np.nanmean(holes)), (time.process_time() - t0) / len(items)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--clips", type=int, default=16, help="held-out clips scored")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--resume", action="store_true", help="reuse finished runs in --out")
    a = ap.parse_args()
    torch.set_num_threads(1)
    from panoworld.tools.train.common import resolve_config
    from panoworld.tools.train.video.config import PRESETS, VideoTrainConfig
    from panoworld.tools.train.video.data import ClipDataset, read_index, split_scenes

    cfg = resolve_config(VideoTrainConfig, PRESETS, "tiny", a.sets)
    rows = read_index(a.data)
    _, val_scenes = split_scenes([r.scene for r in rows], cfg.val_fraction, cfg.split_seed)
    val = ClipDataset([r for r in rows if r.scene in val_scenes], cfg.frames, cfg.height)
    t0, c0 = time.perf_counter(), time.process_time()
    items = [val[i] for i in range(min(a.clips, len(val)))]
    load_s, load_cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"held-out: {len(val_scenes)} scenes, {len(val)} clips ({len(items)} scored); ClipDataset: "
          f"{len(items) / load_s:.1f} clips/s wall, {len(items) / max(load_cpu, 1e-9):.1f} clips/s per CPU second "
          f"({cfg.frames} frames x {cfg.height}x{2 * cfg.height})")

    run_a, run_b = a.out / "shortcut_rho075", a.out / "fm_only_rho1"
    times = {}
    if not (a.resume and (run_a / "export" / "scene.yaml").is_file()):
        times["A"] = _run(["--data", str(a.data), "--out", str(run_a), "--preset", "tiny", *sum((["--set", s] for s in a.sets), [])])
    if not (a.resume and (run_b / "export" / "scene.yaml").is_file()):
        times["B"] = _run(["--data", str(a.data), "--out", str(run_b), "--preset", "tiny", "--weights", str(run_a / "base"),
                           "--set", "base=wan", "--set", "rho=1", *sum((["--set", s] for s in a.sets), [])])
    for k, v in times.items():
        print(f"run {k}: {v['wall_s']:.0f} s wall, {v['cpu_s']:.0f} s CPU")
    base = run_a / "base"
    rows_out = [
        ("untrained init (base + zero-init condition), flow 4 steps", _generator(None, base, "flow", 4)),
        ("untrained init, shortcut 4 steps", _generator(None, base, "shortcut", 4)),
        ("FM only (rho = 1), flow 4 steps", _generator(run_b / "export", base, "flow", 4)),
        ("FM only (rho = 1), flow 4 steps, shift 1", _generator(run_b / "export", base, "flow", 4, 1.0)),
        ("shortcut (rho = 0.75), shortcut 4 steps", _generator(run_a / "export", base, "shortcut", 4)),
        ("shortcut (rho = 0.75), flow 4 steps", _generator(run_a / "export", base, "flow", 4)),
        ("FM only (rho = 1), flow 20 steps", _generator(run_b / "export", base, "flow", 20)),
        ("shortcut (rho = 0.75), flow 20 steps", _generator(run_a / "export", base, "flow", 20)),
    ]
    table = []
    vae = rows_out[0][1].vae
    rec = []
    with torch.no_grad():  # the ceiling every row shares: the frozen tiny VAE's reconstruction of the targets
        from panoworld.models import wan_layers as wl
        from panoworld.tools.train.video.trainer import _uint8, psnr

        for it in items:
            video = wl.decode_latents(vae, wl.encode_video(vae, it["target"][None]))[0]
            rec.append(psnr(_uint8(video)[1:], _uint8(it["target"])[1:]))
    print(f"\nVAE reconstruction of the held-out targets (ceiling): {np.mean(rec):.2f} dB")
    print("\n| model, sampler | PSNR all (dB) | PSNR disoccluded (dB) | CPU s / clip |\n| --- | --- | --- | --- |")
    for name, gen in rows_out:
        p_all, p_hole, cpu = _score(gen, items)
        table.append({"row": name, "psnr": p_all, "psnr_disoccluded": p_hole, "cpu_s_per_clip": cpu})
        print(f"| {name} | {p_all:.2f} | {p_hole:.2f} | {cpu:.2f} |", flush=True)
    (a.out / "bench.json").write_text(json.dumps({"rows": table, "times": times, "clips": len(items)}, indent=2))


if __name__ == "__main__":
    main()
