"""Rewrite the marked tables of docs/training.md from the --json outputs of the two training benches.

    python bench/training_tables.py [--video video.json] [--recon recon.json] [--doc docs/training.md] [--check]

Each JSON replaces the text between `<!-- BEGIN <name> -->` and `<!-- END <name> -->` where <name> is video-<mode> or
recon-<mode> (mode: quick or full, from the JSON); --check exits 1 instead of writing when the file would change.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np

DOC = Path(__file__).resolve().parent.parent / "docs" / "training.md"


def _video_rows(d: dict, split: str) -> list[dict]:
    return [r for r in d["rows"] if r.get("split", d.get("split", "test")) == split]


def video_table(d: dict) -> str:
    split = d.get("split", "test")
    rows = _video_rows(d, split)
    seeds = sorted({r["seed"] for r in rows})
    better = "higher" if d["higher_is_better"] else "lower"
    how = " --split both" if len(d.get("splits", [])) > 1 else ""
    head = (f"`python bench/bench_train_video.py --{d['mode']}{how} --json video.json` — {len(d['train_scenes'])} train "
            f"scenes, {len(d[f'{split}_scenes'])} {split} scenes, {d['clips']} {split} clips per seed, seeds {seeds}; "
            f"metric: {d['metric']} ({better} is better), mean ± std over seeds; {d['wall_s']:.0f} s wall, "
            f"{d['cpu_s']:.0f} s CPU")
    if "stage_steps" in d:
        st = d["stage_steps"]
        head += (f"; LoRA stage: shortcut {st['shortcut']} steps ({d['config']['sc_split']} split), FM-only "
                 f"{st['fm-only']} (held equal: {d['held_equal']})")
    n = d.get("processes", 1)
    head += f" (run as {n} processes side by side, one `--seeds` each, merged)." if n > 1 else "."
    out = [head, "", "| model | steps | sampler | SWD | PSNR (dB) | distance to nearest fill |",
           "| --- | --- | --- | --- | --- | --- |"]
    for model in ("fm-only", "shortcut"):
        for steps in sorted({r["steps"] for r in rows}):
            sel = [r for r in rows if r["model"] == model and r["steps"] == steps]
            if not sel:
                continue
            v = np.array([r["value"] for r in sel])
            out.append(f"| {model} | {steps} | {sel[0]['sampler']} | {v.mean():.4f} ± {v.std():.4f} | "
                       f"{np.mean([r['psnr'] for r in sel]):.2f} | {np.mean([r['mode_error'] for r in sel]):.3f} |")
    if "floor" in d:
        out += ["", f"SWD between two independent draws of the true fills ({d['clips']} each): {d['floor']:.4f} "
                    "(what a perfect sampler scores)."]
    for sp in d.get("splits", [split]):
        t = d.get("targets" if sp == split else f"{sp}_targets", {})
        if t:
            out += ["", f"Per seed, {sp} split: " + "; ".join(f"{k.replace('_', ' ')}: {'met' if ok else '**not met**'}"
                                                          for k, ok in t.items()) + "."]
    if "val" in d.get("splits", []) and split != "val":
        val = _video_rows(d, "val")
        cells = [f"{m} {k}: {np.mean([r['value'] for r in val if r['model'] == m and r['steps'] == k]):.4f}"
                 for m in ("fm-only", "shortcut") for k in sorted({r["steps"] for r in val})]
        out += ["", f"The same models on the val split ({len(d['val_scenes'])} scenes), SWD mean over seeds: "
                    + ", ".join(cells) + "."]
    return "\n".join(out)


def merge_video(results: list[dict]) -> dict[str, dict]:
    """One result per mode: the rows of every file of that mode (e.g. one seed per process); wall = the longest run,
    CPU = the sum, targets recomputed over all seeds."""
    merged: dict[str, dict] = {}
    for d in results:
        m = merged.get(d["mode"])
        if m is None:
            merged[d["mode"]] = dict(d, rows=list(d["rows"]), processes=1)
            continue
        if m["train_scenes"] != d["train_scenes"] or m.get("split") != d.get("split"):
            raise SystemExit(f"video JSON files of mode {d['mode']} differ in their scenes or split; not merged")
        seen = {r["seed"] for r in m["rows"]}
        m["rows"] += [r for r in d["rows"] if r["seed"] not in seen]
        m["wall_s"], m["cpu_s"] = max(m["wall_s"], d["wall_s"]), m["cpu_s"] + d["cpu_s"]
        m["processes"] += 1
    for m in merged.values():
        for sp in m.get("splits", [m.get("split", "test")]):
            m["targets" if sp == m.get("split", "test") else f"{sp}_targets"] = targets(_video_rows(m, sp))
    return merged


def targets(rows: list[dict]) -> dict[str, bool]:
    """The issue's 'done when', for every seed: FM-20 beats FM-4; shortcut beats FM-only at 1 and 2 (and 4) steps."""
    v = {(r["model"], r["steps"], r["seed"]): r["value"] for r in rows}
    seeds = sorted({r["seed"] for r in rows})

    def beats(a: tuple, b: tuple) -> bool:
        return all((*a, s) in v and (*b, s) in v and v[(*a, s)] < v[(*b, s)] for s in seeds)

    return {"fm20_beats_fm4": beats(("fm-only", 20), ("fm-only", 4)),
            "shortcut_beats_fm_at_1": beats(("shortcut", 1), ("fm-only", 1)),
            "shortcut_beats_fm_at_2": beats(("shortcut", 2), ("fm-only", 2)),
            "shortcut_beats_fm_at_4": beats(("shortcut", 4), ("fm-only", 4))}


def recon_table(d: dict) -> str:
    disjoint = not (set(d["test_scenes"]) & (set(d["train_scenes"]) | set(d["val_scenes"])))
    seeds = ", ".join(f"{k} {v}" for k, v in d["split_seeds"].items())
    head = (f"`python bench/bench_train_recon.py --{d['mode']} --out WORK --json recon.json` — scenes by split "
            f"(synth seeds {seeds}): {len(d['train_scenes'])} train / {len(d['val_scenes'])} val / "
            f"{len(d['test_scenes'])} test, test disjoint from train and val: {'yes' if disjoint else '**no**'}; "
            f"stage 1 {d['steps']['stage1']} steps, stage 2 {d['steps']['stage2']}; {d['wall_s']:.0f} s wall, "
            f"{d['cpu_s']:.0f} s CPU.")
    out = [head, "",
           "| split | model | refine_iters | ATE (m) | RPE_t (m) | RPE_r (°) | depth AbsRel | novel PSNR (dB) |",
           "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(d["rows"], key=lambda r: (r["split"] != "test", r["refine_iters"], r["model"] != "trained")):
        label = "0 (paper)" if r["refine_iters"] == 0 else f"{r['refine_iters']} (not in the paper)"
        nv = "–" if r["novel_psnr"] is None else f"{r['novel_psnr']:.2f}"
        out.append(f"| {r['split']} | {r['model']} | {label} | {r['ate']:.4f} | {r['rpe_t']:.4f} | {r['rpe_r']:.2f} | "
                   f"{r['abs_rel']:.3f} | {nv} |")
    by = {(r["split"], r["model"], r["refine_iters"]): r for r in d["rows"]}
    ratios = []
    for split in ("test", "val"):
        t, i = by.get((split, "trained", 0)), by.get((split, "init", 0))
        if t and i:
            ratios.append(f"{split}: init / trained ATE = {i['ate'] / t['ate']:.2f}x "
                          f"({'meets' if t['ate'] <= i['ate'] / 3 else '**misses**'} the 3x target)")
    return "\n".join(out + ["", "Feed-forward (refine_iters 0): " + "; ".join(ratios) + "."])


def replace(doc: str, name: str, body: str) -> str:
    pattern = re.compile(rf"(<!-- BEGIN {re.escape(name)} -->\n).*?(\n<!-- END {re.escape(name)} -->)", re.DOTALL)
    if not pattern.search(doc):
        raise SystemExit(f"{DOC}: no <!-- BEGIN {name} --> ... <!-- END {name} --> section; add the markers")
    return pattern.sub(lambda m: m.group(1) + body + m.group(2), doc)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--video", type=Path, action="append", default=[], help="bench_train_video.py --json output")
    ap.add_argument("--recon", type=Path, action="append", default=[], help="bench_train_recon.py --json output")
    ap.add_argument("--doc", type=Path, default=DOC)
    ap.add_argument("--check", action="store_true", help="exit 1 if the document is not up to date")
    a = ap.parse_args(argv)
    doc = old = a.doc.read_text()
    for mode, d in merge_video([json.loads(path.read_text()) for path in a.video]).items():
        doc = replace(doc, f"video-{mode}", video_table(d))
    for path in a.recon:
        d = json.loads(path.read_text())
        doc = replace(doc, f"recon-{d['mode']}", recon_table(d))
    if a.check:
        return int(doc != old)
    a.doc.write_text(doc)
    print(f"{a.doc}: {'updated' if doc != old else 'unchanged'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
