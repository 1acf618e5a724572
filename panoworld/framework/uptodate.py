"""Up-to-date records: the stat of every file a run's cache decisions read, replayed while none of them changes."""

from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Any

from panoworld.framework import code_digest
from panoworld.io.manifest import ARTIFACTS_DIRNAME, MANIFEST, REPO_ROOT, VARIANTS_DIRNAME, schema_dirs
from panoworld.io.user_cache import user_cache_path

RECORD_DIR = "uptodate"
"""The records' folder in the user cache: one file per scene, pipeline, preset and --set list."""
KEEP = 256
"""Records kept (the most recently written)."""
MAX_SCENE_ENTRIES = 20_000
"""A scene folder with more files and folders than this (outside artifacts/) gets no record."""
FORMAT = 1
"""The records' layout (part of the key: a runner reading another layout finds no record)."""
ENV_PREFIXES = ("PANOWORLD_", "HF_", "HUGGINGFACE_", "XDG_CACHE_HOME")
"""Environment variables that can change what a run decides (schema path, weights caches)."""


def record_key(scene_root: Path, pipeline_path: Path, args: Any) -> str:
    """The record's name: a digest of the scene, the pipeline file, the run's arguments (JSON values) and what else
    the decisions depend on (the checkout, the interpreter, its import path, the environment variables above)."""
    doc = {
        "format": FORMAT, "scene": str(scene_root), "pipeline": str(Path(pipeline_path).absolute()), "args": args,
        "repo": str(REPO_ROOT), "python": [sys.version, sys.executable], "path": sys.path,
        "env": sorted((k, v) for k, v in os.environ.items() if k.startswith(ENV_PREFIXES)),
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:32]


def _record_path(key: str) -> Path:
    return user_cache_path(RECORD_DIR) / f"{key}.json"


def stat_of(path: str) -> list[int] | None:
    """(size, mtime, ctime, inode, device) of path, None when it is missing: a write of any kind changes the ctime,
    which no tool sets back."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev]


def _walk(top: Path, skip_top: str | None = None) -> list[str] | None:
    """Every folder and file under top (top included, the top-level entry skip_top left out, linked folders
    followed); None past MAX_SCENE_ENTRIES (a link loop included)."""
    out = [str(top)]
    for root, dirs, files in os.walk(top, followlinks=True):
        if root == str(top) and skip_top in dirs:
            dirs.remove(skip_top)
        out += [os.path.join(root, n) for n in dirs + files]
        if len(out) > MAX_SCENE_ENTRIES:
            return None
    return out


def _module_roots(mod: Any) -> tuple[str, ...]:
    """The code roots of a stage module (code_digest.stage_roots)."""
    name = getattr(getattr(mod, "__spec__", None), "name", None) or mod.__name__  # `python -m` runs it as __main__
    return tuple(map(str, code_digest.stage_roots(mod.__file__, name)))


def _find(rel: str, roots: tuple[str, ...]) -> str | None:
    """The file of a code digest's relative path: under the first root that has it (as code_digest finds it)."""
    return next((os.path.join(r, rel) for r in roots if os.path.isfile(os.path.join(r, rel))), None)


def watched_paths(scene_root: Path, pipeline_path: Path, stages: list[tuple[Path, Any]]) -> list[str] | None:
    """Every path whose content the run's decisions read: pipeline.yaml, the scene folder outside artifacts/ (its
    inputs and scene.yaml), the folders the runner checks inside artifacts/, each (artifact folder, stage module)'s manifest, files and code, the schemas, and the
    runner's own code (the modules this process loaded from a code root and what the pipeline module imports), with
    the folders of the code (a new module there can change what an import finds). None when a record cannot stand for
    the decisions (a scene folder past MAX_SCENE_ENTRIES, an artifact missing or naming weights, which live outside
    the scene)."""
    scene = _walk(Path(scene_root), ARTIFACTS_DIRNAME)
    if scene is None:
        return None
    arts = Path(scene_root) / ARTIFACTS_DIRNAME
    paths = [str(Path(pipeline_path).absolute()), *scene, str(arts / "logs"), str(arts / VARIANTS_DIRNAME)]
    rels: dict[tuple[str, ...], set[str]] = {}  # code files by the roots they are found under
    for d, mod in stages:
        try:
            manifest = json.loads((d / MANIFEST).read_text())
            if manifest.get("weights"):
                return None
            paths += [str(d / MANIFEST)] + [str(d / rel) for rel in manifest["files"]]
            rels.setdefault(_module_roots(mod), set()).update(manifest["code"]["files"])
        except (OSError, ValueError, TypeError, KeyError, AttributeError):
            return None
    rels.setdefault((str(REPO_ROOT),), set()).update(code_digest.code_digests("panoworld.framework.pipeline"))
    code = {f for mod_roots, names in rels.items() for rel in names if (f := _find(rel, mod_roots))}
    roots = {r for mod_roots in rels for r in mod_roots}
    for d in schema_dirs():
        paths.append(str(d))
        if d.is_dir():
            paths += sorted(str(p) for p in d.glob("*.schema.json"))
    for m in list(sys.modules.values()):
        f = getattr(m, "__file__", None)
        if f and any(os.path.abspath(f).startswith(r + os.sep) for r in roots):
            code.add(os.path.abspath(f))
    return paths + sorted(code | {os.path.dirname(f) for f in code} | roots)


def stats(paths: list[str]) -> list[list[int] | None]:
    return [stat_of(p) for p in paths]


def save(key: str, paths: list[str], before: list[list[int] | None], results: list[dict[str, Any]],
         notes: list[str]) -> None:
    """Record the run's report with the stats its paths had before the decisions that found every stage up to date,
    when they still have them (a file changed meanwhile: no record); keep the KEEP newest. A read-only cache only
    costs the decisions again next time."""
    if stats(paths) != before:
        return
    path = _record_path(key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"paths": paths, "stats": before, "results": results, "notes": notes}))
        os.replace(tmp, path)
        names = [n for n in os.listdir(path.parent) if n.endswith(".json")]
        if len(names) > KEEP:
            records = sorted((path.parent / n for n in names), key=lambda p: p.stat().st_mtime_ns)
            for old in records[:-KEEP]:
                old.unlink(missing_ok=True)
    except OSError:
        pass


def drop(key: str) -> None:
    """Forget the record (a run that decided anything but a no-op)."""
    try:
        _record_path(key).unlink(missing_ok=True)
    except OSError:
        pass


def replayable(key: str) -> dict[str, Any] | None:
    """The record of key ({paths, stats, results, notes}) when every path it watches has the stat it had; None
    otherwise."""
    try:
        rec = json.loads(_record_path(key).read_text())
        paths, recorded = rec["paths"], rec["stats"]
    except (OSError, ValueError, TypeError, KeyError):
        return None
    if not isinstance(paths, list) or not paths or len(paths) != len(recorded) or any(
            stat_of(p) != s for p, s in zip(paths, recorded)):
        return None
    return rec
