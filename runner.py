"""Command-line runner for the PanoWorld pipeline (a thin CLI over panoworld.framework.pipeline)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from panoworld.core.errors import PanoWorldError, from_os_error
from panoworld.framework import pipeline as pl
from panoworld.io.safe_write import check_output_dir


def _add_run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--only", action="append", default=[], metavar="STAGE", help="run exactly this stage from cached inputs (repeatable)")
    p.add_argument("--from", dest="from_", metavar="STAGE", help="rerun this stage and everything downstream")
    p.add_argument("--until", metavar="STAGE", help="stop after this stage (runs only it and its upstream)")
    p.add_argument("--force", action="store_true", help="ignore the cache for the selected stages")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.PARAM=VALUE", help="override one param (repeatable)")
    p.add_argument("--preset", help="param preset from pipeline.yaml (default, ci-tiny, ...)")
    p.add_argument("--dry-run", action="store_true", help="print what would run and why; run nothing")
    p.add_argument("--keep-going", action="store_true", help="keep running independent stages after a failure")
    p.add_argument("--json", action="store_true", help="print the report as JSON on stdout")
    _add_pipeline_arg(p)


def _add_pipeline_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pipeline", type=Path, default=None, help="pipeline file (default: the repository's pipeline.yaml)")


def _same_destination(a, b) -> bool:
    """Whether the streams a and b write to one file, pipe or terminal (`2>&1`)."""
    try:
        sa, sb = os.fstat(a.fileno()), os.fstat(b.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def _print_report(report: pl.Report, as_json: bool) -> int:
    if as_json:
        print(json.dumps(report.as_dict(), indent=2))
    else:
        print(report.table())
    sys.stdout.flush()
    # The table ends with the notes; where stdout is not the terminal (--json, a pipe, a file) the terminal hears them
    # on stderr too: a partial result is never silent, and never said twice on one screen or in one log (`2>&1`).
    if (as_json or not sys.stdout.isatty()) and not _same_destination(sys.stdout, sys.stderr):
        for note in report.notes:
            print(f"note: {note}", file=sys.stderr)
    failed = [r for r in report.results if r.action == "failed"]
    for r in failed:
        print(f"error: stage {r.stage} failed: {r.reason}", file=sys.stderr)
    if not failed:
        return 0
    return 2 if all(r.bad_input for r in failed) else 1


def cmd_run(args) -> int:
    if args.all:
        from panoworld.tools.batch.run import cmd_run_all

        return cmd_run_all(args)
    if args.sweep or args.executor != "local" or args.workers != 1 or args.ray_address:
        raise pl.PipelineError("--sweep, --executor, --workers and --ray-address need --all (SCENE = a dataset directory)")

    def live(r: pl.StageResult) -> None:
        if not args.json and not r.bad_input:  # a refused input: one line, the report's error line
            print(f"[{r.stage}] {r.action}: {r.reason}", file=sys.stderr, flush=True)

    report = pl.run(
        args.scene, only=args.only, from_=args.from_, until=args.until, force=args.force, sets=args.sets,
        preset=args.preset, dry_run=args.dry_run, keep_going=args.keep_going, echo=not args.json, on_result=live,
        pipeline=pl.Pipeline.load(args.pipeline),
    )
    return _print_report(report, args.json)


def cmd_status(args) -> int:
    rows = pl.status(args.scene, preset=args.preset, sets=args.sets, pipeline=pl.Pipeline.load(args.pipeline))
    notes = pl.scene_notes({r["stage"]: Path(r["artifact"]) for r in rows if r["state"] == "up-to-date"},
                           Path(args.scene))
    if args.json:
        print(json.dumps({"scene": str(args.scene), "stages": rows, "notes": notes}, indent=2))
        return 0
    for r in rows:
        sv = r["schema_version"] if r["schema_version"] is not None else "-"
        print(f"{r['stage']:<11} {r['state']:<10} {r['reason']}\n{'':<11} {r['artifact']} (schema {r['schema']} v{sv})")
    for note in notes:
        print(f"note: {note}")
    return 0


def cmd_dag(args) -> int:
    pipe = pl.Pipeline.load(args.pipeline)
    print(pipe.mermaid() if args.mermaid else pipe.text())
    return 0


def cmd_demo(args) -> int:
    import resource
    import time

    import yaml

    from panoworld.tools.synth.cli import main as synth_main

    out = check_output_dir(args.out_dir)
    scene = out / "scene"
    cfg = scene / pl.SCENE_CONFIG
    t_start = time.perf_counter()
    if (scene / "panorama.png").is_file():
        made = (yaml.safe_load(cfg.read_text()) or {}).get("preset") if cfg.is_file() else None
        if made is not None and made != args.preset:
            print(f"error: {scene} is the demo of preset {made}; rerun with --preset {made} or give another OUT_DIR",
                  file=sys.stderr)
            return 2
    else:
        # The synthetic scene's size follows the preset: ci-tiny is one small room, the rest a furnished flat.
        synth_preset = "ci-tiny" if args.preset == "ci-tiny" else "default"
        code = synth_main([str(scene), "--seed", str(args.seed), "--preset", synth_preset])
        if code:
            return code
    if not cfg.is_file():  # status, run and eval on the scene later resolve the same params
        cfg.write_text(yaml.safe_dump({"preset": args.preset}))
    t_synth = time.perf_counter() - t_start

    def cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime

    cpu_s: dict[str, float] = {}
    last = [cpu()]

    def live(r: pl.StageResult) -> None:
        now = cpu()
        cpu_s[r.stage], last[0] = now - last[0], now
        extra = f" ({r.seconds:.1f} s, CPU {cpu_s[r.stage]:.1f} s)" if r.action == "ran" else ""
        print(f"[{r.stage}] {r.action}: {r.reason}{extra}", file=sys.stderr, flush=True)

    report = pl.run(scene, echo=True, on_result=live)
    code = _print_report(report, False)
    ran = [r for r in report.results if r.action == "ran"]
    from panoworld.tools.report.cli import build_scene_report

    t_report = time.perf_counter()
    page = build_scene_report(scene, run_results=[r.as_dict() for r in report.results])
    t_report = time.perf_counter() - t_report
    print(f"\nscene synthesis {t_synth:.1f} s; stages {sum(r.seconds for r in ran):.1f} s wall, "
          f"{sum(cpu_s.get(r.stage, 0.0) for r in ran):.1f} s CPU (user+sys); report {t_report:.1f} s; demo total "
          f"{time.perf_counter() - t_start:.1f} s")
    if code == 0:
        print(f"\ndemo scene: {scene} (preset {args.preset}, remembered in {cfg.name})\n"
              f"artifacts:  {scene / pl.ARTIFACTS_DIRNAME}\n"
              f"open {scene / pl.ARTIFACTS_DIRNAME / 'gaussians' / 'gaussians.ply'} in a 3DGS viewer (e.g. SuperSplat), "
              f"{scene / pl.ARTIFACTS_DIRNAME / 'video' / 'preview.mp4'} in any player; "
              f"score it: python runner.py eval {scene}")
    print(f"report: {page} (open it in a browser; 3D viewer: python runner.py view {scene})")
    return code


# Verbs whose CLI lives in a library module: verb -> ("module:function" called with the remaining argv, help).
DELEGATED = {
    "synth": ("panoworld.tools.synth.cli:main", "generate synthetic scenes with ground truth"),
    "eval": ("panoworld.tools.eval.cli:main", "evaluate a scene's artifacts against its reference, or a dataset in the paper's tables (--all)"),
    "precompute": ("panoworld.tools.precompute.run:main", "precompute training conditions for a dataset"),
    "train": ("panoworld.tools.train.cli:main", "train the video generator or the reconstruction model (train video|recon)"),
    "weights": ("panoworld.framework.hub.cli:main", "list, fetch and resolve the learned backends' weights (weights list|fetch|resolve)"),
    "report": ("panoworld.tools.report.cli:main", "write a scene's (or a precompute dataset's) self-contained HTML report"),
    "view": ("panoworld.tools.viewer.app:main", "interactive 3D viewer of a scene in the browser (viser)"),
    "split": ("panoworld.tools.split_home:main", "each group of a home's panoramas that registration left unplaced as a home of its own"),
    "warmup": ("panoworld.tools.warmup:main", "compile every numba kernel once per install (a first run then pays none)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python runner.py", description=__doc__)
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("run", help="bring a scene's artifacts up to date")
    p.add_argument("scene", type=Path, help="scene directory (panorama.png|jpg, optional depth.npy|exr|png, scene.yaml; or a home: panoramas/, docs/multi.md)")
    _add_run_args(p)
    g = p.add_argument_group("datasets (--all: SCENE is a directory of scene directories; docs/scale.md)")
    g.add_argument("--all", action="store_true", help="run every scene directory under SCENE; failures never stop the others")
    g.add_argument("--executor", choices=["local", "ray"], default="local", help="run stages locally or as Ray tasks")
    g.add_argument("--workers", type=int, default=1, help="scenes in flight at once")
    g.add_argument("--ray-address", default=None, help="Ray cluster address (default: start a local instance)")
    g.add_argument("--sweep", action="append", default=[], metavar="STAGE.PARAM=V1,V2",
                   help="named variants of the DAG's tail, e.g. trajectory.stride=1,2,4 (repeatable: cross product)")
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("status", help="each stage's state and reason, and its artifact")
    p.add_argument("scene", type=Path)
    p.add_argument("--preset")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.PARAM=VALUE")
    p.add_argument("--json", action="store_true")
    _add_pipeline_arg(p)
    p.set_defaults(func=cmd_status)
    p = sub.add_parser("dag", help="print the DAG")
    p.add_argument("--mermaid", action="store_true", help="as a Mermaid graph")
    _add_pipeline_arg(p)
    p.set_defaults(func=cmd_dag)
    p = sub.add_parser("demo", help="build the bundled synthetic example scene and run the whole pipeline on it")
    p.add_argument("out_dir", nargs="?", default="demo_out", type=Path)
    p.add_argument("--preset", default="default",
                   help="param preset (default: a furnished multi-room scene, 81 frames of 720x1440, planned poses, "
                        "a few minutes on 2 cores; ci-tiny: one small room in well under a minute)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_demo)
    for verb, (_, text) in DELEGATED.items():
        sub.add_parser(verb, help=f"{text} (python runner.py {verb} --help)", add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in DELEGATED:
            import importlib

            module, func = DELEGATED[argv[0]][0].split(":")
            return getattr(importlib.import_module(module), func)(argv[1:])
        args = build_parser().parse_args(argv)
        return args.func(args)
    except PanoWorldError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    except OSError as e:  # the environment (read-only scene, full disk, ...): one line, never a traceback
        err = from_os_error(e)
        print(f"error: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
