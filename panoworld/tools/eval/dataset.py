"""`runner.py eval DATASET --all`: every scene and sweep variant evaluated, aggregated into the paper's tables."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from panoworld.tools.eval.common import EvalInputError, EvalParams
from panoworld.tools.eval.tables import build_tables, group_key

RESULTS = "eval_results.json"


def dataset_units(dataset_dir: Path) -> list[tuple[Path, str | None]]:
    """(scene, variant) pairs to evaluate: each sweep variant of a scene, and the scene's own artifacts when its
    tail ran there (a trajectory artifact under artifacts/) or it has no variant at all."""
    from panoworld.io.manifest import ARTIFACTS_DIRNAME
    from panoworld.tools.batch.run import dataset_scenes
    from panoworld.tools.batch.variants import scene_variants

    units: list[tuple[Path, str | None]] = []
    for scene in dataset_scenes(dataset_dir):
        variants = scene_variants(scene)
        if not variants or (scene / ARTIFACTS_DIRNAME / "trajectory" / "manifest.json").is_file():
            units.append((scene, None))
        units += [(scene, v) for v in variants]
    return units


def _eval_unit(task: tuple[str, str | None, dict]) -> dict:
    """One (scene, variant) report; never raises (an error becomes the report's "error")."""
    from panoworld.framework.stage_params import params_from_dict
    from panoworld.tools.eval.report import evaluate_scene

    scene, variant, pdict = task
    unit = Path(scene).name + (f"/{variant}" if variant else "")
    try:
        report, errors = evaluate_scene(Path(scene), params_from_dict(EvalParams, pdict, where="eval"), variant=variant)
        return {**report, "unit": unit, "errors": errors}
    except Exception as e:  # one bad scene never stops the others
        return {"unit": unit, "scene": str(scene), "variant": variant, "error": f"{type(e).__name__}: {e}",
                "stages": {}, "reference": None, "setting": {}}


def evaluate_dataset(dataset_dir: Path, params: EvalParams | None = None, *, workers: int = 1,
                     progress: bool = True) -> dict[str, Any]:
    """{"dataset", "units": [report per scene/variant], "distribution": {...}, "tables": [Table.as_dict()]}."""
    from tqdm import tqdm

    from panoworld.core.errors import PipelineError
    from panoworld.framework.stage_params import params_to_dict
    from panoworld.tools.eval.distribution import distribution_metrics

    params = params or EvalParams()
    try:
        units = dataset_units(Path(dataset_dir))
    except PipelineError as e:
        raise EvalInputError(str(e)) from None
    pdict = params_to_dict(params)
    tasks = [(str(s), v, pdict) for s, v in units]
    if workers > 1:
        from panoworld.tools.precompute.run import LocalExecutor

        stream = LocalExecutor(workers).imap_unordered(_eval_unit, tasks)
    else:
        stream = map(_eval_unit, tasks)
    reports = list(tqdm(stream, total=len(tasks), desc="eval scenes", unit="scene", disable=not progress, file=sys.stderr))
    reports.sort(key=lambda r: r["unit"])
    dists: dict[str, dict[str, dict]] = {"gt": {}, "plan": {}}
    if params.fid_weights or params.fvd_weights:
        for table, refs in (("gt", ("synthetic", "frames")), ("plan", ("plan-only",))):
            groups: dict[str, list[tuple[Path, str | None]]] = {}
            for r in reports:
                if r.get("reference") in refs and not r.get("error"):
                    groups.setdefault(group_key(r), []).append((Path(r["scene"]), r.get("variant")))
            for name, members in groups.items():
                dists[table][name] = distribution_metrics(members, params)
    else:
        for table, refs in (("gt", ("synthetic", "frames")), ("plan", ("plan-only",))):
            for r in reports:
                if r.get("reference") in refs:
                    dists[table].setdefault(group_key(r), distribution_metrics([], params))
    tables = build_tables([r for r in reports if not r.get("error")], dists)
    return {"dataset": str(dataset_dir), "units": reports, "distribution": dists, "tables": [t.as_dict() for t in tables],
            "_tables": tables}


def main_dataset(args, params: EvalParams) -> int:
    """CLI body of `eval DATASET --all [--json] [--markdown] [--out FILE]`: exit 1 when a scene could not be evaluated."""
    from panoworld.tools.eval.report import jsonable

    try:
        result = evaluate_dataset(args.scene, params, workers=args.workers, progress=not args.json and sys.stderr.isatty())
    except EvalInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    tables = result.pop("_tables")
    text = json.dumps(jsonable(result), indent=2)
    out = args.out or Path(args.scene) / RESULTS
    out.write_text(text + "\n")
    if args.json:
        print(text)
    else:
        n = len(result["units"])
        print(f"dataset: {args.scene}  ({n} scene runs; per-scene reports in {out})\n")
        print("\n\n".join(t.markdown() if args.markdown else t.text() for t in tables))
    bad = [r for r in result["units"] if r.get("error") or r.get("errors")]
    for r in bad:
        print(f"error: {r['unit']}: {r.get('error') or 'stages ' + ', '.join(r['errors']) + ' could not be evaluated'}",
              file=sys.stderr)
    return 1 if bad else 0
