"""The pipeline's DAG: stages, their inputs and presets from pipeline.yaml (parsed once per text, cached)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from panoworld.core.errors import PipelineError
from panoworld.core.params import suggest
from panoworld.io import manifest as art
from panoworld.io.user_cache import read_user_cache, write_user_cache

if TYPE_CHECKING:
    from panoworld.framework.stage import StageSpec

PIPELINE_FILE = art.REPO_ROOT / "pipeline.yaml"
DEFAULT_PRESET = "default"


@dataclass(frozen=True)
class InputRef:
    name: str
    source: str
    """'scene' or 'stage'."""
    target: str
    """Scene file key (e.g. 'panorama') or upstream stage name."""
    optional: bool


@dataclass
class StageNode:
    name: str
    module: str
    inputs: list[InputRef]
    resources: dict[str, float]
    params: dict[str, Any]
    presets: dict[str, dict[str, Any]]
    _spec: StageSpec | None = None

    @property
    def spec(self) -> StageSpec:
        from panoworld.framework.stage import load_stage

        if self._spec is None:
            try:
                self._spec = load_stage(self.module)
            except ImportError as e:
                raise PipelineError(f"stage {self.name}: cannot import {self.module} ({e})") from None
        return self._spec


_YAML_CACHE = "yaml_docs.json"
_YAML_CACHE_KEEP = 64
"""YAML documents (pipeline.yaml, scene.yaml) kept parsed in the user cache, by the digest of their text."""


def text_digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def cached_yaml(text: str, parse: Callable[[str], Any]) -> Any:
    """parse(text), or its result for the same text (by sha256) from the user cache: an unchanged pipeline.yaml or
    scene.yaml needs no YAML parser (a no-op run skips importing one). Only documents that JSON keeps exactly are
    cached; a text that fails to parse raises every time."""
    key = text_digest(text)
    cache = read_user_cache(_YAML_CACHE)
    hit = cache.get(key)
    if isinstance(hit, list) and len(hit) == 1:
        return hit[0]
    doc = parse(text)
    try:
        exact = json.loads(json.dumps(doc)) == doc
    except (TypeError, ValueError):
        exact = False
    if exact:
        cache.pop(key, None)
        cache[key] = [doc]
        write_user_cache(_YAML_CACHE, dict(list(cache.items())[-_YAML_CACHE_KEEP:]))
    return doc


def _parse_pipeline_yaml(text: str) -> Any:
    import yaml

    try:
        return yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))  # libyaml: ~10x faster
    except yaml.YAMLError as e:
        raise ValueError(str(e)) from None


@dataclass
class Pipeline:
    path: Path
    stages: dict[str, StageNode]
    order: list[str]
    scene_files: dict[str, list[str]]
    presets: list[str]
    text_digest: str = ""
    """text_digest of the file as read (a run's up-to-date record is keyed by it)."""

    @classmethod
    def load(cls, path: Path | str | None = None) -> Pipeline:
        path = Path(path) if path else PIPELINE_FILE
        try:
            text = path.read_text()
            doc = cached_yaml(text, _parse_pipeline_yaml)
        except (OSError, ValueError) as e:  # _parse_pipeline_yaml raises YAML errors as ValueError
            raise PipelineError(f"{path}: cannot read pipeline ({e})") from None
        stages: dict[str, StageNode] = {}
        for name, s in (doc.get("stages") or {}).items():
            refs = []
            for in_name, src in (s.get("inputs") or {}).items():
                optional = src.endswith("?")
                src = src.rstrip("?")
                if src.startswith("scene."):
                    refs.append(InputRef(in_name, "scene", src.split(".", 1)[1], optional))
                else:
                    refs.append(InputRef(in_name, "stage", src, optional))
            stages[name] = StageNode(
                name=name,
                module=s.get("module", f"stages.{name}"),
                inputs=refs,
                resources=dict(s.get("resources") or {}),
                params=dict(s.get("params") or {}),
                presets={k: dict(v or {}) for k, v in (s.get("presets") or {}).items()},
            )
        pipe = cls(path, stages, [], dict(doc.get("scene_files") or {}), list(doc.get("presets") or [DEFAULT_PRESET]),
                   text_digest(text))
        pipe.order = pipe._toposort()
        return pipe

    def _toposort(self) -> list[str]:
        order: list[str] = []
        state: dict[str, int] = {}

        def visit(n: str, trail: tuple[str, ...]):
            if state.get(n) == 2:
                return
            if state.get(n) == 1:
                raise PipelineError(f"{self.path}: cycle in the DAG: {' -> '.join(trail + (n,))}")
            state[n] = 1
            for ref in self.stages[n].inputs:
                if ref.source == "stage":
                    if ref.target not in self.stages:
                        raise PipelineError(f"{self.path}: stage {n} input {ref.name} names unknown stage {ref.target!r}")
                    visit(ref.target, trail + (n,))
            state[n] = 2
            order.append(n)

        for n in self.stages:  # declaration order breaks ties
            visit(n, ())
        return order

    def upstream(self, name: str) -> list[str]:
        return [r.target for r in self.stages[name].inputs if r.source == "stage"]

    def ancestors(self, name: str) -> set[str]:
        out: set[str] = set()
        todo = [name]
        while todo:
            for u in self.upstream(todo.pop()):
                if u not in out:
                    out.add(u)
                    todo.append(u)
        return out

    def descendants(self, name: str) -> set[str]:
        return {n for n in self.stages if name in self.ancestors(n)}

    def check_stage(self, name: str, flag: str) -> None:
        if name not in self.stages:
            raise PipelineError(f"{flag} {name}: unknown stage{suggest(name, self.order)}")

    def text(self) -> str:
        lines = []
        for n in self.order:
            node = self.stages[n]
            ins = ", ".join(f"{r.name}<-{r.source + '.' if r.source == 'scene' else ''}{r.target}{'?' if r.optional else ''}" for r in node.inputs)
            res = ", ".join(f"{k}={v}" for k, v in node.resources.items())
            lines.append(f"{n:<11} [{res}]  inputs: {ins}")
        return "\n".join(lines)

    def mermaid(self) -> str:
        lines = ["graph TD"]
        scene_nodes = sorted({r.target for n in self.stages.values() for r in n.inputs if r.source == "scene"})
        for s in scene_nodes:
            lines.append(f"  scene_{s}[/{s}/]")
        for n in self.order:
            gpu = " (gpu)" if self.stages[n].resources.get("gpu") else ""
            lines.append(f"  {n}[{n}{gpu}]")
        for n in self.order:
            for r in self.stages[n].inputs:
                src = f"scene_{r.target}" if r.source == "scene" else r.target
                arrow = "-.->" if r.optional else "-->"
                lines.append(f"  {src} {arrow} {n}")
        return "\n".join(lines)
