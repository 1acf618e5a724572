"""Evaluate a scene's artifacts against its reference, or a whole dataset in the paper's tables (`runner.py eval`).

The library lives in panoworld/tools/eval/ (common params and results, ground-truth references, the per-scene evaluation,
reports, dataset tables); this module keeps the CLI and re-exports the stable entry points `evaluate` / `evaluate_scene`.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import json
import sys
import typing
from pathlib import Path

from panoworld.conditions.warp import true_disocclusion  # noqa: F401 - re-exported API
from panoworld.io.safe_write import check_output_file, write_text_atomic
from panoworld.tools.eval.common import (  # noqa: F401 - re-exported API
    GT_DIRNAME,
    TARGETS,
    EvalInputError,
    EvalParams,
    Lpips,
    LpipsNet,
    Target,
    depth_errors,
    interpolate_pose,
    iou,
    is_unavailable,
    unavailable,
)
from panoworld.tools.eval.groundtruth import FramesGroundTruth, GroundTruth, NoReference, PlanOnly, open_ground_truth  # noqa: F401 - re-exported API
from panoworld.tools.eval.report import NOTHING_MESSAGE, evaluate_scene, format_table, jsonable, target_report  # noqa: F401 - re-exported API
from panoworld.tools.eval.scene import Evaluation

evaluate = evaluate_scene
"""The name of evaluate_scene before dataset evaluation existed."""


# ---------------------------------------------------------------- CLI


def build_parser() -> argparse.ArgumentParser:
    from panoworld.framework.stage_params import field_docs

    ap = argparse.ArgumentParser(prog="python runner.py eval", description=__doc__)
    ap.add_argument("scene", type=Path, help="scene directory (artifacts/ and optional gt/), or with --all a dataset "
                    "directory of scene directories")
    ap.add_argument("--all", action="store_true", help="evaluate every scene (and sweep variant) of the dataset "
                    "directory and aggregate the paper's tables")
    ap.add_argument("--markdown", action="store_true", help="--all: print the tables as Markdown")
    ap.add_argument("--workers", type=int, default=1, help="--all: scenes evaluated in parallel (local processes)")
    ap.add_argument("--variant", help="evaluate this sweep variant of the scene (artifacts/variants/NAME)")
    ap.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")
    ap.add_argument("--out", type=Path, help="also write the JSON report to this file (the scene is never modified)")
    ap.add_argument("--only", action="append", default=[], choices=list(Evaluation.STAGES), metavar="STAGE",
                    help=f"evaluate only this stage (repeatable; one of {', '.join(Evaluation.STAGES)})")
    docs = field_docs(EvalParams)
    hints = typing.get_type_hints(EvalParams)
    for f in dataclasses.fields(EvalParams):
        tp = hints[f.name]
        choices = [m.value for m in tp] if isinstance(tp, type) and issubclass(tp, enum.Enum) else None
        default = f.default.value if isinstance(f.default, enum.Enum) else f.default
        ap.add_argument(f"--{f.name.replace('_', '-')}", dest=f"p_{f.name}", default=None, choices=choices,
                        metavar=None if choices else getattr(tp, "__name__", "path").upper(),
                        help=f"{docs.get(f.name, '')} (default: {default})")
    return ap


def main(argv: list[str] | None = None) -> int:
    from panoworld.framework.stage_params import params_from_dict

    args = build_parser().parse_args(argv)
    if args.out:
        check_output_file(args.out)
    values = {f.name: getattr(args, f"p_{f.name}") for f in dataclasses.fields(EvalParams)}
    try:
        params = params_from_dict(EvalParams, {k: v for k, v in values.items() if v is not None}, where="eval")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if bool(params.lpips_weights) != bool(params.lpips_lin_weights):
        print("error: LPIPS needs both --lpips-weights (backbone) and --lpips-lin-weights (linear heads)", file=sys.stderr)
        return 2
    if not args.scene.is_dir():
        print(f"error: {args.scene}: {'dataset' if args.all else 'scene'} directory not found", file=sys.stderr)
        return 2
    if args.all:
        from panoworld.tools.eval.dataset import main_dataset

        return main_dataset(args, params)
    try:
        report, errors = evaluate_scene(args.scene, params, stages=args.only or None, progress=sys.stderr.isatty(),
                                        variant=args.variant)
    except EvalInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    text = json.dumps(report, indent=2)
    if args.out:
        write_text_atomic(args.out, text + "\n")
    print(text if args.json else format_table(report))
    for stage in errors:
        print(f"error: stage {stage} could not be evaluated: {report['stages'][stage]['reason']}", file=sys.stderr)
    return 1 if errors else 0
