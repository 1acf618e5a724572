"""The stage contract: inputs, keyword-only params dataclasses, CLI flags derived from them, and transactional execution."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import enum
import importlib
import inspect
import json
import os
import resource
import shutil
import signal
import sys
import textwrap
import time
import types
import typing
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from panoworld import artifacts as art
from panoworld import code_digest
from panoworld.errors import InputError, PanoWorldError, PipelineError
from panoworld.hub import resolve as hub

LOCK_FILE = ".lock"
"""The scene lock, SCENE/artifacts/.lock: held (flock) by the runner working on the scene, naming its pid."""
LOCK_ENV = "PANOWORLD_SCENE_LOCK"
RUNNER_PID_ENV = "PANOWORLD_RUNNER_PID"
"""Set by a local runner for the stages it starts: the lock it holds and its pid (see check_runner)."""

StageInputError = InputError
"""Bad input to a stage (missing/unreadable file, wrong size, ...): exit code 2, one-line message."""


@dataclass(frozen=True)
class Input:
    """One named input of a stage: a scene file or another stage's artifact directory."""

    kind: str
    """'file' for a scene file, otherwise the artifact kind (schema name) of the upstream artifact."""
    optional: bool = False
    """Whether the stage runs without it."""
    help: str = ""
    """One line for --help."""


@dataclass(frozen=True)
class StageSpec:
    name: str
    version: str
    artifact: str
    inputs: dict[str, Input]
    params_cls: type
    module: types.ModuleType


def stage_code(spec: StageSpec) -> dict[str, str]:
    """{file: digest} of the stage module and the project modules it imports (panoworld.code_digest)."""
    mod = spec.module
    name = getattr(getattr(mod, "__spec__", None), "name", None) or mod.__name__  # `python -m` runs it as __main__
    return code_digest.code_digests(name, code_digest.stage_roots(mod.__file__, name))


def load_stage(name_or_module: str | types.ModuleType) -> StageSpec:
    """Import `stages.<name>` (or take a module) and check that it follows the stage contract."""
    mod = name_or_module
    if isinstance(mod, str):
        mod = importlib.import_module(mod if "." in mod else f"stages.{mod}")
    missing = [a for a in ("NAME", "VERSION", "ARTIFACT", "INPUTS", "Params", "run") if not hasattr(mod, a)]
    if missing:
        raise TypeError(f"stage module {mod.__name__} lacks {missing} (see panoworld/stage.py)")
    return StageSpec(mod.NAME, str(mod.VERSION), mod.ARTIFACT, dict(mod.INPUTS), mod.Params, mod)


# ---------------------------------------------------------------- params


def field_docs(cls: type) -> dict[str, str]:
    """Docstrings written under each dataclass field (PEP 257 attribute docstrings)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body
        for a, b in zip(body, body[1:]):
            if (
                isinstance(a, ast.AnnAssign)
                and isinstance(a.target, ast.Name)
                and isinstance(b, ast.Expr)
                and isinstance(getattr(b, "value", None), ast.Constant)
                and isinstance(b.value.value, str)
            ):
                docs[a.target.id] = " ".join(b.value.value.split())
    return docs


def _unwrap_optional(tp):
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return rest[0], True
    return tp, False


def coerce(value: Any, tp: Any, where: str) -> Any:
    """Convert a JSON/YAML/CLI value into the field type; ValueError names `where` on failure."""
    tp, optional = _unwrap_optional(tp)
    if value is None or (optional and isinstance(value, str) and value.lower() in ("none", "null")):
        if optional:
            return None
        raise ValueError(f"{where}: None is not allowed")
    origin = typing.get_origin(tp)
    try:
        if inspect.isclass(tp) and issubclass(tp, enum.Enum):
            try:
                return tp(value)
            except ValueError:
                raise ValueError(f"{where}: {value!r} is not one of {[m.value for m in tp]}") from None
        if tp is bool:
            if isinstance(value, bool):
                return value
            if str(value).lower() in ("1", "true", "yes", "on"):
                return True
            if str(value).lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(f"{where}: {value!r} is not a boolean")
        if tp is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(f"{where}: {value!r} is not an integer")
            return int(value)
        if tp is float:
            return float(value)
        if tp is str:
            return str(value)
        if tp is Path:
            return str(value)
        if origin in (tuple, list):
            (item_tp, *_) = typing.get_args(tp) or (str,)
            items = value.split(",") if isinstance(value, str) else list(value)
            return tuple(coerce(v.strip() if isinstance(v, str) else v, item_tp, where) for v in items if v != "")
    except (TypeError, ValueError) as e:
        if str(e).startswith(where):
            raise
        raise ValueError(f"{where}: cannot read {value!r} as {getattr(tp, '__name__', tp)}") from None
    return value


def params_from_dict(cls: type, values: dict[str, Any], where: str = "params") -> Any:
    """Build a params dataclass from plain values; unknown names are a ValueError naming them."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"{where}: unknown param(s) {unknown}; known: {sorted(names)}")
    kwargs = {k: coerce(v, hints[k], f"{where}.{k}") for k, v in values.items()}
    return cls(**kwargs)


def params_to_dict(params: Any) -> dict[str, Any]:
    """JSON-ready dict of a params dataclass (enums as values, tuples as lists)."""

    def plain(v):
        if isinstance(v, enum.Enum):
            return v.value
        if isinstance(v, (tuple, list)):
            return [plain(x) for x in v]
        if isinstance(v, Path):
            return str(v)
        return v

    return {f.name: plain(getattr(params, f.name)) for f in dataclasses.fields(params)}


def params_hash(params_dict: dict[str, Any]) -> str:
    return art.json_digest(params_dict)


def cache_key(version: str, p_hash: str, input_digests: dict[str, str | None], weights: dict | None = None,
              code: str | None = None) -> str:
    """Stage version + params hash + input digests (+ the content digest of each weights param that is set, + the
    stage's code digest)."""
    doc = {"version": version, "params": p_hash, "inputs": input_digests}
    if weights:
        doc["weights"] = weights
    if code is not None:
        doc["code"] = code
    return art.json_digest(doc)


def resolve_stage_weights(params: Any, hints: dict | None = None, *, stage: str = "") -> dict[str, dict]:
    """{param: record} of every weights-like param that is set (a local path or an `hf:` id, resolved offline);
    StageInputError naming the `weights fetch` command when an id is not in the local cache."""
    try:
        return hub.resolve_params_weights(params, hints, where=f"{stage}." if stage else "")
    except hub.WeightsNotFound as e:
        raise StageInputError(str(e)) from None


def previous_weights(out_dir: Path) -> dict | None:
    """The `weights` records of the artifact already in out_dir (digest hints: unchanged files are not re-hashed)."""
    try:
        return json.loads((Path(out_dir) / art.MANIFEST).read_text()).get("weights")
    except (OSError, ValueError, AttributeError):
        return None


# ---------------------------------------------------------------- inputs


def input_digest(name: str, spec: Input, path: Path | None) -> str | None:
    """Digest of one input: file content hash, or the upstream manifest's content digest."""
    if path is None:
        if not spec.optional:
            raise StageInputError(f"missing required input --{name.replace('_', '-')}")
        return None
    path = Path(path)
    if spec.kind == "file":
        if not path.is_file():
            raise StageInputError(f"input {name}: file not found: {path}")
        return art.file_digest(path)
    try:
        manifest = art.read_manifest(path, spec.kind)
    except art.ArtifactError as e:
        raise StageInputError(f"input {name}: {e}; run the stage that produces it first") from None
    problem = art.verify_files(path, manifest)
    if problem:
        raise StageInputError(f"input {name}: {problem}; rerun the stage that produces it")
    return manifest["digest"]


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MB.

    Linux's VmHWM belongs to the address space created at exec, unlike ru_maxrss, which inherits the parent's
    high-water mark across fork and exec (every stage started by the runner would report the runner's peak).
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def die_with_runner() -> None:
    """In a stage started by a local runner: be killed when the runner dies (Linux PR_SET_PDEATHSIG), and exit at once
    if it is already gone."""
    pid = os.environ.get(RUNNER_PID_ENV)
    if not pid:
        return
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
    if os.getppid() != int(pid):
        raise PipelineError(f"the runner (pid {pid}) that started this stage is gone; not running")


def check_runner() -> None:
    """Refuse to commit unless the runner that started this stage is still its parent and still holds the scene lock
    (a no-op for a stage run by hand or by a Ray worker)."""
    lock, pid = os.environ.get(LOCK_ENV), os.environ.get(RUNNER_PID_ENV)
    if not lock or not pid:
        return
    try:
        holder = Path(lock).read_text()
    except OSError:
        holder = ""
    if os.getppid() != int(pid) or not holder.startswith(f"pid {pid} "):
        raise PipelineError(f"the runner (pid {pid}) that started this stage is gone or no longer holds {lock}; "
                            "not committing")


def execute_stage(
    spec: StageSpec, inputs: dict[str, Path | None], params: Any, out_dir: Path, *, input_digests: dict | None = None
) -> dict:
    """Run one stage transactionally into out_dir and return its manifest.

    The stage writes into a temporary sibling directory; the manifest is written last and the directory is
    renamed into place only on success, so a failure or kill leaves the previous artifact untouched.
    """
    out_dir = Path(out_dir)
    inputs = {k: (Path(v) if v is not None else None) for k, v in inputs.items()}
    unknown = sorted(set(inputs) - set(spec.inputs))
    if unknown:
        raise StageInputError(f"stage {spec.name}: unknown input(s) {unknown}; known: {sorted(spec.inputs)}")
    full_inputs = {name: inputs.get(name) for name in spec.inputs}
    if input_digests is None:
        input_digests = {name: input_digest(name, s, full_inputs[name]) for name, s in spec.inputs.items()}
    pdict = params_to_dict(params)
    phash = params_hash(pdict)
    weights = resolve_stage_weights(params, previous_weights(out_dir), stage=spec.name)
    code = stage_code(spec)
    key = cache_key(spec.version, phash, input_digests, hub.weights_key(weights), code_digest.combined(code))

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    art.recover_dir(out_dir)
    tmp = art.tmp_dir_for(out_dir)
    tmp.mkdir(parents=True)
    started = datetime.now(UTC).isoformat()
    t0 = time.perf_counter()
    try:
        info = spec.module.run(full_inputs, hub.with_resolved_paths(params, weights), tmp) or {}
        files = art.list_files(tmp)
        if not files:
            raise RuntimeError(f"stage {spec.name} wrote no files")
        manifest = {
            "schema": spec.artifact,
            "schema_version": art.current_schema_version(spec.artifact),
            "stage": spec.name,
            "stage_version": spec.version,
            "params": pdict,
            "params_hash": phash,
            "inputs": {
                name: {"path": str(full_inputs[name]) if full_inputs[name] else None, "digest": d}
                for name, d in input_digests.items()
            },
            **({"weights": weights} if weights else {}),
            "code": {"digest": code_digest.combined(code), "files": code},
            "key": key,
            "files": files,
            "digest": art.files_digest(files),
            "started": started,
            "finished": datetime.now(UTC).isoformat(),
            "wall_s": time.perf_counter() - t0,
            "peak_rss_mb": peak_rss_mb(),
            "info": _jsonable(info),
        }
        art.write_manifest(tmp, manifest, spec.artifact)
        check_runner()
        art.commit_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return manifest


def _jsonable(obj: Any) -> Any:
    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


# ---------------------------------------------------------------- CLI


def build_parser(spec: StageSpec) -> argparse.ArgumentParser:
    doc = (spec.module.__doc__ or "").strip().splitlines()
    parser = argparse.ArgumentParser(
        prog=f"python -m stages.{spec.name}",
        description=(doc[0] if doc else spec.name) + " Runs without the runner: give inputs and --out explicitly.",
    )
    g_in = parser.add_argument_group("inputs")
    for name, inp in spec.inputs.items():
        what = "file" if inp.kind == "file" else f"{inp.kind} artifact directory"
        g_in.add_argument(
            f"--{name.replace('_', '-')}", dest=f"in_{name}", type=Path, required=not inp.optional,
            help=f"{inp.help} ({what}{', optional' if inp.optional else ''})",
        )
    parser.add_argument("--out", type=Path, required=True, help=f"output {spec.artifact} artifact directory")
    parser.add_argument("--params-file", type=Path, help="JSON file of params (flags below override it)")
    g_p = parser.add_argument_group("params")
    docs = field_docs(spec.params_cls)
    hints = typing.get_type_hints(spec.params_cls)
    for f in dataclasses.fields(spec.params_cls):
        tp, _ = _unwrap_optional(hints[f.name])
        default = f.default if f.default is not dataclasses.MISSING else None
        if isinstance(default, enum.Enum):
            default = default.value
        choices = [m.value for m in tp] if inspect.isclass(tp) and issubclass(tp, enum.Enum) else None
        g_p.add_argument(
            f"--{f.name.replace('_', '-')}", dest=f"p_{f.name}", default=None, choices=choices,
            metavar=None if choices else tp.__name__.upper() if hasattr(tp, "__name__") else "VALUE",
            help=f"{docs.get(f.name, '')} (default: {default})",
        )
    return parser


def stage_main(module_name: str, argv: list[str] | None = None) -> int:
    """The thin `main()` every stage module exposes: parse flags from the params dataclass and run."""
    spec = load_stage(sys.modules[module_name])
    args = build_parser(spec).parse_args(argv)
    try:
        die_with_runner()
        values: dict[str, Any] = {}
        if args.params_file:
            try:
                values.update(json.loads(args.params_file.read_text()))
            except (OSError, json.JSONDecodeError) as e:
                raise StageInputError(f"--params-file {args.params_file}: {e}") from None
        for f in dataclasses.fields(spec.params_cls):
            v = getattr(args, f"p_{f.name}")
            if v is not None:
                values[f.name] = v
        try:
            params = params_from_dict(spec.params_cls, values, where=spec.name)
        except ValueError as e:
            raise StageInputError(str(e)) from None
        inputs = {name: getattr(args, f"in_{name}") for name in spec.inputs}
        manifest = execute_stage(spec, inputs, params, args.out)
    except PanoWorldError as e:
        print(f"error: stage {spec.name}: {e}", file=sys.stderr)
        return e.exit_code
    print(
        f"{spec.name}: wrote {args.out} ({len(manifest['files'])} files, {manifest['wall_s']:.2f} s, "
        f"peak {manifest['peak_rss_mb']:.0f} MB)",
        file=sys.stderr,
    )
    return 0
