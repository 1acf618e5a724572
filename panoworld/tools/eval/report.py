"""Reports of `runner.py eval`: targets met, JSON-safe values, the per-scene text table."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from panoworld.io.manifest import ARTIFACTS_DIRNAME
from panoworld.tools.eval.common import GT_DIRNAME, TARGETS, EvalInputError, EvalParams, is_unavailable
from panoworld.tools.eval.scene import Evaluation


def target_report(stages: dict[str, dict]) -> dict[str, dict]:
    """{stage: {metric: {"target": text, "met": bool | None}}} for every metric with a target."""
    out: dict[str, dict] = {}
    for stage, targets in TARGETS.items():
        if stage not in stages:
            continue
        metrics = stages[stage]
        for name, t in targets.items():
            value = metrics.get(name) if not is_unavailable(metrics) else None
            out.setdefault(stage, {})[name] = {"target": t.text(), "met": t.met(value)}
    return out


def jsonable(obj: Any) -> Any:
    """obj with numpy scalars as Python numbers and non-finite floats as the strings 'inf', '-inf', 'nan'."""
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj


def _fmt(value: Any) -> str:
    if is_unavailable(value):
        return f"n/a ({value['reason']})"
    if isinstance(value, bool) or isinstance(value, (int, np.integer)):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        a = abs(value)
        return f"{value:.1f}" if a >= 1000 else f"{value:.3f}" if a >= 1 else f"{value:.4g}"
    return str(value)


def format_table(report: dict) -> str:
    """The report as a text table grouped by stage: metric, value, target, ok."""
    lines = [f"scene: {report['scene']}", ""]
    rows = [("stage", "metric", "value", "target", "ok")]
    for stage, metrics in report["stages"].items():
        if is_unavailable(metrics):
            rows.append((stage, "-", _fmt(metrics), "", ""))
            continue
        targets = report["targets"].get(stage, {})
        for k, (name, value) in enumerate(metrics.items()):
            t = targets.get(name)
            ok = "" if t is None or t["met"] is None else ("yes" if t["met"] else "NO")
            rows.append((stage if k == 0 else "", name, _fmt(value), t["target"] if t else "", ok))
    widths = [max(len(r[c]) for r in rows if len(r[c]) < 40) for c in range(4)]
    for r in rows:
        lines.append("  ".join(r[c].ljust(widths[c]) for c in range(4)) + "  " + r[4])
    return "\n".join(line.rstrip() for line in lines)


NOTHING_MESSAGE = ("{scene} has no gt/gt.json and no {artifacts}/: nothing to evaluate; run the pipeline first "
                   "(`python runner.py run SCENE`)")


def evaluate_scene(scene_dir: Path, params: EvalParams | None = None, *, stages: list[str] | None = None,
                   progress: bool = False, variant: str | None = None,
                   roam_images: Path | None = None) -> tuple[dict, list[str]]:
    """The full report {"scene", "reference", "params", "stages", "targets"} of one scene and the stages that errored.

    The reference is the scene's synthetic ground truth, its ground-truth frames + poses, or its plan alone
    (panoworld.tools.eval.groundtruth.open_ground_truth). variant: a named variant of the DAG's tail
    (artifacts/variants/NAME, `runner.py run DATASET --all --sweep`). roam_images: a directory where the roam
    protocol saves its renders and references (the report's pictures). Raises EvalInputError when the scene has
    neither ground truth nor artifacts, or LPIPS weights were passed but cannot be loaded.
    """
    from panoworld.framework.stage_params import params_to_dict

    scene_dir = Path(scene_dir)
    if not (scene_dir / GT_DIRNAME / "gt.json").is_file() and not (scene_dir / ARTIFACTS_DIRNAME).is_dir():
        raise EvalInputError(NOTHING_MESSAGE.format(scene=scene_dir, artifacts=ARTIFACTS_DIRNAME))
    params = params or EvalParams()
    ev = Evaluation(scene_dir, params, progress=progress, variant=variant, roam_images=roam_images)
    if ev.lpips.enabled:
        try:
            _ = ev.lpips.model  # loads the weights now: a bad file is one input error, not a failed stage
        except (OSError, ValueError, KeyError, RuntimeError) as e:
            raise EvalInputError(f"LPIPS weights: {e}") from None
    results, errors = ev.run(stages)
    report = {
        "scene": str(scene_dir),
        "variant": variant,
        "reference": ev.gt.kind,
        "setting": ev.setting(),
        "params": params_to_dict(params),
        "stages": results,
        "targets": target_report(results),
    }
    return jsonable(report), errors
