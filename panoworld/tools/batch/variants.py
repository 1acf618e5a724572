"""Sweep variants: the same scene at other tail params (trajectory stride, kind) sharing its upstream artifacts."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

from panoworld.core.errors import PipelineError
from panoworld.framework.pipeline import Pipeline
from panoworld.io.jsonio import read_json, write_json
from panoworld.io.manifest import ARTIFACTS_DIRNAME, VARIANTS_DIRNAME

VARIANT_JSON = "variant.json"


@dataclass(frozen=True)
class Variant:
    """A named set of `--set STAGE.PARAM=VALUE` overrides; the stages it sets and their descendants form its tail."""

    name: str
    sets: tuple[str, ...]

    def tail(self, pipeline: Pipeline) -> list[str]:
        stages = {s.split(".", 1)[0] for s in self.sets}
        tail = stages.union(*(pipeline.descendants(s) for s in stages))
        return [n for n in pipeline.order if n in tail]

    def as_run_arg(self) -> tuple[str, list[str]]:
        return self.name, list(self.sets)


def parse_sweeps(sweeps: list[str], pipeline: Pipeline) -> list[Variant]:
    """`--sweep trajectory.stride=1,2,4 --sweep trajectory.kind=ring,sector` -> the cross product of the values, named
    `stride-1_kind-ring` ...; no sweep -> []."""
    axes: list[list[tuple[str, str]]] = []
    for sw in sweeps:
        lhs, eq, values = sw.partition("=")
        stage, dot, param = lhs.partition(".")
        vals = [v.strip() for v in values.split(",") if v.strip()]
        if not eq or not dot or not param or not vals:
            raise PipelineError(f"--sweep {sw}: expected STAGE.PARAM=V1,V2,...")
        pipeline.check_stage(stage, "--sweep")
        axes.append([(f"{stage}.{param}", v) for v in vals])
    out = []
    for combo in itertools.product(*axes) if axes else []:
        name = "_".join(f"{key.split('.', 1)[1]}-{value}" for key, value in combo)
        out.append(Variant(name, tuple(f"{key}={value}" for key, value in combo)))
    return out


def variant_dir(scene_dir: Path, name: str) -> Path:
    return Path(scene_dir) / ARTIFACTS_DIRNAME / VARIANTS_DIRNAME / name


def write_variant(scene_dir: Path, variant: Variant, pipeline: Pipeline) -> None:
    """Record the variant (its sets and tail) so eval reads its tail from the variant's directory."""
    d = variant_dir(scene_dir, variant.name)
    d.mkdir(parents=True, exist_ok=True)
    doc = {"name": variant.name, "sets": list(variant.sets), "tail": variant.tail(pipeline)}
    path = d / VARIANT_JSON
    if read_json(path, default=None) != doc:
        write_json(path, doc, indent=2)


def read_variant(scene_dir: Path, name: str) -> dict:
    path = variant_dir(scene_dir, name) / VARIANT_JSON
    try:
        return read_json(path)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: missing or unreadable variant record ({e}); rerun `runner.py run DATASET --all "
                         "--sweep ...`") from None


def scene_variants(scene_dir: Path) -> list[str]:
    """Names of the variants that have a record under the scene's artifacts, sorted."""
    root = Path(scene_dir) / ARTIFACTS_DIRNAME / VARIANTS_DIRNAME
    return sorted(p.parent.name for p in root.glob(f"*/{VARIANT_JSON}")) if root.is_dir() else []
