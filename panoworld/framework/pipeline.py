"""The pipeline runner: DAG from pipeline.yaml, param resolution, cache decisions with reasons, locked transactional runs."""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from panoworld.core.errors import InputError, PipelineError
from panoworld.core.params import flatten, suggest
from panoworld.framework import uptodate
from panoworld.io import manifest as art
from panoworld.io.safe_write import write_text_atomic
from panoworld.io.user_cache import read_user_cache, write_user_cache

if TYPE_CHECKING:
    import subprocess

    from panoworld.framework.stage import StageSpec

# The stage contract (panoworld.framework.stage), the kernels and the weights hub are imported where they are used: a
# replayed no-op (uptodate) needs none of them.

PIPELINE_FILE = art.REPO_ROOT / "pipeline.yaml"
ARTIFACTS_DIRNAME = art.ARTIFACTS_DIRNAME
VARIANTS_DIRNAME = art.VARIANTS_DIRNAME
SCENE_CONFIG = art.SCENE_CONFIG
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


# ---------------------------------------------------------------- scene


@dataclass
class Scene:
    root: Path
    files: dict[str, Path | None]
    config: dict[str, Any]
    variant: str | None = None
    """A named variant of the DAG's tail (panoworld.tools.batch.variants): its `tail` stages live in
    artifacts/variants/NAME/, the shared upstream stages stay in artifacts/."""
    tail: frozenset[str] = frozenset()
    notes: list[str] = field(default_factory=list)
    """What the runner says about the scene's files without refusing them (files it leaves out of the inputs)."""
    config_digest: str | None = None
    """text_digest of scene.yaml as read (None: no scene.yaml)."""

    @property
    def artifacts(self) -> Path:
        return self.root / ARTIFACTS_DIRNAME

    def _home(self, stage: str) -> Path:
        return self.artifacts / VARIANTS_DIRNAME / self.variant if self.variant and stage in self.tail else self.artifacts

    def artifact_dir(self, stage: str) -> Path:
        return self._home(stage) / stage

    def log_file(self, stage: str) -> Path:
        return self._home(stage) / "logs" / f"{stage}.log"


def open_scene(scene_dir: Path | str, pipeline: Pipeline) -> Scene:
    """Find the scene files and check the panorama (exists, readable, 2:1) without writing anything."""
    from panoworld.core import limits  # the image and home readers import numpy: a replayed run needs neither
    from panoworld.io.images import check_image
    from panoworld.register.inputs import check_home, is_multi_scene

    root = Path(scene_dir).absolute()  # stages run from the repository root: a relative path would not hold there
    if not root.is_dir():
        raise PipelineError(f"{scene_dir}: scene directory not found")
    files: dict[str, Path | None] = {}
    for key, names in pipeline.scene_files.items():
        files[key] = next((root / n for n in names if (root / n).exists()), None)
    pano = files.get("panorama")
    if is_multi_scene(root) and (pano or files.get("depth")):
        raise PipelineError(f"{root}: holds both panoramas/ (a home) and {(pano or files['depth']).name} (one "
                            "panorama); keep one layout (docs/multi.md)")
    notes: list[str] = []
    if pano is None and is_multi_scene(root):  # a home: SCENE/panoramas/ (docs/multi.md)
        try:
            home = check_home(root)
        except InputError as e:
            raise PipelineError(str(e)) from None
        panos = list(home.panoramas.values())
        notes += [f"ignored {p.relative_to(root)}: not a panorama, depth or rig mask of this home" for p in home.ignored]
    elif pano is None:
        names = pipeline.scene_files.get("panorama", [])
        raise PipelineError(f"{root}: no panorama; expected one of {', '.join(names)}, or panoramas/ (docs/multi.md)")
    else:
        panos = [pano]
    for pano in panos:
        try:  # fully decoded here, so a truncated or corrupt panorama is refused before anything is written
            w, h = check_image(pano, "panorama", remember=True).oriented  # the depth stage applies EXIF orientation too
            limits.check_image_size(pano, w, h, "panorama")
        except InputError as e:
            raise PipelineError(str(e)) from None
        if w != 2 * h:
            raise PipelineError(f"{pano}: {w}x{h} is not an equirectangular panorama (width must be exactly 2x height)")
    config: dict[str, Any] = {}
    config_digest = None
    cfg_path = root / SCENE_CONFIG
    try:
        check_scene_inputs(root, files)
        if cfg_path.is_file():
            limits.check_size(cfg_path, limits.MAX_CONFIG_BYTES, SCENE_CONFIG)
            text = cfg_path.read_text(errors="replace")
            config_digest = text_digest(text)
            config = cached_yaml(text, lambda text: limits.parse_yaml(text, str(cfg_path))) or {}
    except InputError as e:
        raise PipelineError(str(e)) from None
    check_scene_config(config, cfg_path, pipeline)
    return Scene(root, files, config, notes=notes, config_digest=config_digest)


def check_scene_inputs(root: Path, files: dict[str, Path | None]) -> None:
    """The cheap checks of the scene's other user files, before anything is written or hashed: artifacts/ usable, the
    depth's header and the rig mask within limits, a user trajectory readable and within limits. InputError (one
    line) otherwise."""
    from panoworld.io.images import check_depth_file, check_mask_file

    arts = root / ARTIFACTS_DIRNAME
    if arts.is_symlink() and not arts.exists():
        raise InputError(f"{arts}: a dangling symbolic link; remove it (or point it at a directory)")
    if arts.exists() and not arts.is_dir():
        raise InputError(f"{arts}: exists but is not a directory; move it away, the runner keeps its artifacts there")
    for sub in ("logs", VARIANTS_DIRNAME):
        if (arts / sub).is_symlink() or ((arts / sub).exists() and not (arts / sub).is_dir()):
            raise InputError(f"{arts / sub}: a file is where a folder must be; move it away (the runner keeps its "
                             f"{sub} there)")
    if files.get("depth") is not None:
        check_depth_file(files["depth"])
    if files.get("rig_mask") is not None:
        check_mask_file(files["rig_mask"])
    if files.get("trajectory") is not None:
        from panoworld.io.trajectory import read_trajectory_file

        read_trajectory_file(files["trajectory"])


SCENE_CONFIG_KEYS = ("preset", "params")


def check_scene_config(config: Any, path: Path, pipeline: Pipeline) -> None:
    """scene.yaml's schema: {preset: NAME, params: {STAGE: {PARAM: VALUE}}}; PipelineError (one line, with a
    "did you mean") for unknown keys, stages and params and for wrong shapes. Values are checked at resolve time."""
    if not isinstance(config, dict):
        raise PipelineError(f"{path}: expected a mapping with keys 'preset' and/or 'params', got {_short(config)}")
    for key in config:
        if key not in SCENE_CONFIG_KEYS:
            raise PipelineError(f"{path}: unknown key {key!r}{suggest(str(key), SCENE_CONFIG_KEYS)}")
    if config.get("preset") is not None and not isinstance(config["preset"], str):
        raise PipelineError(f"{path}: preset: expected a preset name ({', '.join(pipeline.presets)}), got {_short(config['preset'])}")
    params = config.get("params")
    if params is None:
        return
    from panoworld.framework.stage import normalize

    if not isinstance(params, dict):
        raise PipelineError(f"{path}: params: expected a mapping of stage: {{param: value}}, got {_short(params)}")
    for stage, values in params.items():
        if stage not in pipeline.stages:
            raise PipelineError(f"{path}: params.{stage}: unknown stage{suggest(str(stage), pipeline.order)}")
        if values is None:
            continue
        try:
            normalize(pipeline.stages[stage].spec.params_cls, values, stage)
        except ValueError as e:
            raise PipelineError(f"{path}: {e}") from None


def _short(value: Any) -> str:
    """repr of a user value, shortened (reprlib): a huge or aliased document never makes a huge message."""
    import reprlib

    return reprlib.repr(value)


# ---------------------------------------------------------------- params


def parse_sets(sets: list[str], pipeline: Pipeline) -> dict[str, dict[str, str]]:
    out: dict[str, dict[str, str]] = {}
    for s in sets:
        lhs, eq, value = s.partition("=")
        stage, dot, param = lhs.partition(".")
        if not eq or not dot or not param:
            raise PipelineError(f"--set {s}: expected STAGE.PARAM=VALUE")
        pipeline.check_stage(stage, "--set")
        out.setdefault(stage, {})[param] = value
    return out


def resolve_params(
    pipeline: Pipeline, preset: str | None, scene: Scene | None, sets: dict[str, dict[str, str]], stages: list[str]
) -> dict[str, Any]:
    """Params objects per stage: dataclass defaults < pipeline params < preset < scene.yaml < --set, each value
    checked against its declared type, range and choices (PipelineError naming the param and where it was set)."""
    from panoworld.framework.stage import merge, normalize, params_from_normalized

    preset = preset or (scene.config.get("preset") if scene else None) or DEFAULT_PRESET
    if preset not in pipeline.presets:
        raise PipelineError(f"--preset {preset}: unknown preset; known: {', '.join(pipeline.presets)}")
    scene_params = (scene.config.get("params") or {}) if scene else {}
    out = {}
    for name in stages:
        node = pipeline.stages[name]
        layers = [
            (node.params, f"{pipeline.path.name} stages.{name}.params"),
            (node.presets.get(preset, {}), f"{pipeline.path.name} preset {preset}"),
            (scene_params.get(name) or {}, f"{SCENE_CONFIG} params.{name}"),
            (sets.get(name, {}), "--set"),
        ]
        values: dict[str, Any] = {}
        for layer, where in layers:
            if not layer:
                continue
            try:
                layer_values = normalize(node.spec.params_cls, layer, name)
                params_from_normalized(node.spec.params_cls, layer_values, where=name)  # names the layer that brings a bad value
                values = merge(values, layer_values)
            except ValueError as e:
                raise PipelineError(f"{e} (from {where})") from None
        try:
            out[name] = params_from_normalized(node.spec.params_cls, values, where=name)
        except ValueError as e:
            raise PipelineError(str(e)) from None
    return out


# ---------------------------------------------------------------- locking


class SceneLock:
    """One runner per scene: an exclusive, non-blocking flock on the artifacts directory itself (deleting a file
    cannot defeat it; stages re-check it and its inode before they commit), with the holder named in
    artifacts/.lock for the message a second runner gets. It dies with the process."""

    def __init__(self, scene: Scene):
        self.path = scene.artifacts / art.LOCK_FILE
        self.fd: int | None = None
        self.inode = ""

    def __enter__(self) -> SceneLock:
        arts = self.path.parent
        arts.mkdir(parents=True, exist_ok=True)
        fd = os.open(arts, os.O_RDONLY | os.O_DIRECTORY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            try:
                holder = self.path.read_text(errors="replace")[:200].strip()
            except OSError:
                holder = ""
            raise PipelineError(
                f"{arts.parent}: another runner is working on this scene ({holder or 'unknown holder'}); "
                "wait for it to finish"
            ) from None
        self.fd = fd
        st = os.fstat(fd)
        self.inode = f"{st.st_dev}:{st.st_ino}"
        with contextlib.suppress(OSError):  # a read-only scene whose stages are all up to date still reports them
            write_text_atomic(self.path, f"pid {os.getpid()} since {time.strftime('%Y-%m-%d %H:%M:%S')}",
                              durable=False)  # the flock is the lock; this only names its holder
            for leftover in arts.glob(f"**/logs/{PARAMS_FILE_PREFIX}*.json"):  # of a killed runner
                leftover.unlink(missing_ok=True)
            art.sweep_leftovers(arts)
        return self

    def remove_bookkeeping(self) -> None:
        """While held: delete the lock file and the empty directories under artifacts/ (logs/ of refused stages)."""
        self.path.unlink(missing_ok=True)
        for d in sorted((p for p in self.path.parent.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
            with contextlib.suppress(OSError):
                d.rmdir()
        with contextlib.suppress(OSError):
            self.path.parent.rmdir()

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None


# ---------------------------------------------------------------- state


@dataclass
class StageResult:
    stage: str
    action: str
    """'ran' | 'cached' | 'failed' | 'skipped' (and 'would-run' in a dry run)."""
    reason: str
    seconds: float = 0.0
    peak_rss_mb: float | None = None
    bad_input: bool = False
    """A failure because the stage refused its input (its exit code 2): the runner exits 2."""

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class Report:
    scene: Path
    results: list[StageResult] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    """What the run did not do in full without failing: files left out, panoramas not registered."""
    compile_process: subprocess.Popen | None = field(default=None, repr=False, compare=False)
    """The background compilation of numba kernels this run started on a cold cache (kernels.start_background_compile;
    None when none): it may outlive the run."""

    @property
    def ok(self) -> bool:
        return all(r.action != "failed" for r in self.results)

    def as_dict(self) -> dict[str, Any]:
        return {"scene": str(self.scene), "stages": [r.as_dict() for r in self.results], "notes": self.notes}

    def table(self) -> str:
        rows = [("stage", "action", "reason", "seconds", "peak MB")]
        for r in self.results:
            mem = f"{r.peak_rss_mb:.0f}" if r.peak_rss_mb is not None else "-"
            rows.append((r.stage, r.action, r.reason, f"{r.seconds:.2f}", mem))
        widths = [min(max(len(row[i]) for row in rows), 70) for i in range(5)]
        fmt = lambda row: "  ".join(c[:70].ljust(w) if i < 3 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
        return "\n".join([fmt(rows[0]), "  ".join("-" * w for w in widths)] + [fmt(r) for r in rows[1:]]
                         + [f"note: {n}" for n in self.notes])


def _input_paths(node: StageNode, scene: Scene) -> dict[str, Path | None]:
    out = {}
    for ref in node.inputs:
        if ref.source == "scene":
            out[ref.name] = scene.files.get(ref.target)
        else:
            d = scene.artifact_dir(ref.target)
            out[ref.name] = d if (d / art.MANIFEST).is_file() else None
    return out


def _diff_params(stage: str, old: dict, new: dict) -> str:
    old, new = flatten(old), flatten(new)
    keys = sorted(set(old) | set(new))
    diffs = [f"{stage}.{k} {json.dumps(old.get(k))} -> {json.dumps(new.get(k))}" for k in keys if old.get(k) != new.get(k)]
    return "params changed: " + ", ".join(diffs)


def stage_state(node: StageNode, scene: Scene, params: Any) -> tuple[bool, str]:
    """(up_to_date, reason) for one stage given the artifacts on disk now."""
    from panoworld.framework import code_digest
    from panoworld.framework.hub import resolve as hub
    from panoworld.framework.stage import (
        input_digest,
        params_hash,
        params_to_dict,
        resolve_stage_weights,
        stage_code,
        stage_key,
    )

    out_dir = scene.artifact_dir(node.name)
    if not out_dir.exists():
        return False, "no artifact yet"
    try:
        manifest = art.read_manifest(out_dir, node.spec.artifact)
    except art.ArtifactError as e:
        return False, f"invalid artifact: {e}"
    problem = art.verify_files(out_dir, manifest)
    if problem:
        return False, problem
    try:
        digests = {r.name: input_digest(r.name, node.spec.inputs[r.name], p) for r, p in zip(node.inputs, _input_paths(node, scene).values())}
        for name, spec in node.spec.inputs.items():  # an optional input the DAG does not wire (the stage sees None)
            if name not in digests:
                digests[name] = input_digest(name, spec, None)
    except InputError as e:
        return False, f"input not ready: {e}"
    try:
        weights = resolve_stage_weights(params, manifest.get("weights"), stage=node.name)
    except InputError as e:
        return False, f"weights missing: {e}"
    pdict = params_to_dict(params)
    code = stage_code(node.spec, params)
    key = stage_key(node.spec, params, digests, weights, code)
    if key == manifest["key"]:
        return True, "up to date"
    if manifest["stage_version"] != node.spec.version:
        return False, f"code version changed: {manifest['stage_version']} -> {node.spec.version}"
    old_code = (manifest.get("code") or {}).get("files")
    if old_code is None:
        return False, "code changed: no code digest recorded (an artifact of an older runner)"
    changed_code = code_digest.changed_files(old_code, code)
    if changed_code:
        more = f" (+{len(changed_code) - 5} more)" if len(changed_code) > 5 else ""
        return False, f"code changed: {', '.join(changed_code[:5])}{more}"
    if manifest["params_hash"] != params_hash(pdict):
        return False, _diff_params(node.name, manifest["params"], pdict)
    changed_weights = hub.describe_change(node.name, manifest.get("weights") or {}, weights)
    if changed_weights:
        return False, changed_weights
    changed = [n for n, d in digests.items() if manifest["inputs"].get(n, {}).get("digest") != d]
    return False, f"input changed: {', '.join(changed) or 'unknown'}"


# ---------------------------------------------------------------- running


def _select(pipeline: Pipeline, only: list[str], from_: str | None, until: str | None) -> tuple[set[str], set[str]]:
    """(selected stages, stages forced to rerun by the selection itself)."""
    for s in only:
        pipeline.check_stage(s, "--only")
    if from_:
        pipeline.check_stage(from_, "--from")
    if until:
        pipeline.check_stage(until, "--until")
    if only and (from_ or until):
        raise PipelineError("--only cannot be combined with --from/--until")
    if only:
        return set(only), set()
    selected = set(pipeline.order)
    forced: set[str] = set()
    if from_:
        selected = {from_} | pipeline.descendants(from_)
        forced = set(selected)
    if until:
        selected &= {until} | pipeline.ancestors(until)
        forced &= selected
    return selected, forced


def stage_command(node: StageNode, scene: Scene, params_file: str, python: str = sys.executable) -> list[str]:
    """`python -m <stage module> --out ... --params-file ... --<input> PATH...` for one stage of a scene."""
    cmd = [python, "-m", node.module, "--out", str(scene.artifact_dir(node.name)), "--params-file", params_file]
    for name, p in _input_paths(node, scene).items():
        if p is not None:
            cmd += [f"--{name.replace('_', '-')}", str(p)]
    return cmd


def pending_log(log: Path) -> Path:
    """Where a stage's log is written while it runs; it becomes `log` unless the stage refused its input (exit 2)."""
    return log.with_name(f".{log.name}.{os.getpid()}.part")


def run_logged(cmd: list[str], log: Path, echo: bool = False, env_extra: dict[str, str] | None = None) -> tuple[int, float, float]:
    """Run cmd from the repository root with its output in `log`; returns (exit code, seconds, peak RSS MB).

    On exit code 2 (bad input) the output stays in pending_log(log), for the runner to read and delete: a refused
    input leaves no log behind, and the previous run's log stays."""
    import subprocess
    import threading

    log = Path(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(art.REPO_ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.update(env_extra or {})
    t0 = time.perf_counter()
    part = pending_log(log)
    with open(part, "wb") as logf:
        logf.write(f"$ {' '.join(cmd)}\n".encode())
        logf.flush()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, cwd=art.REPO_ROOT)

        def pump():
            assert proc.stdout is not None
            for chunk in iter(lambda: proc.stdout.read1(4096), b""):
                logf.write(chunk)
                logf.flush()
                if echo:
                    sys.stderr.buffer.write(chunk)
                    sys.stderr.flush()

        t = threading.Thread(target=pump, daemon=True)
        t.start()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        t.join()
    if proc.returncode != 2:
        os.replace(part, log)
    return proc.returncode, time.perf_counter() - t0, usage.ru_maxrss / 1024.0


PARAMS_FILE_PREFIX = ".params-"
"""Params files live beside the stage's log (never in /tmp) and are deleted after the stage; a run that holds the
scene lock deletes those a killed runner left."""


def run_with_params_file(template: list[str], params: dict, log: Path, echo: bool = False,
                         env_extra: dict[str, str] | None = None) -> tuple[int, float, float]:
    """Write the params file beside the log, run the stage command template ({params_file}, {python}), delete it."""
    import threading

    log = Path(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    params_file = log.parent / f"{PARAMS_FILE_PREFIX}{log.stem}-{os.getpid()}-{threading.get_ident()}.json"
    params_file.write_text(json.dumps(params))
    try:
        cmd = [c.replace("{params_file}", str(params_file)).replace("{python}", sys.executable) for c in template]
        return run_logged(cmd, log, echo, env_extra)
    finally:
        params_file.unlink(missing_ok=True)


def runner_env(scene: Scene) -> dict[str, str]:
    """What a stage started by this process needs to check, before it commits, that its runner still holds the lock."""
    from panoworld.framework.stage import LOCK_ENV, LOCK_INODE_ENV, RUNNER_PID_ENV

    try:
        st = os.stat(scene.artifacts)
        inode = f"{st.st_dev}:{st.st_ino}"
    except OSError:
        inode = ""
    return {LOCK_ENV: str(scene.artifacts / art.LOCK_FILE), LOCK_INODE_ENV: inode, RUNNER_PID_ENV: str(os.getpid())}


def _run_subprocess(node: StageNode, scene: Scene, params: Any, echo: bool) -> tuple[int, float, float]:
    """Run `python -m <stage module>` with explicit inputs; returns (exit code, seconds, peak RSS MB)."""
    from panoworld.framework.stage import REFUSAL_ENV, params_to_dict

    template = stage_command(node, scene, "{params_file}", python="{python}")
    env = {**runner_env(scene), REFUSAL_ENV: str(refusal_file(scene.log_file(node.name)))}
    return run_with_params_file(template, params_to_dict(params), scene.log_file(node.name), echo, env)


def refusal_file(log: Path) -> Path:
    """Where a stage started by this runner writes the one line refusing its input (exit 2)."""
    return log.with_name(f".{log.stem}.refusal")


StageExecutor = Callable[[StageNode, Scene, Any, bool], tuple[int, float, float]]
"""Runs one stage whose cache decision was taken (pipeline.run's `execute` hook): (node, scene, params, echo) ->
(exit code, seconds, peak RSS MB). The default runs a local subprocess; panoworld.tools.batch submits Ray tasks."""


MAX_REASON_CHARS = 400
"""A failed stage's reason is cut to this many characters in the run table and on stderr (the log has it all)."""


def _failure_line(log: Path, stage: str) -> str:
    """The one-line reason a failed stage gave: its `error: stage NAME: ...` line, else the last line of its log."""
    try:
        lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines()[-200:] if ln.strip()]
    except OSError:
        return ""
    prefix = f"error: stage {stage}: "
    line = next((ln[len(prefix):] for ln in reversed(lines) if ln.startswith(prefix)),
                lines[-1] if lines and not lines[-1].startswith("$ ") else "")
    return line if len(line) <= MAX_REASON_CHARS else line[:MAX_REASON_CHARS] + " ... (cut)"


def run(
    scene_dir: Path | str,
    *,
    only: list[str] = (),
    from_: str | None = None,
    until: str | None = None,
    force: bool = False,
    sets: list[str] = (),
    preset: str | None = None,
    dry_run: bool = False,
    keep_going: bool = False,
    echo: bool = False,
    pipeline: Pipeline | None = None,
    on_result: Callable[[StageResult], None] | None = None,
    variant: tuple[str, list[str]] | None = None,
    execute: StageExecutor | None = None,
) -> Report:
    """Bring the scene's artifacts up to date; the library API behind `runner.py run`."""
    pipeline = pipeline or Pipeline.load()
    selected, forced = _select(pipeline, list(only), from_, until)
    set_map = parse_sets(list(sets), pipeline)
    plain = not (only or from_ or until or force or dry_run) and variant is None and execute is None
    if plain:
        replayed = _replay(_record_key(pipeline, Path(scene_dir).absolute(), _config_digest(scene_dir), preset, sets),
                           scene_dir, on_result)
        if replayed is not None:
            return replayed
    from panoworld.framework import kernels
    from panoworld.framework.hub import resolve as hub

    scene = open_scene(scene_dir, pipeline)
    if variant is not None:  # the variant's --set values override the run's; their stages and descendants are its tail
        name, vsets = variant
        vmap = parse_sets(list(vsets), pipeline)
        for stage, values in vmap.items():
            set_map.setdefault(stage, {}).update(values)
        tail = set(vmap).union(*(pipeline.descendants(st) for st in vmap))
        scene = dataclasses.replace(scene, variant=name, tail=frozenset(tail))
    params = resolve_params(pipeline, preset, scene, set_map, [n for n in pipeline.order if n in selected or n in set_map])
    key = _record_key(pipeline, scene.root, scene.config_digest, preset, sets) if plain else None
    if force:
        forced |= selected
    if not dry_run:  # an `hf:` weights id missing from the local cache: one line naming `weights fetch`, nothing run
        for name in (n for n in pipeline.order if n in selected):
            try:
                hub.check_params_weights(params[name], where=f"{name}.")
            except hub.WeightsNotFound as e:
                raise PipelineError(str(e)) from None
    report = Report(scene.root, notes=list(scene.notes))

    def emit(r: StageResult):
        report.results.append(r)
        if on_result:
            on_result(r)

    if dry_run:
        for name in pipeline.order:
            node = pipeline.stages[name]
            if name not in selected:
                emit(StageResult(name, "skipped", "not selected"))
                continue
            up, why = stage_state(node, scene, params[name])
            stale_up = [u for u in pipeline.upstream(name) if any(r.stage == u and r.action == "would-run" for r in report.results)]
            if name in forced:
                emit(StageResult(name, "would-run", "forced (--force/--from)" if up else why))
            elif stale_up and not only:
                emit(StageResult(name, "would-run", f"upstream will rerun: {', '.join(stale_up)}"))
            else:
                emit(StageResult(name, "would-run" if not up else "cached", why))
        return report

    blocked: set[str] = set()  # stages that failed or were skipped because of a failure
    compiling: list = []
    fresh = not scene.artifacts.exists()
    with SceneLock(scene) as lock:
        watch = _watch(pipeline, scene) if key is not None else None
        for name in pipeline.order:
            node = pipeline.stages[name]
            art.recover_dir(scene.artifact_dir(name))
            if name not in selected:
                emit(StageResult(name, "skipped", "not selected"))
                continue
            bad_up = [u for u in pipeline.upstream(name) if u in blocked]
            if bad_up:
                blocked.add(name)
                emit(StageResult(name, "skipped", f"upstream {', '.join(bad_up)} failed"))
                continue
            missing = [
                f"{r.name} ({r.source + '.' if r.source == 'scene' else 'stage '}{r.target})"
                for r, p in zip(node.inputs, _input_paths(node, scene).values())
                if p is None and not r.optional
            ]
            if missing:
                blocked.add(name)
                emit(StageResult(name, "failed", f"missing input: {', '.join(missing)}; run the upstream stage first"))
                if not keep_going:
                    break
                continue
            up, why = stage_state(node, scene, params[name])
            if up and name not in forced:
                emit(StageResult(name, "cached", why))
                continue
            reason = "forced" if up else why
            if execute is None and not compiling:  # numba's cache cold: its kernels compile while earlier stages run
                compiling = [kernels.start_background_compile() if selected & set(kernels.KERNEL_STAGES) else None]
                report.compile_process = compiling[0]
            waited = kernels.wait_for_stage(compiling[0], name) if execute is None else 0.0
            if echo and waited >= 1.0:
                print(f"[{name}] waited {waited:.1f} s for its numba kernels (compiled once, in the background)",
                      file=sys.stderr, flush=True)
            code, secs, rss = (execute or _run_subprocess)(node, scene, params[name], echo)
            if code == 0:
                try:
                    rss = art.read_manifest(scene.artifact_dir(name), node.spec.artifact)["peak_rss_mb"]
                except art.ArtifactError:
                    pass  # keep the (upper-bound) figure of wait4
                emit(StageResult(name, "ran", reason, secs, rss))
            elif code == 2:  # the stage refused its input: one line, its log not kept
                blocked.add(name)
                part, refusal = pending_log(scene.log_file(name)), refusal_file(scene.log_file(name))
                why = refusal.read_text().strip() if refusal.is_file() else _failure_line(part, name)
                part.unlink(missing_ok=True)
                refusal.unlink(missing_ok=True)
                emit(StageResult(name, "failed", f"bad input: {why or 'see the stage output above'}", secs, rss,
                                 bad_input=True))
            else:
                blocked.add(name)
                why = _failure_line(scene.log_file(name), name)
                emit(StageResult(name, "failed", f"exit code {code}: {why}; log: {scene.log_file(name)}" if why else
                                 f"exit code {code}; log: {scene.log_file(name)}", secs, rss))
                if not keep_going:
                    break
        done = {r.stage for r in report.results}
        for name in pipeline.order:
            if name not in done:
                emit(StageResult(name, "skipped", "not run: an earlier stage failed (use --keep-going)"))
        if fresh and not any(r.action == "ran" for r in report.results):
            lock.remove_bookkeeping()  # nothing committed into a new artifacts/: leave the scene as it was
        if "register" in pipeline.stages and any(r.stage == "register" and r.action in ("ran", "cached")
                                                  for r in report.results):
            from panoworld.register.artifact import registration_note

            note = registration_note(scene.artifact_dir("register"), scene.root)
            if note:
                report.notes.append(note)
        if key is not None:
            _record(key, pipeline, scene, params, report, watch)
    return report


def _record_key(pipeline: Pipeline, root: Path, config_digest: str | None, preset: str | None, sets) -> str:
    """The up-to-date record's key of a plain run: its arguments and the texts of pipeline.yaml and scene.yaml."""
    return uptodate.record_key(root, pipeline.path, [pipeline.text_digest, config_digest, preset, list(sets)])


def _config_digest(scene_dir: Path | str) -> str | None:
    try:
        return text_digest((Path(scene_dir) / SCENE_CONFIG).read_text(errors="replace"))
    except OSError:
        return None


def _watch(pipeline: Pipeline, scene: Scene) -> tuple[list[str], list] | None:
    """(paths, their stats now) of what this run's decisions read (uptodate.watched_paths); None when no record can
    stand for them."""
    paths = uptodate.watched_paths(scene.root, pipeline.path, [(scene.artifact_dir(n), pipeline.stages[n].spec.module)
                                                                for n in pipeline.order])
    return None if paths is None else (paths, uptodate.stats(paths))


def _record(key: str, pipeline: Pipeline, scene: Scene, params: dict[str, Any], report: Report,
            watch: tuple[list[str], list] | None) -> None:
    """After a plain run under the lock: record what a no-op of the same arguments reports while nothing it read
    changes (uptodate); the stats are those taken before the decisions that found every stage up to date (for a run
    that ran stages, decided again here)."""
    if [r.stage for r in report.results] != pipeline.order or any(r.action not in ("cached", "ran") for r in report.results):
        uptodate.drop(key)
        return
    results = report.results
    if any(r.action == "ran" for r in results):
        watch = _watch(pipeline, scene)
        if watch is not None:
            results = [StageResult(n, "cached", why) for n in pipeline.order
                       for up, why in [stage_state(pipeline.stages[n], scene, params[n])] if up]
    if watch is None or len(results) != len(pipeline.order):
        uptodate.drop(key)
        return
    uptodate.save(key, *watch, [r.as_dict() for r in results], list(report.notes))


def _replay(key: str, scene_dir: Path | str, on_result: Callable[[StageResult], None] | None) -> Report | None:
    """The report a plain run recorded (_record) when none of the files its decisions read has changed since, checked
    under the scene lock; None otherwise."""
    root = Path(scene_dir).absolute()
    if not (root / ARTIFACTS_DIRNAME).is_dir():
        return None
    with SceneLock(Scene(root, {}, {})):
        rec = uptodate.replayable(key)
        try:
            report = Report(root, notes=[str(n) for n in rec["notes"]], results=[StageResult(**r) for r in rec["results"]])
        except (TypeError, KeyError):  # no record, or not one this runner wrote
            return None
        for r in report.results:
            if on_result:
                on_result(r)
    return report


def status(scene_dir: Path | str, *, preset: str | None = None, sets: list[str] = (), pipeline: Pipeline | None = None) -> list[dict]:
    """Each stage's state and reason, and its artifact's path and schema version (reads manifests, hashes nothing big)."""
    pipeline = pipeline or Pipeline.load()
    scene = open_scene(scene_dir, pipeline)
    set_map = parse_sets(list(sets), pipeline)
    all_params = resolve_params(pipeline, preset, scene, set_map, pipeline.order)  # bad params: exit 2 before any row
    rows = []
    for name in pipeline.order:
        node = pipeline.stages[name]
        params = all_params[name]
        up, why = stage_state(node, scene, params)
        d = scene.artifact_dir(name)
        sv = None
        if (d / art.MANIFEST).is_file():
            try:
                sv = json.loads((d / art.MANIFEST).read_text()).get("schema_version")
            except (OSError, json.JSONDecodeError):
                sv = None
        rows.append(
            {
                "stage": name,
                "state": "up-to-date" if up else "stale",
                "reason": why,
                "artifact": str(d),
                "schema": node.spec.artifact,
                "schema_version": sv,
                "accepted_schema_versions": art.accepted_schema_versions(node.spec.artifact),
            }
        )
    return rows
