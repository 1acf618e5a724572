"""Versioned on-disk artifacts: manifests, digests, JSON-Schema validation and transactional writes."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from functools import cache
from pathlib import Path
from typing import Any

from panoworld.core.errors import ArtifactError
from panoworld.io.safe_write import atomic_output

MANIFEST = "manifest.json"
REPO_ROOT = Path(__file__).resolve().parents[2]
SCHEMA_DIR = REPO_ROOT / "artifacts_schema"
TMP_PREFIX = ".tmp-"
OLD_PREFIX = ".old-"
ARTIFACTS_DIRNAME = "artifacts"
"""A scene's artifacts live in SCENE/artifacts/<stage>/ (the scene layout is docs/architecture.md's)."""
LOCK_FILE = ".lock"
"""The scene lock, SCENE/artifacts/.lock: held (flock) by the runner working on the scene, naming its pid."""
VARIANTS_DIRNAME = "variants"
"""Sweep variants of the DAG's tail: SCENE/artifacts/variants/NAME/<stage>/."""
SCENE_CONFIG = "scene.yaml"


def file_digest(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def json_digest(obj: Any) -> str:
    return hashlib.sha256(canonical_json(obj).encode()).hexdigest()


def canonical_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def files_digest(files: dict[str, dict]) -> str:
    """Digest of an artifact's content: its relative paths with their sha256, order-independent."""
    return json_digest(sorted((rel, meta["sha256"]) for rel, meta in files.items()))


def schema_dirs() -> list[Path]:
    """artifacts_schema/ plus any directories in $PANOWORLD_SCHEMA_PATH (schemas of your own stages)."""
    extra = [Path(p) for p in os.environ.get("PANOWORLD_SCHEMA_PATH", "").split(os.pathsep) if p]
    return [SCHEMA_DIR, *extra]


@cache
def load_schema(kind: str) -> dict:
    for d in schema_dirs():
        path = d / f"{kind}.schema.json"
        if path.is_file():
            return json.loads(path.read_text())
    raise ArtifactError(f"no JSON Schema for artifact kind {kind!r} in {', '.join(map(str, schema_dirs()))}")


def manifest_checksum(manifest: dict) -> str:
    """Digest of the whole manifest except its own checksum field: any edit to it is detected."""
    return json_digest({k: v for k, v in manifest.items() if k != "checksum"})


@cache
def _validator(kind: str):
    import jsonschema
    from referencing import Registry, Resource

    base = load_schema("manifest")
    registry = Registry().with_resource(base["$id"], Resource.from_contents(base))
    schema = load_schema(kind)
    cls = jsonschema.validators.validator_for(schema)
    return cls(schema, registry=registry)


def accepted_schema_versions(kind: str) -> list[int]:
    schema = load_schema(kind)
    for part in schema.get("allOf", [schema]):
        sv = part.get("properties", {}).get("schema_version")
        if sv and "enum" in sv:
            return list(sv["enum"])
    raise ArtifactError(f"artifacts_schema/{kind}.schema.json does not declare properties.schema_version.enum")


def current_schema_version(kind: str) -> int:
    return max(accepted_schema_versions(kind))


_VALIDATED_FILE = "validated_manifests.json"
_VALIDATED_KEEP = 4096
_validated: dict[str, list[str]] | None = None
"""schema digest -> checksums of manifests that passed its JSON Schema (the user cache, loaded once)."""


_schema_digests: dict[str, tuple[dict, dict, str]] = {}


def _schema_digest(kind: str) -> str:
    """Digest of the schemas a manifest of `kind` is validated against (recomputed when load_schema reloads them)."""
    base, schema = load_schema("manifest"), load_schema(kind)
    hit = _schema_digests.get(kind)
    if hit is None or hit[0] is not base or hit[1] is not schema:
        hit = _schema_digests[kind] = (base, schema, json_digest([base, schema]))
    return hit[2]


def _validated_checksums(kind: str) -> list[str]:
    global _validated
    if _validated is None:
        from panoworld.io.user_cache import read_user_cache

        _validated = {k: v for k, v in read_user_cache(_VALIDATED_FILE).items() if isinstance(v, list)}
    return _validated.setdefault(_schema_digest(kind), [])


def _remember_valid(kind: str, checksum: str) -> None:
    global _validated
    from panoworld.io.user_cache import read_user_cache, write_user_cache

    known = _validated_checksums(kind)
    if checksum not in known:
        known.append(checksum)
        # merged with the file as it is now: other runs add theirs meanwhile, and replacing the file with this
        # process's view would only make them validate again
        merged = {k: v for k, v in read_user_cache(_VALIDATED_FILE).items() if isinstance(v, list)}
        for key, sums in _validated.items():
            merged[key] = list(dict.fromkeys(merged.get(key, []) + sums))[-_VALIDATED_KEEP:]
        _validated = merged
        write_user_cache(_VALIDATED_FILE, merged)


def validate_manifest(manifest: dict, kind: str, where: Path | str = "manifest") -> None:
    """Raise ArtifactError with a readable reason if the manifest does not match its kind's schema.

    A manifest with its checksum passed is remembered (by checksum, per schema text) in the user cache, so that
    read_manifest does not validate the same unedited manifest against the same schema again."""
    if manifest.get("schema") != kind:
        raise ArtifactError(f"{where}: schema is {manifest.get('schema')!r} but expected {kind!r}")
    sv = manifest.get("schema_version")
    accepted = accepted_schema_versions(kind)
    if sv not in accepted:
        raise ArtifactError(f"{where}: schema version {sv} of {kind!r} is no longer accepted (accepted: {accepted})")
    errors = sorted(_validator(kind).iter_errors(manifest), key=lambda e: list(e.path))
    if errors:
        e = errors[0]
        loc = "/".join(str(p) for p in e.path) or "<root>"
        raise ArtifactError(f"{where}: schema-invalid at {loc}: {e.message}")
    if isinstance(manifest.get("checksum"), str):
        _remember_valid(kind, manifest["checksum"])


def read_manifest(artifact_dir: Path, kind: str | None = None) -> dict:
    """Read and validate `artifact_dir/manifest.json`; raises ArtifactError naming the file and the reason."""
    path = Path(artifact_dir) / MANIFEST
    if not path.is_file():
        raise ArtifactError(f"{path}: missing")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ArtifactError(f"{path}: unreadable ({e})") from e
    if not isinstance(manifest, dict):
        raise ArtifactError(f"{path}: not a JSON object")
    kind = kind or str(manifest.get("schema"))
    checksum = manifest.get("checksum")
    unedited = isinstance(checksum, str) and manifest_checksum(manifest) == checksum
    if not (unedited and manifest.get("schema") == kind and checksum in _validated_checksums(kind)):
        validate_manifest(manifest, kind, path)
    if not unedited or files_digest(manifest["files"]) != manifest["digest"]:
        raise ArtifactError(f"{path}: checksum mismatch (manifest edited after it was written)")
    return manifest


_HASHES_FILE = "file_hashes.json"
_HASHES_KEEP = 20000
_hashes: dict[str, list] | None = None
"""absolute path -> [size, mtime_ns, sha256] of files re-hashed because their mtime no longer matched their manifest."""


def _rehash(p: Path, st: os.stat_result) -> tuple[str, bool]:
    """(sha256 of p, whether it was hashed now): a file re-hashed before with the same size and mtime is not read."""
    global _hashes
    if _hashes is None:
        from panoworld.io.user_cache import read_user_cache

        _hashes = read_user_cache(_HASHES_FILE)
    key = str(p.resolve())
    hit = _hashes.get(key)
    if isinstance(hit, list) and len(hit) == 3 and hit[:2] == [st.st_size, st.st_mtime_ns]:
        return str(hit[2]), False
    digest = file_digest(p)
    _hashes.pop(key, None)
    _hashes[key] = [st.st_size, st.st_mtime_ns, digest]
    for old in list(_hashes)[: max(0, len(_hashes) - _HASHES_KEEP)]:
        del _hashes[old]
    return digest, True


def verify_files(artifact_dir: Path, manifest: dict) -> str | None:
    """Cheap check that the files on disk are the ones the manifest describes; None if they are.

    Like DVC: compare size and mtime first and re-hash only files whose stat changed (once: the new stat of a file
    whose content still matches is remembered in the user cache, so a copied or touched artifact is read once).
    """
    artifact_dir = Path(artifact_dir)
    hashed = False
    try:
        for rel, meta in manifest["files"].items():
            p = artifact_dir / rel
            try:
                st = p.stat()
            except OSError:
                return f"output file missing: {p}"
            if st.st_size != meta["size"]:
                return f"output file changed: {p} (size {meta['size']} -> {st.st_size})"
            if st.st_mtime_ns != meta.get("mtime_ns"):
                digest, now = _rehash(p, st)
                hashed |= now
                if digest != meta["sha256"]:
                    return f"output file changed: {p} (content differs from manifest digest)"
        return None
    finally:
        if hashed:
            _save_hashes()


def _save_hashes() -> None:
    """Merge this process's re-hashed files into the file as it is now (other runs add theirs meanwhile), newest last."""
    global _hashes
    from panoworld.io.user_cache import read_user_cache, write_user_cache

    on_disk = {k: v for k, v in read_user_cache(_HASHES_FILE).items() if k not in _hashes}
    _hashes = dict(list({**on_disk, **_hashes}.items())[-_HASHES_KEEP:])
    write_user_cache(_HASHES_FILE, _hashes)


def list_files(root: Path) -> dict[str, dict]:
    """Hash every file under root (except the manifest) -> {relpath: {size, sha256, mtime_ns}}."""
    out = {}
    for p in sorted(Path(root).rglob("*")):
        if p.is_file() and p.name != MANIFEST:
            st = p.stat()
            out[p.relative_to(root).as_posix()] = {"size": st.st_size, "sha256": file_digest(p), "mtime_ns": st.st_mtime_ns}
    return out


def tmp_dir_for(out_dir: Path) -> Path:
    out_dir = Path(out_dir)
    return out_dir.parent / f"{TMP_PREFIX}{out_dir.name}-{os.getpid()}-{time.time_ns()}"


def write_manifest(tmp_dir: Path, manifest: dict, kind: str) -> None:
    """Add the checksum, validate and write the manifest last, atomically (write + fsync + rename)."""
    manifest = dict(manifest, checksum=manifest_checksum(manifest))
    validate_manifest(manifest, kind, Path(tmp_dir) / MANIFEST)
    with atomic_output(Path(tmp_dir) / MANIFEST, "w") as f:
        json.dump(manifest, f, indent=2, sort_keys=True)
        f.write("\n")


def commit_dir(tmp_dir: Path, out_dir: Path) -> None:
    """Move a finished tmp dir into place; the previous artifact survives until the new one is in place."""
    tmp_dir, out_dir = Path(tmp_dir), Path(out_dir)
    old = None
    if out_dir.exists():
        old = out_dir.parent / f"{OLD_PREFIX}{out_dir.name}-{os.getpid()}-{time.time_ns()}"
        os.replace(out_dir, old)
    os.replace(tmp_dir, out_dir)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def recover_dir(out_dir: Path) -> None:
    """Clean up leftovers of killed writes next to out_dir; restore a previous artifact if it was mid-swap."""
    out_dir = Path(out_dir)
    parent = out_dir.parent
    if not parent.is_dir():
        return
    for p in parent.glob(f"{TMP_PREFIX}{out_dir.name}-*"):
        shutil.rmtree(p, ignore_errors=True)
    olds = sorted(parent.glob(f"{OLD_PREFIX}{out_dir.name}-*"))
    if olds and not out_dir.exists():
        os.replace(olds[-1], out_dir)
        olds = olds[:-1]
    for p in olds:
        shutil.rmtree(p, ignore_errors=True)


def sweep_leftovers(artifacts_dir: Path) -> list[Path]:
    """Under the scene lock: clear what killed runs left anywhere under artifacts_dir (variants included) and return
    it: `.tmp-*` and `.old-*` siblings of artifacts (recover_dir: a previous artifact caught mid-swap is restored),
    and hidden `.*.part` files beside logs (kept as the log when the log itself is missing: the last attempt's)."""
    artifacts_dir = Path(artifacts_dir)
    found: list[Path] = []
    for p in sorted(artifacts_dir.rglob(f"{TMP_PREFIX}*")) + sorted(artifacts_dir.rglob(f"{OLD_PREFIX}*")):
        if p.is_dir() and p.parent.name != "logs":
            prefix = TMP_PREFIX if p.name.startswith(TMP_PREFIX) else OLD_PREFIX
            name = p.name[len(prefix):].rsplit("-", 2)[0]
            if p.exists():
                found.append(p)
                recover_dir(p.parent / name)
    for p in sorted(artifacts_dir.rglob("logs/.*.part")):
        found.append(p)
        log = p.with_name(p.name[1:].split(".log")[0] + ".log")
        if not log.exists() and p.name.startswith(f".{log.name}"):
            os.replace(p, log)
        else:
            p.unlink(missing_ok=True)
    return found
