"""Fetching weights: Hugging Face snapshots into the standard cache (or a folder), release URLs, verified and atomic."""

from __future__ import annotations

import hashlib
import re
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

from panoworld.core.errors import PanoWorldError
from panoworld.framework.hub.registry import REGISTRY, WeightsEntry
from panoworld.framework.hub.resolve import (
    HfId,
    WeightsNotFound,
    hf_blob_id,
    hf_offline,
    hub_cache_dir,
    parse_hf,
    resolve_hf,
    sha256_file,
    weights_dir,
)
from panoworld.io.safe_write import atomic_output, check_output_dir, check_output_file


class FetchError(PanoWorldError, RuntimeError):
    """A download that failed or did not verify; one line naming the file and what to do."""


@dataclass
class Fetched:
    entry: WeightsEntry
    location: Path
    """The snapshot / --to folder (hub entries) or the folder holding the files (URL entries)."""
    commit: str | None = None
    files: dict[str, Path] = field(default_factory=dict)
    """Local path of each registry file."""
    notes: list[str] = field(default_factory=list)


def check_content(n_bytes: int, sha256: str, size: int | None, expected_sha256: str | None) -> str | None:
    """What is wrong with content of n_bytes and digest sha256 given the published size / sha256 (or its prefix)."""
    if size is not None and n_bytes != size:
        return f"size {n_bytes} bytes but expected {size}"
    if expected_sha256 and not sha256.startswith(expected_sha256.lower()):
        return f"sha256 {sha256[:16]}... does not match the published {expected_sha256[:16]}"
    return None


def verify_file(path: Path, size: int | None, sha256: str | None) -> str | None:
    if not path.is_file():
        return "missing"
    if size is not None and path.stat().st_size != size:
        return f"size {path.stat().st_size} bytes but expected {size}"
    return check_content(path.stat().st_size, sha256_file(path), None, sha256) if sha256 else None


def download_url(url: str, dest: Path, *, size: int | None = None, sha256: str | None = None, timeout: float = 60.0) -> bool:
    """Download url to dest through a temporary sibling, verified before an atomic rename; True if downloaded,
    False if dest was already there and verifies. A failed or corrupted download leaves dest as it was."""
    from tqdm import tqdm

    dest = Path(dest)
    if dest.is_file() and verify_file(dest, size, sha256) is None:
        return False
    if hf_offline():
        raise FetchError(f"{dest.name}: HF_HUB_OFFLINE is set, not downloading {url}; unset it or put the file at {dest}")
    check_output_file(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    try:
        req = urllib.request.Request(url, headers={"User-Agent": "panoworld-weights"})
        h, n = hashlib.sha256(), 0
        with urllib.request.urlopen(req, timeout=timeout) as r, atomic_output(dest) as f:
            total = int(r.headers.get("Content-Length") or 0) or size
            with tqdm(total=total, unit="B", unit_scale=True, desc=dest.name, disable=None) as bar:
                while chunk := r.read(1 << 20):
                    f.write(chunk)
                    h.update(chunk)
                    n += len(chunk)
                    bar.update(len(chunk))
            if total and n != total:
                raise FetchError(f"{url}: truncated download ({n} of {total} bytes); {dest} left unchanged, run fetch again")
            problem = check_content(n, h.hexdigest(), size, sha256)
            if problem:
                raise FetchError(f"{url}: {problem}; the download was discarded and {dest} left unchanged")
    except (urllib.error.URLError, OSError, ValueError) as e:
        raise FetchError(f"{url}: download failed ({e}); check the network, or download it by hand to {dest}") from None
    return True


def _git_blob_sha1(path: Path) -> str:
    h = hashlib.sha1()
    h.update(f"blob {path.stat().st_size}\0".encode())
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            h.update(block)
    return h.hexdigest()


def etag_problem(path: Path, etag: str) -> str | None:
    """Check a hub file against its etag: the sha256 of LFS files, the git blob sha1 of the others."""
    if re.fullmatch(r"[0-9a-f]{64}", etag):
        got = sha256_file(path)
    elif re.fullmatch(r"[0-9a-f]{40}", etag):
        got = _git_blob_sha1(path)
    else:
        return None  # an etag we cannot check (e.g. a xet hash)
    return None if got == etag else f"content hash {got[:12]}... does not match {etag[:12]}..."


def _local_dir_etag(root: Path, rel: str) -> str | None:
    """The etag huggingface_hub recorded for a `local_dir` download (.cache/huggingface/download/REL.metadata)."""
    meta = root / ".cache" / "huggingface" / "download" / f"{rel}.metadata"
    try:
        lines = meta.read_text().splitlines()
    except OSError:
        return None
    return lines[1].strip() if len(lines) > 1 else None


def verify_hub_files(root: Path, rels: list[str]) -> list[str]:
    """Verify the given files of a snapshot (cache symlinks) or local_dir download against their etags; a file that
    fails is deleted (with its blob) so it can never be loaded, and listed in the returned problems."""
    from tqdm import tqdm

    problems = []
    present = [rel for rel in rels if (root / rel).is_file()]
    total = sum((root / rel).stat().st_size for rel in present)
    bar = tqdm(total=total, unit="B", unit_scale=True, desc="verifying", disable=total < (1 << 28) or None)
    for rel in present:
        p = root / rel
        blob = hf_blob_id(p)
        etag = blob or _local_dir_etag(root, rel)
        problem = etag_problem(p, etag) if etag else None
        bar.update(p.stat().st_size)
        if problem:
            target = p.resolve()
            p.unlink()
            if blob:
                target.unlink(missing_ok=True)
            problems.append(f"{rel}: {problem}")
    bar.close()
    return problems


def _snapshot_files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*")
                  if p.is_file() and not any(s.startswith(".") for s in p.relative_to(root).parts))


def fetch_hf(hid: HfId, *, to: Path | None = None, patterns: tuple[str, ...] = (), required: tuple[str, ...] = ()) -> tuple[Path, str | None]:
    """snapshot_download an id into the standard cache (or the folder `to`), then verify every file it holds against
    its etag and check the required files are present. Offline (HF_HUB_OFFLINE) it only checks the cache."""
    try:
        from huggingface_hub import snapshot_download
    except ImportError as e:
        raise ImportError(f"fetching from the hub needs huggingface_hub ({e}); pip install '.[models]'") from e
    offline = hf_offline()
    if offline and to is None:
        try:
            root, commit = resolve_hf(HfId(hid.repo, hid.revision))
        except WeightsNotFound:
            raise FetchError(f"{hid}: HF_HUB_OFFLINE is set and it is not in {hub_cache_dir()}; unset HF_HUB_OFFLINE "
                             "to download it") from None
    else:
        try:
            root = Path(snapshot_download(
                hid.repo, revision=hid.revision or "main", cache_dir=hub_cache_dir(), local_dir=to,
                allow_patterns=list(patterns) or None, local_files_only=offline,
            ))
        except Exception as e:  # network, auth and not-found errors all get one actionable line
            msg = " ".join(str(e).split())[:300]
            raise FetchError(f"{hid}: download failed ({type(e).__name__}: {msg})") from None
        commit = root.name if to is None else None
    problems = verify_hub_files(root, _snapshot_files(root))
    if problems:
        raise FetchError(f"{hid}: {'; '.join(problems)}; the bad files were removed, run fetch again")
    missing = [r for r in required if not (root / r).exists()]
    if missing:
        raise FetchError(f"{hid}: {root} lacks {', '.join(missing)} after the download; run fetch again")
    return root, commit


def fetch_entry(entry: WeightsEntry, *, to: Path | None = None) -> Fetched:
    """Fetch one registry entry (hub snapshot or release URLs) and return where its files are."""
    if to is not None:
        check_output_dir(to)
    if entry.trained:
        raise FetchError(f"{entry.name}: not downloadable, these weights are trained by this project: {entry.trained}")
    if entry.repo:
        hid = HfId(entry.repo, entry.revision if entry.revision != "main" else None)
        root, commit = fetch_hf(hid, to=to, patterns=entry.patterns, required=tuple(f.path for f in entry.files))
        for f in entry.files:
            problem = verify_file(root / f.path, f.size, f.sha256) if (f.size or f.sha256) else None
            if problem:
                raise FetchError(f"{entry.name}: {root / f.path}: {problem}")
        return Fetched(entry, root, commit, {f.path: root / f.path for f in entry.files})
    dest_dir = Path(to) if to is not None else weights_dir()
    out = Fetched(entry, dest_dir)
    for f in entry.files:
        dest = dest_dir / f.path
        fresh = download_url(f.url, dest, size=f.size, sha256=f.sha256)
        out.notes.append(f"{dest}: {'downloaded and verified' if fresh else 'already present'}")
        out.files[f.path] = dest
    return out


def fetch(name: str, *, to: Path | None = None) -> Fetched:
    """Fetch a registry name or a raw `hf:ORG/NAME[@REVISION]` id."""
    hid = parse_hf(name)
    if hid is not None:
        if hid.path:
            raise FetchError(f"{name}: fetch a whole repo (hf:ORG/NAME[@REVISION]); reference files in it with /PATH")
        entry = WeightsEntry(name=str(hid), model=hid.repo, licence="see the model card", size="?", uses=(),
                             repo=hid.repo, revision=hid.revision or "main")
        return fetch_entry(entry, to=to)
    if name not in REGISTRY:
        raise FetchError(f"{name}: unknown weights; known: {', '.join(REGISTRY)} (or hf:ORG/NAME)")
    return fetch_entry(REGISTRY[name], to=to)
