"""The stage contract: inputs, keyword-only params dataclasses, CLI flags derived from them, and transactional execution."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import enum
import fcntl
import functools
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
import traceback
import types
import typing
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from panoworld.core import params as P
from panoworld.core import registry
from panoworld.core.errors import InputError, PanoWorldError, PipelineError, from_os_error
from panoworld.framework import code_digest
from panoworld.framework.hub import resolve as hub
from panoworld.io import manifest as art
from panoworld.io.jsonio import to_jsonable

LOCK_ENV = "PANOWORLD_SCENE_LOCK"
LOCK_INODE_ENV = "PANOWORLD_SCENE_LOCK_INODE"
"""`DEV:INODE` of the artifacts directory the runner holds the flock of (a directory removed and made again is not
the one locked)."""
RUNNER_PID_ENV = "PANOWORLD_RUNNER_PID"
REFUSAL_ENV = "PANOWORLD_REFUSAL_FILE"
"""Set by a runner: a stage that refuses its input (exit 2) writes its one line there, for the runner to print once."""
"""Set by a local runner for the stages it starts: the lock it holds and its pid (see check_runner)."""

StageInputError = InputError
"""Bad input to a stage (missing/unreadable file, wrong size, ...): exit code 2, one-line message."""


@dataclass(frozen=True)
class Input:
    """One named input of a stage: a scene file or another stage's artifact directory."""

    kind: str
    """'file' for a scene file, 'dir' for a scene directory (digest over its files), otherwise the artifact kind
    (schema name) of the upstream artifact."""
    optional: bool = False
    """Whether the stage runs without it."""
    help: str = ""
    """One line for --help."""
    suffixes: tuple[str, ...] = ()
    """For kind 'dir': only its top-level files with these suffixes are the input (others are left out of the
    digest, so a stray notes.txt reruns nothing); empty: every file under it."""


@dataclass(frozen=True)
class StageSpec:
    name: str
    version: str
    artifact: str
    inputs: dict[str, Input]
    params_cls: type
    module: types.ModuleType


def stage_code(spec: StageSpec, params: Any = None) -> dict[str, str]:
    """{file: digest} of the stage module and the project modules it imports (panoworld.framework.code_digest); with
    params naming one backend (not auto), the stage's other backends are left out: the code this run executes."""
    mod = spec.module
    name = getattr(getattr(mod, "__spec__", None), "name", None) or mod.__name__  # `python -m` runs it as __main__
    return code_digest.code_digests(name, code_digest.stage_roots(mod.__file__, name), unused_backends(spec, params))


def unused_backends(spec: StageSpec, params: Any) -> frozenset[str]:
    """Modules of the stage's registered backends other than the one `params.backend` names (none for auto, or for a
    stage without backends). Backend modules of one stage never import each other (an import-linter contract), so
    leaving them out of the code digest leaves out nothing the chosen backend runs."""
    chosen = getattr(params, "backend", None)
    if chosen is None or str(chosen) == "auto":
        return frozenset()
    try:
        found = registry.backends(spec.name)
    except ModuleNotFoundError:
        return frozenset()
    if str(chosen) not in found:
        return frozenset()
    keep = found[str(chosen)].impl.__module__
    return frozenset(b.impl.__module__ for b in found.values()) - {keep}


def load_stage(name_or_module: str | types.ModuleType) -> StageSpec:
    """Import `stages.<name>` (or take a module) and check that it follows the stage contract."""
    mod = name_or_module
    if isinstance(mod, str):
        mod = importlib.import_module(mod if "." in mod else f"stages.{mod}")
    missing = [a for a in ("NAME", "VERSION", "ARTIFACT", "INPUTS", "Params", "run") if not hasattr(mod, a)]
    if missing:
        raise TypeError(f"stage module {mod.__name__} lacks {missing} (see panoworld/framework/stage.py)")
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


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """typing.get_type_hints of a params class, evaluated once per process (every layer of every stage asks)."""
    return typing.get_type_hints(cls)


@functools.cache
def _fields(cls: type) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(cls)}


def normalize(cls: type, values: Any, where: str) -> dict[str, Any]:
    """A nested {param: value} dict from a layer of values (dotted keys and old names resolved, options nested);
    ValueError naming the param (with a "did you mean") for unknown names and wrong shapes."""
    if not isinstance(values, dict):
        raise ValueError(f"{where}: expected a mapping of param: value, got {type(values).__name__} {values!r}")
    fields = _fields(cls)
    hints = _hints(cls)
    old = P.renamed(cls)
    out: dict[str, Any] = {}
    for key, v in values.items():
        key = old.get(str(key), str(key))
        head, dot, rest = key.partition(".")
        f = fields.get(head)
        if f is None:
            raise ValueError(f"{where}.{head}: unknown param{P.suggest(head, list(fields) + list(old))}")
        if P.is_options(f):
            if dot:
                v = {rest: v}
            if not isinstance(v, dict):
                raise ValueError(f"{where}.{head}: expected a mapping of {head} options, got {v!r}")
            sub = normalize(hints[head], v, f"{where}.{head}")
            out[head] = merge(out.get(head) or {}, sub)
        elif dot:
            raise ValueError(f"{where}.{head}: {head} has no sub-params (got {key})")
        else:
            out[head] = v
    return out


def merge(a: dict, b: dict) -> dict:
    """Deep merge of nested param dicts: b wins."""
    out = dict(a)
    for k, v in b.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _build(cls: type, values: dict[str, Any], where: str) -> Any:
    hints = _hints(cls)
    fields = _fields(cls)
    kwargs = {k: _build(hints[k], v, f"{where}.{k}") if P.is_options(fields[k]) else coerce(v, hints[k], f"{where}.{k}")
              for k, v in values.items()}
    return cls(**kwargs)


def params_from_dict(cls: type, values: Any, where: str = "params") -> Any:
    """Build and validate a params dataclass from plain values (nested or dotted `wan.steps`); ValueError
    `where.param=value: what is allowed` naming the first bad param."""
    return params_from_normalized(cls, normalize(cls, values, where), where)


def params_from_normalized(cls: type, values: dict[str, Any], where: str = "params") -> Any:
    """params_from_dict of values normalize() already returned."""
    params = _build(cls, values, where)
    P.validate(params, where)
    return params


def params_to_dict(params: Any) -> dict[str, Any]:
    """JSON-ready dict of a params dataclass (enums as values, tuples as lists, the chosen backend's options nested;
    the options of the other backends are left out, so they neither enter the cache key nor rerun the stage)."""
    return P.active_dict(params)


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


def stage_key(spec: StageSpec, params: Any, input_digests: dict[str, str | None], weights: dict | None = None,
              code: dict[str, str] | None = None) -> str:
    """The cache key of running `spec` with these params on inputs with these digests: the one definition used by
    the runner, execute_stage and precompute (version, params hash, input digests, weights digests, code digest;
    code: stage_code(spec, params) when the caller has it already)."""
    return cache_key(spec.version, params_hash(params_to_dict(params)), input_digests, hub.weights_key(weights or {}),
                     code_digest.combined(stage_code(spec, params) if code is None else code))


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
    if spec.kind == "dir":
        if not path.is_dir():
            raise StageInputError(f"input {name}: directory not found: {path}")
        if spec.suffixes:
            files = sorted(p for p in path.iterdir() if p.suffix.lower() in spec.suffixes and p.is_file())
        else:
            files = sorted(p for p in path.rglob("*") if p.is_file() and art.ARTIFACTS_DIRNAME not in p.relative_to(path).parts)
        return art.json_digest([[p.relative_to(path).as_posix(), art.file_digest(p)] for p in files])
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
    """Refuse to commit unless the runner that started this stage is still its parent and still holds the scene lock:
    the flock on the artifacts directory (of the inode it locked), and artifacts/.lock, when present, naming it
    (a no-op for a stage run by hand or by a Ray worker)."""
    lock, pid = os.environ.get(LOCK_ENV), os.environ.get(RUNNER_PID_ENV)
    if not lock or not pid:
        return
    try:
        holder: str | None = Path(lock).read_text()
    except FileNotFoundError:
        holder = None  # deleted by hand: the flock on the directory still decides
    except OSError:
        holder = ""
    held = dir_locked(Path(lock).parent, os.environ.get(LOCK_INODE_ENV))
    if os.getppid() != int(pid) or not held or (holder is not None and not holder.startswith(f"pid {pid} ")):
        raise PipelineError(f"the runner (pid {pid}) that started this stage is gone or no longer holds {lock}; "
                            "not committing")


def dir_locked(directory: Path, inode: str | None = None) -> bool:
    """Whether someone holds an exclusive flock on directory (and, with inode `DEV:INO`, it is that directory)."""
    try:
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return False
    try:
        st = os.fstat(fd)
        if inode and inode != f"{st.st_dev}:{st.st_ino}":
            return False
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


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
    code = stage_code(spec, params)
    key = stage_key(spec, params, input_digests, weights)

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    art.recover_dir(out_dir)
    tmp = art.tmp_dir_for(out_dir)
    tmp.mkdir(parents=True)
    started = datetime.now(UTC).isoformat()
    t0, c0 = time.perf_counter(), time.process_time()
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
            "cpu_s": time.process_time() - c0,
            "peak_rss_mb": peak_rss_mb(),
            "info": to_jsonable(info),
        }
        art.write_manifest(tmp, manifest, spec.artifact)
        check_runner()
        art.commit_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return manifest


# ---------------------------------------------------------------- CLI


def build_parser(spec: StageSpec) -> argparse.ArgumentParser:
    doc = (spec.module.__doc__ or "").strip().splitlines()
    parser = argparse.ArgumentParser(
        prog=f"python -m stages.{spec.name}",
        description=(doc[0] if doc else spec.name) + " Runs without the runner: give inputs and --out explicitly.",
    )
    g_in = parser.add_argument_group("inputs")
    for name, inp in spec.inputs.items():
        what = {"file": "file", "dir": "directory"}.get(inp.kind, f"{inp.kind} artifact directory")
        g_in.add_argument(
            f"--{name.replace('_', '-')}", dest=f"in_{name}", type=Path, required=not inp.optional,
            help=f"{inp.help} ({what}{', optional' if inp.optional else ''})",
        )
    parser.add_argument("--out", type=Path, required=True, help=f"output {spec.artifact} artifact directory")
    parser.add_argument("--params-file", type=Path, help="JSON file of params (flags below override it)")
    _add_param_flags(parser, parser.add_argument_group("params"), spec.params_cls, "")
    return parser


def _add_param_flags(parser: argparse.ArgumentParser, group, cls: type, prefix: str) -> None:
    """One flag per param (`--max-features`), nested backend options as `--wan-steps`; help from the field docstring
    and its declared rule."""
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    for old, new in P.renamed(cls).items():  # old flags keep working, unlisted
        group.add_argument("--" + old.replace("_", "-"), dest="p_" + new.replace(".", "__"), help=argparse.SUPPRESS)
    for f in dataclasses.fields(cls):
        if P.is_options(f):
            sub = parser.add_argument_group(f"{prefix}{f.name} options (--set STAGE.{prefix}{f.name}.PARAM=VALUE)")
            _add_param_flags(parser, sub, hints[f.name], f"{prefix}{f.name}.")
            continue
        tp, _ = _unwrap_optional(hints[f.name])
        default = P.plain(f.default) if f.default is not dataclasses.MISSING else None
        rule = P.rule_of(f)
        choices = [m.value for m in tp] if inspect.isclass(tp) and issubclass(tp, enum.Enum) else None
        if rule.choices is not None:
            choices = [P.plain(c) for c in rule.choices]
        allowed = rule.describe()
        name = f"{prefix}{f.name}"
        group.add_argument(
            "--" + name.replace(".", "-").replace("_", "-"), dest="p_" + name.replace(".", "__"), default=None,
            metavar=("{" + ",".join(map(str, choices)) + "}") if choices else tp.__name__.upper() if hasattr(tp, "__name__") else "VALUE",
            help=f"{docs.get(f.name, '')} (default: {default}{'; ' + allowed if allowed and not choices else ''})".replace("%", "%%"),
        )


def _param_flag_values(args: argparse.Namespace) -> dict[str, Any]:
    """{dotted param: value} of the param flags given on the command line."""
    return {k[2:].replace("__", "."): v for k, v in vars(args).items() if k.startswith("p_") and v is not None}


def stage_main(module_name: str, argv: list[str] | None = None) -> int:
    """The thin `main()` every stage module exposes: parse flags from the params dataclass and run."""
    # Before torch loads OpenMP: its idle threads sleep instead of spinning. On a busy 2-core machine spinning
    # threads made one Gaussian ERP render cost 122 CPU-s (222 s wall) instead of 23 (48 s): docs/multi.md, "Speed".
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
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
        try:
            flags = normalize(spec.params_cls, _param_flag_values(args), spec.name)
            values = merge(normalize(spec.params_cls, values, spec.name), flags)
            params = params_from_dict(spec.params_cls, values, where=spec.name)
        except ValueError as e:
            raise StageInputError(str(e)) from None
        inputs = {name: getattr(args, f"in_{name}") for name in spec.inputs}
        manifest = execute_stage(spec, inputs, params, args.out)
    except PanoWorldError as e:
        refusal = os.environ.get(REFUSAL_ENV)
        if refusal and e.exit_code == 2:
            Path(refusal).write_text(str(e))
        else:
            print(f"error: stage {spec.name}: {e}", file=sys.stderr)
        return e.exit_code
    except OSError as e:  # the environment (full disk, read-only output): one line
        err = from_os_error(e)
        if err.exit_code != 2:
            traceback.print_exc()  # kept in the stage's log; the runner shows the line below
        print(f"error: stage {spec.name}: {err}", file=sys.stderr)
        return err.exit_code
    print(
        f"{spec.name}: wrote {args.out} ({len(manifest['files'])} files, {manifest['wall_s']:.2f} s, "
        f"peak {manifest['peak_rss_mb']:.0f} MB)",
        file=sys.stderr,
    )
    return 0
