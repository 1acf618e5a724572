"""The stage contract: inputs, the cache key, the runner's lock checks, and transactional execution."""

from __future__ import annotations

import fcntl
import importlib
import json
import os
import resource
import shutil
import time
import types
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from panoworld.core import registry
from panoworld.core.errors import InputError, PipelineError
from panoworld.framework import code_digest
from panoworld.framework.hub import resolve as hub
from panoworld.framework.stage_params import params_hash, params_to_dict
from panoworld.io import manifest as art
from panoworld.io.jsonio import to_jsonable

LOCK_ENV = "PANOWORLD_SCENE_LOCK"
LOCK_INODE_ENV = "PANOWORLD_SCENE_LOCK_INODE"
"""`DEV:INODE` of the artifacts directory the runner holds the flock of (a directory removed and made again is not
the one locked)."""
RUNNER_PID_ENV = "PANOWORLD_RUNNER_PID"
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
            from panoworld.core.limits import is_appledouble  # here: limits brings numpy, which a replayed run skips

            files = sorted(p for p in path.iterdir() if p.suffix.lower() in spec.suffixes and p.is_file()
                           and not is_appledouble(p))
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
