"""Reports of `runner.py eval`: targets met, JSON-safe values, the per-scene text table."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from panoworld.eval.common import TARGETS, is_unavailable


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
