"""`runner.py run DATASET --all`: every scene (and sweep variant) of a dataset, locally or on Ray; failures never stop
the others; a summary and a failures file at the dataset root."""

from __future__ import annotations

import json
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from panoworld.framework import pipeline as pl
from panoworld.io.jsonio import write_json
from panoworld.io.jsonl import write_jsonl
from panoworld.tools.batch.executors import make_stage_executor
from panoworld.tools.batch.variants import Variant, parse_sweeps, write_variant

SUMMARY = "batch_summary.json"
FAILURES = "batch_failures.jsonl"


def dataset_scenes(dataset_dir: Path) -> list[Path]:
    """Every non-hidden directory directly under dataset_dir, sorted (a directory without a panorama is a failure)."""
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise pl.PipelineError(f"{dataset_dir}: dataset directory not found")
    scenes = sorted(p for p in dataset_dir.iterdir() if p.is_dir() and not p.name.startswith((".", "_")))
    if not scenes:
        raise pl.PipelineError(f"{dataset_dir}: no scene directories inside")
    return scenes


@dataclass
class Job:
    scene: Path
    variants: list[Variant | None]


@dataclass
class JobResult:
    scene: str
    runs: list[dict[str, Any]] = field(default_factory=list)
    """One per variant: {variant, ok, seconds, stages: [StageResult dicts], error?}."""


def _run_job(job: Job, pipeline: pl.Pipeline, execute, options: dict, on_stage) -> JobResult:
    out = JobResult(job.scene.name)
    for variant in job.variants:
        name = variant.name if variant else None
        t0 = time.perf_counter()
        entry: dict[str, Any] = {"variant": name, "ok": False, "stages": []}
        try:
            if variant is not None and not options.get("dry_run"):
                pl.open_scene(job.scene, pipeline)  # a bad scene fails here, before anything is written
                write_variant(job.scene, variant, pipeline)
            report = pl.run(job.scene, pipeline=pipeline, execute=execute, variant=variant.as_run_arg() if variant else None,
                            on_result=lambda r, n=name: on_stage(job.scene.name, n, r), **options)
            entry["stages"] = [r.as_dict() for r in report.results]
            entry["ok"] = report.ok
        except Exception as e:  # one failing scene never stops the others
            entry["error"] = f"{type(e).__name__}: {e}" if not isinstance(e, pl.PipelineError) else str(e)
        entry["seconds"] = time.perf_counter() - t0
        out.runs.append(entry)
    return out


def run_dataset(
    dataset_dir: Path, *, executor: str = "local", workers: int = 1, ray_address: str | None = None,
    sweeps: list[str] = (), sets: list[str] = (), preset: str | None = None, only: list[str] = (),
    from_: str | None = None, until: str | None = None, force: bool = False, keep_going: bool = False,
    dry_run: bool = False, pipeline: pl.Pipeline | None = None, progress: bool = True, echo_stages: bool = True,
) -> dict:
    """Run every scene (x every sweep variant) of dataset_dir; write batch_summary.json and batch_failures.jsonl there.

    Scenes run `workers` at a time (driver threads); each scene's variants run one after the other under the scene's
    lock, so their shared upstream stages are computed once. Returns the summary.
    """
    from tqdm import tqdm

    pipeline = pipeline or pl.Pipeline.load()
    dataset_dir = Path(dataset_dir)
    scenes = dataset_scenes(dataset_dir)
    variants: list[Variant | None] = list(parse_sweeps(list(sweeps), pipeline)) or [None]
    for v in variants:  # bad --set / --sweep values (type, range, choices): one error before anything runs
        sets_v = pl.parse_sets(list(sets) + list(v.sets if v else ()), pipeline)
        pl.resolve_params(pipeline, preset, None, sets_v, [n for n in pipeline.order if n in sets_v])
    if workers < 1:
        raise pl.PipelineError(f"--workers {workers}: must be >= 1")
    execute = make_stage_executor(executor, workers, ray_address)
    options = dict(sets=list(sets), preset=preset, only=list(only), from_=from_, until=until, force=force,
                   keep_going=keep_going, dry_run=dry_run)
    jobs = [Job(s, variants) for s in scenes]
    lock = threading.Lock()
    counts = {"ran": 0, "cached": 0, "failed": 0, "skipped": 0}
    bar = tqdm(total=len(jobs) * len(variants), desc="scenes", unit="run", disable=not progress, file=sys.stderr)

    def on_stage(scene: str, variant: str | None, r: pl.StageResult) -> None:
        with lock:
            counts[r.action] = counts.get(r.action, 0) + 1
            bar.set_postfix(counts)
            if echo_stages and r.action != "skipped":
                tqdm.write(f"[{scene}{'/' + variant if variant else ''}] {r.stage} {r.action}: {r.reason}", file=sys.stderr)

    t0 = time.perf_counter()
    results: list[JobResult] = []
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(_run_job, j, pipeline, execute, options, on_stage) for j in jobs]
        for f in as_completed(futures):
            res = f.result()
            results.append(res)
            bar.update(len(res.runs))
    bar.close()
    wall = time.perf_counter() - t0
    execute.close()
    results.sort(key=lambda r: r.scene)
    failures = []
    for res in results:
        for run in res.runs:
            if run.get("error"):
                failures.append({"scene": res.scene, "variant": run["variant"], "stage": None, "error": run["error"]})
            for st in run["stages"]:
                if st["action"] == "failed":
                    failures.append({"scene": res.scene, "variant": run["variant"], "stage": st["stage"],
                                     "error": st["reason"]})
    ok_runs = sum(run["ok"] and not run.get("error") for res in results for run in res.runs)
    ok_scenes = sum(all(run["ok"] and not run.get("error") for run in res.runs) for res in results)
    summary = {
        "dataset": str(dataset_dir),
        "scenes": len(scenes),
        "variants": [v.name for v in variants if v is not None],
        "runs": len(jobs) * len(variants),
        "runs_ok": ok_runs,
        "scenes_ok": ok_scenes,
        "scenes_failed": sorted({f["scene"] for f in failures}),
        "stages": counts,
        "seconds": wall,
        "scenes_per_hour": 3600.0 * len(scenes) / wall if wall > 0 else 0.0,
        "executor": executor,
        "workers": workers,
        "results": [{"scene": r.scene, "runs": r.runs} for r in results],
    }
    write_json(dataset_dir / SUMMARY, summary, indent=2, atomic=True)
    write_jsonl(dataset_dir / FAILURES, failures)
    return summary


def format_summary(summary: dict) -> str:
    rows = [("scene", "variant", "result", "ran", "cached", "seconds")]
    for res in summary["results"]:
        for run in res["runs"]:
            acts = [s["action"] for s in run["stages"]]
            result = "ok" if run["ok"] and not run.get("error") else "FAILED"
            rows.append((res["scene"], run["variant"] or "-", result, str(acts.count("ran")), str(acts.count("cached")),
                         f"{run['seconds']:.1f}"))
    widths = [max(len(r[i]) for r in rows) for i in range(6)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    s = summary
    lines.append(f"\n{s['scenes_ok']}/{s['scenes']} scenes ok, {s['runs_ok']}/{s['runs']} runs; stages {s['stages']}; "
                 f"{s['seconds']:.1f} s ({s['scenes_per_hour']:.1f} scenes/hour, {s['executor']} x {s['workers']})")
    return "\n".join(lines)


def cost_table(summary: dict) -> str:
    """Per-stage mean seconds and peak memory over the runs of a summary that ran the stage (the sizing table of
    docs/scale.md)."""
    acc: dict[str, list[tuple[float, float | None]]] = {}
    for res in summary["results"]:
        for run in res["runs"]:
            for st in run["stages"]:
                if st["action"] == "ran":
                    acc.setdefault(st["stage"], []).append((st["seconds"], st.get("peak_rss_mb")))
    rows = ["| stage | runs | mean s | max s | peak MB |", "|---|---|---|---|---|"]
    total = 0.0
    for stage, vals in acc.items():
        secs = [v[0] for v in vals]
        mem = [v[1] for v in vals if v[1] is not None]
        total += sum(secs) / len(secs)
        rows.append(f"| {stage} | {len(vals)} | {sum(secs) / len(secs):.1f} | {max(secs):.1f} | "
                    f"{max(mem) if mem else float('nan'):.0f} |")
    rows.append(f"| **per scene** | | {total:.1f} | | |")
    return "\n".join(rows)


def cmd_run_all(args) -> int:
    """`runner.py run DATASET --all ...`: exit 0 when every scene ran, 1 when any failed, 2 for a bad request."""
    summary = run_dataset(
        args.scene, executor=args.executor, workers=args.workers, ray_address=args.ray_address, sweeps=args.sweep,
        sets=args.sets, preset=args.preset, only=args.only, from_=args.from_, until=args.until, force=args.force,
        keep_going=args.keep_going, dry_run=args.dry_run, pipeline=pl.Pipeline.load(args.pipeline), progress=not args.json,
        echo_stages=not args.json,
    )
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    for scene in summary["scenes_failed"]:
        print(f"error: scene {scene} failed (see {Path(args.scene) / FAILURES})", file=sys.stderr)
    return 1 if summary["scenes_failed"] else 0
