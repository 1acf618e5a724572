"""Weights specs to local files: `hf:ORG/NAME[@REVISION][/PATH]` from the local Hugging Face cache, or a local path."""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from panoworld.core.errors import WeightsError
from panoworld.io.manifest import file_digest, json_digest

HF_PREFIX = "hf:"
WEIGHTS_PARAMS = frozenset({"weights", "lora", "extra_weights", "upscale_weights", "prompt_embeds"})
"""Params that name weights in every stage (plus any `*_weights` field, or one with metadata {"weights": True})."""
_NAME = r"[A-Za-z0-9][\w.-]{0,95}"
_HF_ID = re.compile(rf"(?P<repo>{_NAME}/{_NAME})(?:@(?P<rev>[A-Za-z0-9][\w.-]{{0,127}}))?(?:/(?P<path>[\w.+-]+(?:/[\w.+-]+)*))?")


class WeightsNotFound(WeightsError):
    """A weights id that does not resolve locally; the message is one line naming the command that fetches it."""


def hub_cache_dir() -> Path:
    """The Hugging Face hub cache, from the environment at call time (HF_HUB_CACHE, else HF_HOME/hub)."""
    explicit = os.environ.get("HF_HUB_CACHE") or os.environ.get("HUGGINGFACE_HUB_CACHE")
    if explicit:
        return Path(explicit).expanduser()
    home = os.environ.get("HF_HOME") or os.path.join(os.environ.get("XDG_CACHE_HOME", "~/.cache"), "huggingface")
    return Path(os.path.expandvars(home)).expanduser() / "hub"


def weights_dir() -> Path:
    """Where files fetched from release URLs land by default: $PANOWORLD_WEIGHTS_DIR or ~/.cache/panoworld/weights."""
    explicit = os.environ.get("PANOWORLD_WEIGHTS_DIR")
    if explicit:
        return Path(explicit).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME", "~/.cache")).expanduser() / "panoworld" / "weights"


def hf_offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")


@dataclass(frozen=True)
class HfId:
    """A parsed `hf:ORG/NAME[@REVISION][/PATH]` id."""

    repo: str
    revision: str | None = None
    path: str | None = None
    """A file or folder inside the repo; None = the whole snapshot."""

    def __str__(self) -> str:
        return f"{HF_PREFIX}{self.repo}" + (f"@{self.revision}" if self.revision else "") + (f"/{self.path}" if self.path else "")


def parse_hf(spec: str) -> HfId | None:
    """Parse an `hf:` id; None when spec is not one. A malformed id is a WeightsNotFound naming the syntax.

    Strict grammar (_HF_ID): ORG and NAME as on the Hub; REVISION a branch, tag or commit without `/` or `..`; PATH
    relative `/`-separated segments, none empty, `.` or `..` (never absolute, never leaving the snapshot)."""
    if not spec.startswith(HF_PREFIX):
        return None
    m = _HF_ID.fullmatch(spec[len(HF_PREFIX):].strip())
    path = m and m["path"]
    if m is None or ".." in m["repo"] or ".." in (m["rev"] or "") or (path and {".", ".."} & set(path.split("/"))):
        raise WeightsNotFound(f"{spec}: expected hf:ORG/NAME[@REVISION][/PATH] (PATH relative, no '..'), "
                              "e.g. hf:depth-anything/Depth-Anything-V2-Small-hf")
    return HfId(m["repo"], m["rev"], path)


def fetch_command(hid: HfId) -> str:
    """The command that puts an id into the cache: by registry name where the repo has an entry."""
    from panoworld.framework.hub.registry import find_by_repo

    entry = find_by_repo(hid.repo)
    if entry is not None and (hid.revision in (None, entry.revision)):
        return f"python runner.py weights fetch {entry.name}"
    return f"python runner.py weights fetch {HF_PREFIX}{hid.repo}" + (f"@{hid.revision}" if hid.revision else "")


def _snapshot_by_prefix(storage: Path, prefix: str) -> Path | None:
    snaps = storage / "snapshots"
    if not re.fullmatch(r"[0-9a-f]{7,39}", prefix) or not snaps.is_dir():
        return None
    hits = [p for p in snaps.iterdir() if p.name.startswith(prefix)]
    return hits[0] if len(hits) == 1 else None


def resolve_hf(hid: HfId) -> tuple[Path, str]:
    """(local path, commit hash) of an id from the local cache only (never downloads)."""
    try:
        from huggingface_hub import snapshot_download, try_to_load_from_cache
        from huggingface_hub.errors import LocalEntryNotFoundError
    except ImportError as e:
        raise ImportError(f"hf: weights ids need huggingface_hub ({e}); pip install '.[models]'") from e
    cache = hub_cache_dir()
    try:
        snapshot = Path(snapshot_download(hid.repo, revision=hid.revision or "main", cache_dir=cache, local_files_only=True))
    except LocalEntryNotFoundError as e:
        # A snapshot holding part of the repo (a download with allow_patterns, e.g. Wan without its assets) is
        # "incomplete" to huggingface_hub; the backend checks the files it needs itself.
        partial = getattr(e, "snapshot_path", None)
        snapshot = Path(partial) if partial else _snapshot_by_prefix(cache / f"models--{hid.repo.replace('/', '--')}", hid.revision or "")
        if snapshot is None:
            raise WeightsNotFound(f"{hid}: not in the local Hugging Face cache {cache}; run `{fetch_command(hid)}`") from None
    commit = snapshot.name
    if hid.path is None:
        return snapshot, commit
    found = try_to_load_from_cache(hid.repo, hid.path, cache_dir=cache, revision=commit)
    if isinstance(found, str):
        return Path(found), commit
    if (snapshot / hid.path).is_dir():
        return snapshot / hid.path, commit
    raise WeightsNotFound(f"{hid}: no {hid.path} in the cached snapshot {commit[:12]} ({snapshot}); "
                          f"run `{fetch_command(HfId(hid.repo, hid.revision))}`")


# ---------------------------------------------------------------- digests


sha256_file = file_digest


def hf_blob_id(path: Path) -> str | None:
    """The blob name an HF cache snapshot file links to: the sha256 (LFS files) or git sha1 of its content."""
    if not path.is_symlink():
        return None
    target = Path(os.readlink(path))
    return target.name if target.parent.name == "blobs" else None


def _files_under(path: Path) -> list[tuple[str, Path]]:
    if path.is_file():
        return [(path.name, path)]
    out = []
    for p in sorted(path.rglob("*")):
        rel = p.relative_to(path)
        if any(part.startswith(".") for part in rel.parts) or not p.is_file():
            continue  # hidden bookkeeping such as a local_dir download's .cache/huggingface
        out.append((rel.as_posix(), p))
    return out


def file_records(path: Path, hint: dict | None = None) -> dict[str, dict]:
    """{relative path: {size, digest[, mtime_ns]}} of a weights file or folder.

    HF cache files take their digest from the blob they link to (no hashing); other files are hashed unless the
    hint (the same record from the last run) has the same size and mtime for them.
    """
    hint = hint or {}
    out, todo = {}, []
    for rel, p in _files_under(path):
        st = p.stat()
        blob = hf_blob_id(p)
        if blob is not None:
            out[rel] = {"size": st.st_size, "digest": blob}
            continue
        old = hint.get(rel) or {}
        out[rel] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns}
        if old.get("size") == st.st_size and old.get("mtime_ns") == st.st_mtime_ns and old.get("digest"):
            out[rel]["digest"] = old["digest"]
        else:
            todo.append((rel, p))
    if todo:
        from tqdm import tqdm

        total = sum(out[rel]["size"] for rel, _ in todo)
        with tqdm(total=total, unit="B", unit_scale=True, desc=f"hashing {path.name}", disable=total < (1 << 28) or None) as bar:
            for rel, p in todo:
                out[rel]["digest"] = sha256_file(p)
                bar.update(out[rel]["size"])
    return {rel: out[rel] for rel in sorted(out)}


def resolve_weights(spec: str, hint: dict | None = None) -> dict[str, Any]:
    """Resolve one weights value to a manifest record: spec, local path, (repo, revision, commit), file digests, and
    `digest` (what the cache key holds): the file digests, with the commit for `hf:` ids.

    A local path that does not exist resolves to itself with `missing: true` (the stage then says what it expects);
    an `hf:` id that is not cached raises WeightsNotFound naming the fetch command.
    """
    hint_files = (hint or {}).get("files") if hint and hint.get("spec") == spec else None
    hid = parse_hf(spec)
    if hid is not None:
        path, commit = resolve_hf(hid)
        rec: dict[str, Any] = {"spec": spec, "path": str(path), "repo": hid.repo, "revision": hid.revision or "main",
                               "commit": commit}
    else:
        path = Path(spec).expanduser()
        rec = {"spec": spec, "path": str(path.resolve()) if path.exists() else spec}
        if not path.exists():
            return {**rec, "missing": True, "files": {}, "digest": None}
    files = file_records(path, hint_files)
    content = sorted((k, v["digest"]) for k, v in files.items())
    return {**rec, "files": files, "digest": json_digest({"commit": rec["commit"], "files": content} if hid else content)}


def is_weights_field(f: dataclasses.Field) -> bool:
    return f.name in WEIGHTS_PARAMS or f.name.endswith("_weights") or bool(f.metadata.get("weights"))


def weights_fields(params_cls: type) -> list[str]:
    """Names of the weights-like params of a params dataclass (nested backend options as `wan.weights`)."""
    out = []
    for f in dataclasses.fields(params_cls):
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(sub):
            out += [f"{f.name}.{n}" for n in weights_fields(type(sub))]
        elif is_weights_field(f):
            out.append(f.name)
    return out


def _get(params: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        params = getattr(params, part)
    return params


def _set_weights(params: Any) -> list[tuple[str, str]]:
    values = ((n, _get(params, n)) for n in weights_fields(type(params)))
    return [(n, str(v)) for n, v in values if isinstance(v, (str, os.PathLike)) and str(v) != ""]


def resolve_params_weights(params: Any, hints: dict | None = None, *, where: str = "") -> dict[str, dict]:
    """{param: record} for every weights-like param that is set; hints = the `weights` of the last manifest.

    WeightsNotFound names the param as `{where}{param}` (e.g. where='depth.')."""
    hints = hints or {}
    out = {}
    for name, value in _set_weights(params):
        try:
            out[name] = resolve_weights(value, hints.get(name))
        except WeightsNotFound as e:
            raise WeightsNotFound(f"{where}{name} {e}") from None
    return out


def check_params_weights(params: Any, *, where: str = "") -> None:
    """Raise WeightsNotFound if an `hf:` id among the params is not in the local cache (hashes nothing)."""
    for name, value in _set_weights(params):
        hid = parse_hf(value) if isinstance(value, str) else None
        if hid is not None:
            try:
                resolve_hf(hid)
            except WeightsNotFound as e:
                raise WeightsNotFound(f"{where}{name} {e}") from None


def with_resolved_paths(params: Any, records: dict[str, dict]) -> Any:
    """A copy of params whose weights-like values are the resolved local paths."""
    for name, r in records.items():
        head, _, rest = name.partition(".")
        value = with_resolved_paths(getattr(params, head), {rest: r}) if rest else r["path"]
        params = dataclasses.replace(params, **{head: value})
    return params


def weights_key(records: dict[str, dict]) -> dict[str, str | None]:
    """What enters the cache key: each weights param's content digest."""
    return {k: r["digest"] for k, r in sorted(records.items())}


def describe_change(stage: str, old: dict[str, dict], new: dict[str, dict]) -> str | None:
    """`weights changed: depth.depth_anything.weights hf:ORG/NAME commit 1a2b3c4 -> 5d6e7f8 (model.safetensors)`, or None."""
    parts = []
    for name in sorted(set(old) | set(new)):
        a, b = old.get(name) or {}, new.get(name) or {}
        if a.get("digest") == b.get("digest"):
            continue
        what = f"{stage}.{name} {b.get('spec') or a.get('spec')}"
        if a.get("commit") and b.get("commit") and a["commit"] != b["commit"]:
            what += f" commit {a['commit'][:7]} -> {b['commit'][:7]}"
        fa, fb = a.get("files") or {}, b.get("files") or {}
        changed = sorted(k for k in set(fa) | set(fb) if (fa.get(k) or {}).get("digest") != (fb.get(k) or {}).get("digest"))
        if b.get("missing"):
            changed = ["now missing"]
        if changed:
            what += f" ({', '.join(changed[:4])}{', ...' if len(changed) > 4 else ''})"
        parts.append(what)
    return "weights changed: " + "; ".join(parts) if parts else None


def find_local_weights(param: str) -> tuple[Any, Path, str] | None:
    """(registry entry, local path, commit) of the first registered weights for `param` (e.g.
    `depth.depth_anything.weights`, in registry order: the smallest first) whose files are in the local Hugging Face
    cache; None when there are none (or huggingface_hub is not installed)."""
    from panoworld.framework.hub.registry import REGISTRY

    for entry in REGISTRY.values():
        if entry.kind != "hf" or not any(u.param == param for u in entry.uses):
            continue
        try:
            path, commit = resolve_hf(HfId(entry.repo, entry.revision))
        except (WeightsNotFound, ImportError):
            continue
        if all((path / f.path).is_file() for f in entry.files):
            return entry, path, commit
    return None
