"""Weights by name: offline `hf:` resolution from a test-built Hugging Face cache, cache keys, fetch verification."""

from __future__ import annotations

import hashlib
import http.server
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from panoworld.framework import pipeline as pl
from panoworld.framework.hub import cli, registry
from panoworld.framework.hub import fetch as hf_fetch
from panoworld.framework.hub.resolve import HfId, WeightsNotFound, describe_change, parse_hf, resolve_weights

REPO = Path(__file__).resolve().parent.parent
TINY = "test-org/tiny-depth-anything"
C1, C2 = "1" * 40, "2" * 40


def put_snapshot(cache: Path, repo: str, files: dict[str, bytes], commit: str, *, ref: str | None = "main",
                 corrupt: str | None = None) -> Path:
    """Lay files out as huggingface_hub does: blobs named by their sha256, snapshot symlinks, refs/<ref> = commit."""
    storage = cache / f"models--{repo.replace('/', '--')}"
    snap = storage / "snapshots" / commit
    for rel, data in files.items():
        blob = storage / "blobs" / hashlib.sha256(data).hexdigest()
        blob.parent.mkdir(parents=True, exist_ok=True)
        blob.write_bytes(data + b"corrupted" if rel == corrupt else data)
        link = snap / rel
        link.parent.mkdir(parents=True, exist_ok=True)
        link.unlink(missing_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    if ref:
        (storage / "refs").mkdir(parents=True, exist_ok=True)
        (storage / "refs" / ref).write_text(commit)
    return snap


@pytest.fixture
def hub_env(tmp_path, monkeypatch):
    cache = tmp_path / "hf" / "hub"
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setenv("PANOWORLD_WEIGHTS_DIR", str(tmp_path / "weights"))
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    return cache


@pytest.fixture(scope="module")
def tiny_files(tmp_path_factory) -> tuple[dict[str, bytes], dict[str, bytes]]:
    """Two versions of a tiny Depth Anything checkpoint saved with save_pretrained (v2: other head weights)."""
    from safetensors.torch import load_file, save_file

    from tests.test_depth import tiny_depth_anything

    root = tiny_depth_anything(tmp_path_factory.mktemp("tiny") / "w")
    (root / "preprocessor_config.json").write_text(json.dumps({"image_mean": [0.485, 0.456, 0.406],
                                                                "image_std": [0.229, 0.224, 0.225]}))
    v1 = {p.name: p.read_bytes() for p in sorted(root.iterdir()) if p.is_file()}
    state = load_file(str(root / "model.safetensors"))
    state["head.conv3.bias"] = state["head.conv3.bias"] + 0.5
    save_file(state, str(root / "model.safetensors"), metadata={"format": "pt"})
    v2 = {**v1, "model.safetensors": (root / "model.safetensors").read_bytes()}
    assert v2["model.safetensors"] != v1["model.safetensors"]
    return v1, v2


# ---------------------------------------------------------------- resolution


def test_parse_hf_ids():
    assert parse_hf("/some/local/dir") is None
    assert parse_hf("hf:org/name") == HfId("org/name")
    assert parse_hf("hf:org/name@v1.0") == HfId("org/name", "v1.0")
    assert parse_hf("hf:org/name@abc1234/sub/file.pth") == HfId("org/name", "abc1234", "sub/file.pth")
    assert str(parse_hf("hf:org/name@abc1234/sub/file.pth")) == "hf:org/name@abc1234/sub/file.pth"
    for bad in ("hf:name-only", "hf:org/na me", "hf:org/name@", "hf:org/name/../x", "hf:a/b@..", "hf:org/name//abs",
                "hf:/etc/passwd", "hf:org/name/./x", "hf:org/name@a/../../x", "hf:org/name/sub/", "hf:org/n\\x"):
        with pytest.raises(WeightsNotFound, match=r"expected hf:ORG/NAME\[@REVISION\]\[/PATH\]"):
            parse_hf(bad)


def test_id_resolves_offline_to_cached_files(hub_env, tiny_files, monkeypatch):
    v1, _ = tiny_files
    snap = put_snapshot(hub_env, TINY, v1, C1)
    rec = resolve_weights(f"hf:{TINY}")
    assert Path(rec["path"]) == snap and rec["commit"] == C1 and rec["revision"] == "main"
    assert set(rec["files"]) == set(v1)
    for rel, data in v1.items():  # digests are the content sha256, read from the blob names without hashing
        assert rec["files"][rel] == {"size": len(data), "digest": hashlib.sha256(data).hexdigest()}
    assert resolve_weights(f"hf:{TINY}@{C1}")["digest"] == rec["digest"]
    assert resolve_weights(f"hf:{TINY}@{C1[:8]}")["commit"] == C1  # a short commit hash
    one = resolve_weights(f"hf:{TINY}/config.json")
    assert Path(one["path"]) == snap / "config.json" and list(one["files"]) == ["config.json"]
    # a new commit with the same files: recorded, keyed, and named as the reason
    put_snapshot(hub_env, TINY, v1, C2)
    rec2 = resolve_weights(f"hf:{TINY}")
    assert rec2["commit"] == C2 and rec2["files"] == rec["files"] and rec2["digest"] != rec["digest"]
    assert describe_change("depth", {"depth_anything.weights": rec}, {"depth_anything.weights": rec2}) == \
        f"weights changed: depth.depth_anything.weights hf:{TINY} commit {C1[:7]} -> {C2[:7]}"
    assert describe_change("depth", {"weights": rec}, {"weights": rec}) is None
    # HF_HOME is respected when HF_HUB_CACHE is unset
    monkeypatch.delenv("HF_HUB_CACHE")
    monkeypatch.setenv("HF_HOME", str(hub_env.parent))
    assert resolve_weights(f"hf:{TINY}")["commit"] == C2
    # the model loads from the resolved snapshot
    from panoworld.models.depth_anything import DepthAnything

    assert DepthAnything.from_pretrained(rec["path"], input_size=56).model.config.backbone_config.hidden_size == 32


def test_partial_snapshot_resolves(hub_env, tiny_files):
    """A download with allow_patterns leaves a snapshot huggingface_hub calls incomplete (its cached tree listing
    names more files); it still resolves, to the files that are there."""
    tree_cache = pytest.importorskip("huggingface_hub._tree_cache")
    v1, _ = tiny_files
    snap = put_snapshot(hub_env, TINY, v1, C1)
    listing = {rel: tree_cache.TreeCacheEntry(size=len(d), blob_id="0" * 40) for rel, d in v1.items()}
    listing["assets/teaser.gif"] = tree_cache.TreeCacheEntry(size=10, blob_id="0" * 40)
    tree_cache.write_tree_cache(str(hub_env / f"models--{TINY.replace('/', '--')}"), C1, listing)
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import IncompleteSnapshotError

    with pytest.raises(IncompleteSnapshotError):  # what huggingface_hub itself says of it
        snapshot_download(TINY, cache_dir=hub_env, local_files_only=True)
    rec = resolve_weights(f"hf:{TINY}")
    assert Path(rec["path"]) == snap and set(rec["files"]) == set(v1) and rec["commit"] == C1


def test_missing_id_is_one_line_naming_weights_fetch(hub_env, tiny_files):
    with pytest.raises(WeightsNotFound) as e:
        resolve_weights("hf:nobody/nothing")
    assert "run `python runner.py weights fetch hf:nobody/nothing`" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(WeightsNotFound, match=r"weights fetch depth-anything-v2-small`"):
        resolve_weights("hf:depth-anything/Depth-Anything-V2-Small-hf")
    put_snapshot(hub_env, TINY, tiny_files[0], C1)
    with pytest.raises(WeightsNotFound, match=rf"no missing.bin in the cached snapshot .*weights fetch hf:{TINY}`"):
        resolve_weights(f"hf:{TINY}/missing.bin")
    with pytest.raises(WeightsNotFound, match="not in the local Hugging Face cache"):
        resolve_weights(f"hf:{TINY}@v9")


def test_local_weights_are_hashed_once_per_change(tmp_path, monkeypatch):
    from panoworld.framework.hub import resolve as res

    d = tmp_path / "w"
    d.mkdir()
    (d / "model.bin").write_bytes(b"a" * 100)
    (d / ".cache").mkdir()
    (d / ".cache" / "meta").write_text("ignored")
    rec = resolve_weights(str(d))
    assert list(rec["files"]) == ["model.bin"] and rec["files"]["model.bin"]["digest"] == hashlib.sha256(b"a" * 100).hexdigest()
    calls = []
    real = res.sha256_file
    monkeypatch.setattr(res, "sha256_file", lambda p: calls.append(p) or real(p))
    assert resolve_weights(str(d), hint=rec)["digest"] == rec["digest"] and calls == []  # same stat: no re-hash
    (d / "model.bin").write_bytes(b"b" * 100)
    os.utime(d / "model.bin", ns=(1, 1))
    changed = resolve_weights(str(d), hint=rec)
    assert len(calls) == 1 and changed["digest"] != rec["digest"]
    assert resolve_weights(str(tmp_path / "absent"))["missing"] is True


# ---------------------------------------------------------------- the depth stage from an id


def _scene(tmp_path) -> Path:
    from tests.test_mesh import BoxRoom

    rgb, _ = BoxRoom().render(np.eye(4), 64, 128)
    scene = tmp_path / "scene"
    scene.mkdir()
    Image.fromarray(rgb).save(scene / "panorama.png")
    return scene


DEPTH_SETS = [f"depth.depth_anything.weights=hf:{TINY}", "depth.backend=depth-anything", "depth.depth_anything.view_size=56", "depth.rescale=never"]


@pytest.mark.slow
def test_depth_stage_runs_from_id_and_reruns_when_snapshot_changes(hub_env, tiny_files, tmp_path):
    v1, v2 = tiny_files
    put_snapshot(hub_env, TINY, v1, C1)
    scene = _scene(tmp_path)

    def run():
        return {r.stage: r for r in pl.run(scene, only=["depth"], sets=DEPTH_SETS).results}["depth"]

    first = run()
    assert first.action == "ran", first.reason
    manifest = json.loads((scene / "artifacts" / "depth" / "manifest.json").read_text())
    rec = manifest["weights"]["depth_anything.weights"]
    assert manifest["params"]["depth_anything"]["weights"] == f"hf:{TINY}"  # the id is the param; its resolution is recorded apart
    assert rec["commit"] == C1 and rec["files"]["model.safetensors"]["digest"] == hashlib.sha256(v1["model.safetensors"]).hexdigest()
    assert manifest["info"]["backend"] == "depth-anything"
    assert run().action == "cached"

    put_snapshot(hub_env, TINY, v2, C2)  # a new revision lands in the cache: refs/main -> C2
    row = {r["stage"]: r for r in pl.status(scene, sets=DEPTH_SETS)}["depth"]
    assert row["state"] == "stale"
    assert row["reason"] == f"weights changed: depth.depth_anything.weights hf:{TINY} commit {C1[:7]} -> {C2[:7]} (model.safetensors)"
    again = run()
    assert again.action == "ran" and again.reason == row["reason"]
    assert json.loads((scene / "artifacts" / "depth" / "manifest.json").read_text())["weights"]["depth_anything.weights"]["commit"] == C2
    pinned = [s.replace(f"hf:{TINY}", f"hf:{TINY}@{C2}") for s in DEPTH_SETS]  # the same files pinned: params changed
    assert {r["stage"]: r for r in pl.status(scene, sets=pinned)}["depth"]["reason"].startswith("params changed: depth.depth_anything.weights")
    (hub_env / f"models--{TINY.replace('/', '--')}" / "refs" / "main").unlink()  # the id no longer resolves
    reason = {r["stage"]: r for r in pl.status(scene, sets=DEPTH_SETS)}["depth"]["reason"]
    assert reason.startswith(f"weights missing: depth.depth_anything.weights hf:{TINY}: not in the local Hugging Face cache")


def test_runner_with_a_missing_id_fails_in_one_line_and_writes_nothing(hub_env, tmp_path, capsys):
    scene = tmp_path / "scene"
    scene.mkdir()
    Image.fromarray(np.zeros((16, 32, 3), np.uint8)).save(scene / "panorama.png")
    proc = subprocess.run(
        [sys.executable, str(REPO / "runner.py"), "run", str(scene), "--set", "depth.depth_anything.weights=hf:depth-anything/Depth-Anything-V2-Small-hf"],
        capture_output=True, text=True, cwd=REPO, env=dict(os.environ),
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "depth.depth_anything.weights hf:depth-anything/Depth-Anything-V2-Small-hf" in lines[0]
    assert "run `python runner.py weights fetch depth-anything-v2-small`" in lines[0]
    assert not (scene / "artifacts").exists()
    # a stage run alone says the same (exit 2) and writes nothing
    from stages import depth

    assert depth.main(["--panorama", str(scene / "panorama.png"), "--out", str(tmp_path / "alone"),
                       "--weights", "hf:nobody/nothing"]) == 2
    assert "depth.depth_anything.weights hf:nobody/nothing: not in the local Hugging Face cache" in capsys.readouterr().err
    assert not (tmp_path / "alone").exists()


# ---------------------------------------------------------------- fetching


class _Server:
    """A local HTTP server over a folder (the release-URL transport without a network)."""

    def __init__(self, root: Path):
        handler = lambda *a, **kw: http.server.SimpleHTTPRequestHandler(*a, directory=str(root), **kw)
        http.server.SimpleHTTPRequestHandler.log_message = lambda *a: None
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def __enter__(self):
        self.thread.start()
        return f"http://127.0.0.1:{self.httpd.server_address[1]}"

    def __exit__(self, *exc):
        self.httpd.shutdown()
        self.httpd.server_close()


def test_url_fetch_verifies_and_is_atomic(tmp_path, hub_env):
    served = tmp_path / "served"
    served.mkdir()
    good = b"real weights" * 1000
    (served / "model.pth").write_bytes(good)
    sha = hashlib.sha256(good).hexdigest()
    dest = tmp_path / "out" / "model.pth"
    with _Server(served) as base:
        url = f"{base}/model.pth"
        assert hf_fetch.download_url(url, dest, size=len(good), sha256=sha) is True
        assert dest.read_bytes() == good
        assert hf_fetch.download_url(url, dest, size=len(good), sha256=sha[:8]) is False  # present, prefix verifies
        (served / "model.pth").write_bytes(good[:-3] + b"bad")  # same size, other content
        dest.unlink()
        with pytest.raises(hf_fetch.FetchError, match=r"sha256 .* does not match the published .* left unchanged"):
            hf_fetch.download_url(url, dest, size=len(good), sha256=sha)
        assert not dest.exists()
        dest.write_bytes(b"old file the user had")  # a failing download never replaces what is there
        with pytest.raises(hf_fetch.FetchError, match="size"):
            hf_fetch.download_url(url, dest, size=len(good) + 1)
        assert dest.read_bytes() == b"old file the user had"
        assert hf_fetch.download_url(url, dest) is False  # nothing published to check against: kept as it is
        with pytest.raises(hf_fetch.FetchError, match="404.*download failed|download failed.*404"):
            hf_fetch.download_url(f"{base}/absent.pth", dest.with_name("absent.pth"))
    assert sorted(p.name for p in dest.parent.iterdir()) == ["model.pth"]  # no partial files left behind


def test_registry_url_entry_fetch_prints_set_lines(tmp_path, hub_env, monkeypatch, capsys):
    served = tmp_path / "served"
    served.mkdir()
    (served / "x2.pth").write_bytes(b"esrgan")
    with _Server(served) as base:
        entry = registry.WeightsEntry(
            name="test-upscaler", model="test", licence="MIT", size="6 B",
            files=(registry.WeightsFile("x2.pth", url=f"{base}/x2.pth", size=6, sha256=hashlib.sha256(b"esrgan").hexdigest()),),
            uses=(registry.Use("video.upscale_weights", also=("video.upscale=realesrgan",)),),
        )
        monkeypatch.setitem(registry.REGISTRY, entry.name, entry)
        assert cli.main(["fetch", "test-upscaler"]) == 0
    out = capsys.readouterr().out
    dest = Path(os.environ["PANOWORLD_WEIGHTS_DIR"]) / "x2.pth"
    assert dest.read_bytes() == b"esrgan"
    assert f"--set video.upscale=realesrgan --set video.upscale_weights={dest}" in out
    assert f"video: {{upscale: realesrgan, upscale_weights: {dest}}}" in out


def _fake_snapshot_download(cache: Path, files: dict[str, bytes], commit: str, corrupt: str | None = None):
    """huggingface_hub.snapshot_download with the network replaced by writing `files` (offline look-ups stay real)."""
    import huggingface_hub

    real = huggingface_hub.snapshot_download

    def fake(repo_id, *, revision=None, cache_dir=None, local_dir=None, allow_patterns=None, local_files_only=False, **kw):
        if local_files_only:
            return real(repo_id, revision=revision, cache_dir=cache_dir, local_dir=local_dir, local_files_only=True)
        assert Path(cache_dir) == cache
        if local_dir is not None:  # a --to download: plain files plus huggingface_hub's etag metadata
            for rel, data in files.items():
                (Path(local_dir) / rel).write_bytes(data + (b"x" if rel == corrupt else b""))
                meta = Path(local_dir) / ".cache" / "huggingface" / "download" / f"{rel}.metadata"
                meta.parent.mkdir(parents=True, exist_ok=True)
                meta.write_text(f"{commit}\n{hashlib.sha256(data).hexdigest()}\n0\n")
            return str(local_dir)
        return str(put_snapshot(cache, repo_id, files, commit, corrupt=corrupt))

    return fake


def test_hub_fetch_verifies_blobs_and_prints_the_id(hub_env, tiny_files, monkeypatch, capsys, tmp_path):
    import huggingface_hub

    v1, _ = tiny_files
    repo = "depth-anything/Depth-Anything-V2-Small-hf"
    monkeypatch.setattr(huggingface_hub, "snapshot_download", _fake_snapshot_download(hub_env, v1, C1, corrupt="model.safetensors"))
    assert cli.main(["fetch", "depth-anything-v2-small"]) == 1
    assert "model.safetensors: content hash" in capsys.readouterr().err
    snap = hub_env / f"models--{repo.replace('/', '--')}" / "snapshots" / C1
    assert not (snap / "model.safetensors").exists()  # the corrupted file can never be loaded
    status = cli.entry_status(registry.REGISTRY["depth-anything-v2-small"])
    assert status["state"] == "incomplete" and "model.safetensors" in status["detail"]

    monkeypatch.setattr(huggingface_hub, "snapshot_download", _fake_snapshot_download(hub_env, v1, C1))
    assert cli.main(["fetch", "depth-anything-v2-small"]) == 0
    out = capsys.readouterr().out
    assert f"commit {C1[:12]}" in out
    assert f"--set depth.backend=depth-anything --set depth.depth_anything.weights=hf:{repo}" in out
    assert f"depth: {{backend: depth-anything, depth_anything.weights: hf:{repo}}}" in out
    assert resolve_weights(f"hf:{repo}")["commit"] == C1

    to = tmp_path / "da-small"
    to.mkdir()
    assert cli.main(["fetch", "depth-anything-v2-small", "--to", str(to)]) == 0
    assert f"--set depth.depth_anything.weights={to}" in capsys.readouterr().out
    monkeypatch.setattr(huggingface_hub, "snapshot_download", _fake_snapshot_download(hub_env, v1, C1, corrupt="config.json"))
    assert cli.main(["fetch", "depth-anything-v2-small", "--to", str(to)]) == 1
    assert "config.json: content hash" in capsys.readouterr().err and not (to / "config.json").exists()


def test_weights_list(hub_env, tiny_files, capsys):
    put_snapshot(hub_env, "depth-anything/Depth-Anything-V2-Small-hf", tiny_files[0], C1)
    assert cli.main(["list", "--json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)["weights"]}
    for name in ("depth-anything-v2-small", "depth-anything-v2-base", "depth-anything-v2-large", "wan2.2-ti2v-5b",
                 "realesrgan-x2plus", "lpips-alex", "lpips-vgg", "panovggt", "gs-decoder"):
        assert name in rows
    small = rows["depth-anything-v2-small"]
    assert small["status"]["state"] == "present" and small["status"]["commit"] == C1 and small["status"]["on_disk"] > 0
    assert small["params"] == ["depth.depth_anything.weights"] and small["licence"] == "Apache-2.0"
    assert rows["depth-anything-v2-base"]["status"]["state"] == "missing"
    assert rows["wan2.2-ti2v-5b"]["repo"] == "Wan-AI/Wan2.2-TI2V-5B-Diffusers"
    assert rows["realesrgan-x2plus"]["files"][0]["url"].startswith("https://github.com/xinntao/Real-ESRGAN/releases/")
    assert rows["panovggt"]["status"]["state"] == "trained" and "train recon" in rows["panovggt"]["trained_by"]
    with pytest.raises(ValueError, match="already registered"):
        registry.register(registry.WeightsEntry(name="panovggt", model="x", licence="x", size="x", uses=()))


def test_a_home_without_depths_is_refused_naming_where_its_depth_goes(hub_env, tmp_path):
    """A home (panoramas/, no depths/) with no depth model on disk: one line naming the home's depth file for the
    panorama (SCENE/depths/NAME.npy|exr|png), not a file beside the panorama; exit 2, no artifact."""
    from tests.test_mesh import BoxRoom

    rgb, _ = BoxRoom().render(np.eye(4), 64, 128)
    scene = tmp_path / "home"
    (scene / "panoramas").mkdir(parents=True)
    for name in ("hall", "kitchen"):
        Image.fromarray(rgb).save(scene / "panoramas" / f"{name}.png")
    cmd = [sys.executable, str(REPO / "runner.py"), "run", str(scene), "--until", "depth"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=dict(os.environ))
    assert proc.returncode == 2
    refusals = [ln for ln in proc.stderr.splitlines() if "weights fetch" in ln]
    assert len(refusals) == 1, proc.stderr
    assert f"{scene / 'panoramas' / 'hall.png'}: no depth file" in refusals[0]
    assert f"give its metric depth as {scene / 'depths' / 'hall'}.npy|exr|png" in refusals[0]
    assert "next to the panorama" not in refusals[0]
    assert not (scene / "artifacts").exists()


def test_rgb_only_scene_takes_the_depth_model_already_on_disk_and_refuses_in_one_line_without(hub_env, tiny_files,
                                                                                              tmp_path):
    scene = _scene(tmp_path)
    sets = ["depth.depth_anything.view_size=56", "depth.rescale=never"]  # backend auto, no weights named
    cmd = [sys.executable, str(REPO / "runner.py"), "run", str(scene), "--until", "depth", *sum((["--set", s] for s in sets), [])]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=dict(os.environ))
    assert proc.returncode == 2
    refusals = [ln for ln in proc.stderr.splitlines() if "weights fetch" in ln]
    assert refusals == [refusals[0]] and "run `python runner.py weights fetch depth-anything-v2-small`" in refusals[0]
    assert "no depth file in the scene and no depth model on disk" in refusals[0]
    assert not (scene / "artifacts").exists()

    entry = registry.REGISTRY["depth-anything-v2-small"]
    put_snapshot(hub_env, entry.repo, tiny_files[0], C1)  # `weights fetch depth-anything-v2-small`, offline
    result = {r.stage: r for r in pl.run(scene, until="depth", sets=sets).results}["depth"]
    assert result.action == "ran", result.reason
    info = json.loads((scene / "artifacts" / "depth" / "manifest.json").read_text())["info"]
    assert info["backend"] == "depth-anything" and info["weights_found"]["name"] == "depth-anything-v2-small"
    assert info["weights_found"]["commit"] == C1
    assert any("depth from depth-anything-v2-small found on disk" in d for d in info["decisions"])
    depth = np.load(scene / "artifacts" / "depth" / "depth.npy")
    assert depth.shape == (64, 128) and np.isfinite(depth).all() and (depth > 0).any()
