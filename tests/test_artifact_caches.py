"""What a cached run does not redo: schema validation of an unedited manifest, re-hashing a file whose mtime changed."""

import json
import os
from pathlib import Path

import pytest

from panoworld.io import manifest as art
from tests.toy.common import use_toy_schemas


@pytest.fixture
def fresh_caches(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    use_toy_schemas(monkeypatch)
    monkeypatch.setattr(art, "_validated", None)
    monkeypatch.setattr(art, "_hashes", None)


def toy_artifact(root: Path, text: str = "hello") -> Path:
    d = root / "a"
    d.mkdir(parents=True)
    (d / "out.txt").write_text(text)
    files = art.list_files(d)
    art.write_manifest(d, {
        "schema": "toy", "schema_version": 1, "stage": "a", "stage_version": "1", "params": {}, "params_hash": "0" * 64,
        "inputs": {}, "key": "1" * 64, "files": files, "digest": art.files_digest(files), "started": "s", "finished": "f",
        "wall_s": 0.0, "peak_rss_mb": 1.0, "info": {},
    }, "toy")
    return d


def count_calls(monkeypatch, name: str) -> list:
    calls, f = [], getattr(art, name)
    monkeypatch.setattr(art, name, lambda *a, **k: calls.append(a) or f(*a, **k))
    return calls


def test_an_unedited_manifest_is_validated_once_per_schema(tmp_path, monkeypatch, fresh_caches):
    d = toy_artifact(tmp_path)  # write_manifest validated it
    art._validated = None  # a new process: the user cache remembers
    validations = count_calls(monkeypatch, "_validator")
    assert art.read_manifest(d, "toy")["stage"] == "a" and art.read_manifest(d)["stage"] == "a"
    assert validations == []
    # An edit that keeps the checksum right is validated (and refused) all the same.
    m = json.loads((d / art.MANIFEST).read_text())
    m["wall_s"] = "slow"
    m["checksum"] = art.manifest_checksum(m)
    (d / art.MANIFEST).write_text(json.dumps(m))
    with pytest.raises(art.ArtifactError, match="schema-invalid at wall_s"):
        art.read_manifest(d, "toy")
    # So is an edit without a new checksum, before the checksum is compared.
    m["wall_s"] = 1.0
    (d / art.MANIFEST).write_text(json.dumps(m))
    with pytest.raises(art.ArtifactError, match="checksum mismatch"):
        art.read_manifest(d, "toy")
    assert len(validations) == 2


def test_a_touched_file_is_rehashed_once_and_a_changed_one_is_caught(tmp_path, monkeypatch, fresh_caches):
    d = toy_artifact(tmp_path)
    manifest = art.read_manifest(d, "toy")
    st = (d / "out.txt").stat()
    os.utime(d / "out.txt", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # copied or touched: same content
    hashed = count_calls(monkeypatch, "file_digest")
    assert art.verify_files(d, manifest) is None and len(hashed) == 1
    art._hashes = None  # a new process
    assert art.verify_files(d, manifest) is None and len(hashed) == 1
    (d / "out.txt").write_text("jello")  # same size, new content and mtime
    assert "content differs" in art.verify_files(d, manifest) and len(hashed) == 2


def test_two_runs_remembering_at_once_keep_each_others_entries(tmp_path, monkeypatch, fresh_caches):
    a, b = toy_artifact(tmp_path / "one"), toy_artifact(tmp_path / "two", "other")
    art._validated = art._hashes = None
    checksum_b = json.loads((b / art.MANIFEST).read_text())["checksum"]
    disk = art._validated_checksums("toy")  # this process loaded the record, then another run added b's manifest
    assert checksum_b in disk
    art._validated = {k: [c for c in v if c != checksum_b] for k, v in art._validated.items()}
    art._remember_valid("toy", "f" * 64)
    art._validated = None  # a new process sees both
    assert {"f" * 64, checksum_b} <= set(art._validated_checksums("toy"))
    for d in (a, b):  # re-hashed files: each process's view merged into the record
        st = (d / "out.txt").stat()
        os.utime(d / "out.txt", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert art.verify_files(a, art.read_manifest(a, "toy")) is None
    art._hashes = {}  # another process, which read the record before the first one wrote it
    assert art.verify_files(b, art.read_manifest(b, "toy")) is None
    art._hashes = None
    hashed = count_calls(monkeypatch, "file_digest")
    assert art.verify_files(a, art.read_manifest(a, "toy")) is None and hashed == []


def test_validated_manifests_written_by_other_processes_are_kept(tmp_path, monkeypatch, fresh_caches):
    """Stages and runners of other scenes remember their manifests in the same user cache meanwhile: a process adding
    one keeps theirs (else the next no-op run validates its manifests again)."""
    from panoworld.io.user_cache import read_user_cache, write_user_cache

    art._validated = None
    toy_artifact(tmp_path)  # validated and remembered: this process's view of the record is loaded
    write_user_cache(art._VALIDATED_FILE, {art._schema_digest("toy"): ["theirs"], "another schema": ["x"]})
    toy_artifact(tmp_path / "b", "bye")  # validated and remembered by this process
    doc = read_user_cache(art._VALIDATED_FILE)
    assert doc["another schema"] == ["x"]
    assert doc[art._schema_digest("toy")][0] == "theirs" and len(doc[art._schema_digest("toy")]) == 3  # + a and b
