"""Runner tests on the toy pipeline: caching, reruns, crash safety, tampering, locking, bad input."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from panoworld.framework import pipeline as pl
from panoworld.io import manifest as art
from tests.toy.common import toy_scene, use_toy_schemas

TOY = Path(__file__).parent / "toy"
REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def toy_schemas(monkeypatch):
    use_toy_schemas(monkeypatch)


@pytest.fixture
def scene(tmp_path) -> Path:
    return toy_scene(tmp_path)


def toy_pipe() -> pl.Pipeline:
    return pl.Pipeline.load(TOY / "pipeline.yaml")


def run(scene, **kw) -> dict[str, pl.StageResult]:
    report = pl.run(scene, pipeline=toy_pipe(), **kw)
    return {r.stage: r for r in report.results}


def actions(res) -> dict[str, str]:
    return {k: r.action for k, r in res.items()}


def cli(*args, env_extra=None, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas"), **(env_extra or {}))
    return subprocess.run([sys.executable, str(REPO / "runner.py"), *args], capture_output=True, text=True, env=env,
                          **{"cwd": REPO, **kw})


def test_second_run_is_all_cached(scene):
    assert actions(run(scene)) == dict.fromkeys("abcd", "ran")
    res = run(scene)
    assert actions(res) == dict.fromkeys("abcd", "cached")
    assert all(r.reason == "up to date" for r in res.values())


def test_param_change_reruns_stage_and_downstream_only(scene):
    run(scene)
    res = run(scene, sets=["b.n=2"])
    assert actions(res) == {"a": "cached", "b": "ran", "c": "ran", "d": "cached"}
    assert res["b"].reason == "params changed: b.n 1 -> 2"
    assert res["c"].reason == "input changed: b"
    (scene / "scene.yaml").write_text("params:\n  b: {n: 2}\n")
    assert actions(run(scene)) == dict.fromkeys("abcd", "cached")


def test_identical_upstream_output_keeps_downstream_cached(scene):
    run(scene)
    res = run(scene, only=["a"], force=True)
    assert actions(res) == {"a": "ran", "b": "skipped", "c": "skipped", "d": "skipped"}
    assert actions(run(scene)) == dict.fromkeys("abcd", "cached")


def test_only_reruns_one_stage_from_cached_inputs(scene):
    run(scene)
    res = run(scene, only=["c"], sets=["c.n=3"])
    assert actions(res) == {"a": "skipped", "b": "skipped", "c": "ran", "d": "skipped"}
    assert (scene / "artifacts/c/out.txt").read_text().startswith("c|3|b|1|a|1|")


def test_only_with_missing_input_is_a_clear_failure(scene):
    res = run(scene, only=["b"])
    assert res["b"].action == "failed"
    assert "missing input: a (stage a)" in res["b"].reason
    assert not (scene / "artifacts/b").exists()


def test_from_reruns_the_tail(scene):
    run(scene)
    res = run(scene, from_="b")
    assert actions(res) == {"a": "skipped", "b": "ran", "c": "ran", "d": "skipped"}


def test_until_stops(scene):
    res = run(scene, until="b")
    assert actions(res) == {"a": "ran", "b": "ran", "c": "skipped", "d": "skipped"}


def test_scene_given_relative_to_another_directory(scene):
    """Stages run from the repository root; a scene path relative to the user's directory must still be found."""
    out = cli("run", scene.name, "--pipeline", str(TOY / "pipeline.yaml"), cwd=scene.parent)
    assert out.returncode == 0, out.stdout + out.stderr
    assert (scene / "artifacts/d/out.txt").exists()


def test_failure_stops_and_keep_going_runs_independent_branch(scene):
    res = run(scene, sets=["b.fail=true"])
    assert res["b"].action == "failed" and "log:" in res["b"].reason
    assert "failed on purpose" in (scene / "artifacts/logs/b.log").read_text()
    assert res["c"].action == "skipped" and res["d"].action == "skipped"
    assert not (scene / "artifacts/b").exists()
    assert not list((scene / "artifacts").glob(".tmp-*"))
    res = run(scene, sets=["b.fail=true"], keep_going=True)
    assert actions(res) == {"a": "cached", "b": "failed", "c": "skipped", "d": "ran"}
    assert res["c"].reason == "upstream b failed"


def test_killed_stage_leaves_old_artifact_valid_and_next_run_repairs(scene):
    run(scene)
    old = (scene / "artifacts/b/out.txt").read_text()
    proc = subprocess.Popen(
        [sys.executable, str(REPO / "runner.py"), "run", str(scene), "--pipeline", str(TOY / "pipeline.yaml"),
         "--set", "b.n=7", "--set", "b.sleep=30"],
        env=dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas")), cwd=REPO, start_new_session=True,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    log = scene / f"artifacts/logs/.b.log.{proc.pid}.part"  # the stage's log while it runs
    deadline = time.time() + 30
    while time.time() < deadline and not (log.is_file() and "sleeping" in log.read_text()):
        time.sleep(0.05)
    assert log.is_file() and "sleeping" in log.read_text(), "stage b should be sleeping"
    assert list((scene / "artifacts").glob(".tmp-b-*")), "stage should be mid-write"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    manifest = art.read_manifest(scene / "artifacts/b", "toy")
    assert art.verify_files(scene / "artifacts/b", manifest) is None
    assert (scene / "artifacts/b/out.txt").read_text() == old
    res = run(scene, sets=["b.n=7"])
    assert res["b"].action == "ran" and res["b"].reason == "params changed: b.n 1 -> 7"
    assert not list((scene / "artifacts").glob(".tmp-*"))
    assert (scene / "artifacts/b/out.txt").read_text().startswith("b|7|")


def _rewrite_manifest(path: Path, edit, fix_checksum: bool) -> None:
    m = json.loads(path.read_text())
    edit(m)
    if fix_checksum:
        m["checksum"] = art.manifest_checksum(m)
    path.write_text(json.dumps(m))


@pytest.mark.parametrize(
    "edit, fix, expect",
    [
        (lambda m: m["params"].update(n=9), False, "checksum mismatch"),
        (lambda m: m.pop("key"), True, "schema-invalid at <root>: 'key' is a required property"),
        (lambda m: m.update(schema_version=0), True, "schema version 0 of 'toy' is no longer accepted"),
        (lambda m: m["files"]["out.txt"].update(sha256="0" * 64), False, "checksum mismatch"),
    ],
)
def test_tampered_or_invalid_manifest_is_detected_with_reason(scene, edit, fix, expect):
    run(scene)
    _rewrite_manifest(scene / "artifacts/b/manifest.json", edit, fix)
    res = run(scene)
    assert res["b"].action == "ran"
    assert expect in res["b"].reason
    assert res["a"].action == "cached"


def test_modified_output_file_is_detected(scene):
    run(scene)
    out = scene / "artifacts/b/out.txt"
    out.write_text(out.read_text().replace("b", "x"))  # same size, new mtime
    res = run(scene)
    assert res["b"].action == "ran" and "output file changed" in res["b"].reason


def test_scene_input_change_reruns(scene):
    run(scene)
    Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(scene / "panorama.png")
    res = run(scene)
    assert res["a"].reason == "input changed: panorama"
    (scene / "extra.txt").write_text("x")
    assert actions(run(scene)) == {"a": "cached", "b": "cached", "c": "cached", "d": "ran"}


def test_two_concurrent_runs_do_not_both_write(scene):
    proc = subprocess.Popen(
        [sys.executable, str(REPO / "runner.py"), "run", str(scene), "--pipeline", str(TOY / "pipeline.yaml"), "--set", "a.sleep=5"],
        env=dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas")), cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        log = scene / f"artifacts/logs/.a.log.{proc.pid}.part"  # stage a is running (sleeping 5 s)
        deadline = time.time() + 20
        while time.time() < deadline and not (log.is_file() and "sleeping" in log.read_text()):
            time.sleep(0.05)
        second = cli("run", str(scene), "--pipeline", str(TOY / "pipeline.yaml"))
        assert second.returncode == 2
        assert "another runner is working on this scene" in second.stderr
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == 0


def test_json_report_and_status(scene):
    out = cli("run", str(scene), "--pipeline", str(TOY / "pipeline.yaml"), "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert [s["stage"] for s in doc["stages"]] == list("abcd")
    assert set(doc["stages"][0]) == {"stage", "action", "reason", "seconds", "peak_rss_mb", "bad_input"}
    assert all(s["action"] == "ran" and s["peak_rss_mb"] > 0 for s in doc["stages"])
    st = cli("status", str(scene), "--pipeline", str(TOY / "pipeline.yaml"), "--json")
    rows = json.loads(st.stdout)["stages"]
    assert all(r["state"] == "up-to-date" and r["schema_version"] == 1 for r in rows)
    st = cli("status", str(scene), "--pipeline", str(TOY / "pipeline.yaml"), "--set", "c.n=4", "--json")
    assert json.loads(st.stdout)["stages"][2]["reason"] == "params changed: c.n 1 -> 4"


def test_dry_run_writes_nothing(scene):
    res = run(scene, dry_run=True)
    assert actions(res) == dict.fromkeys("abcd", "would-run")
    assert not (scene / "artifacts").exists()


def test_presets_apply_and_set_overrides(scene):
    run(scene, preset="ci-tiny")
    assert (scene / "artifacts/a/out.txt").read_text().startswith("a|5|")
    run(scene, preset="ci-tiny", sets=["a.n=6"])
    assert (scene / "artifacts/a/out.txt").read_text().startswith("a|6|")


@pytest.mark.parametrize(
    "setup, args, expect",
    [
        ("missing", [], "no panorama; expected one of panorama.png, panorama.jpg"),
        ("square", [], "is not an equirectangular panorama"),
        ("corrupt", [], "panorama is corrupt or not an image"),
        ("ok", ["--only", "nope"], "--only nope: unknown stage"),
        ("ok", ["--set", "b.bogus=1"], "b.bogus: unknown param; known: fail, n, refuse, sleep (from --set)"),
        ("ok", ["--set", "b.sleeep=1"], "b.sleeep: unknown param; did you mean sleep? (from --set)"),
        ("ok", ["--set", "b.n=101"], "b.n=101: must be <= 100 (from --set)"),
        ("ok", ["--dry-run", "--set", "a.sleep=nan"], "a.sleep=nan: must be a finite number (from --set)"),
        ("ok", ["--dry-run", "--set", "a.sleep=-1"], "a.sleep=-1.0: must be >= 0 (from --set)"),
        ("ok", ["--set", "zzz.n=1"], "--set zzz: unknown stage; known: a, b, c, d"),
        ("yaml:params: [1, 2]", [], "scene.yaml: params: expected a mapping of stage: {param: value}, got [1, 2]"),
        ("yaml:params: {bb: {n: 1}}", ["--dry-run"], "scene.yaml: params.bb: unknown stage; did you mean b?"),
        ("yaml:params: {b: {nn: 1}}", ["--dry-run"], "scene.yaml: b.nn: unknown param; did you mean n?"),
        ("yaml:params: {b: [1]}", ["--dry-run"], "scene.yaml: b: expected a mapping of param: value, got list [1]"),
        ("yaml:parms: {}", ["--dry-run"], "scene.yaml: unknown key 'parms'; did you mean params?"),
        ("yaml:params: {b: {n: 1000}}", ["--dry-run"], "b.n=1000: must be <= 100 (from scene.yaml params.b)"),
        ("yaml:params: {b: {n: 1000}}", ["status"], "b.n=1000: must be <= 100 (from scene.yaml params.b)"),
        ("ok", ["--set", "zz.n=1"], "--set zz: unknown stage"),
        ("ok", ["--set", "b.n=abc"], "b.n: cannot read 'abc' as int"),
        ("ok", ["--preset", "huge"], "--preset huge: unknown preset"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, setup, args, expect):
    d = tmp_path / "s"
    d.mkdir()
    if setup == "square":
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(d / "panorama.png")
    elif setup == "corrupt":
        (d / "panorama.png").write_bytes(b"not a png at all")
    elif setup == "ok" or setup.startswith("yaml:"):
        Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(d / "panorama.png")
    if setup.startswith("yaml:"):
        (d / "scene.yaml").write_text(setup[5:])
    before = sorted(p.name for p in d.iterdir())
    verb = "status" if args[:1] == ["status"] else "run"
    out = cli(verb, str(d), "--pipeline", str(TOY / "pipeline.yaml"), *args[1 if verb == "status" else 0:])
    assert out.returncode == 2, out.stderr
    assert expect in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in d.iterdir()) == before


def test_stage_runs_alone_without_runner(scene, tmp_path):
    out = tmp_path / "a_out"
    env = dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas"))
    p = subprocess.run([sys.executable, "-m", "tests.toy.a", "--panorama", str(scene / "panorama.png"), "--out", str(out), "--n", "4"],
                       capture_output=True, text=True, env=env, cwd=REPO)
    assert p.returncode == 0, p.stderr
    m = art.read_manifest(out, "toy")
    assert m["params"]["n"] == 4 and m["stage"] == "a"
    p = subprocess.run([sys.executable, "-m", "tests.toy.b", "--a", str(tmp_path / "missing"), "--out", str(tmp_path / "b")],
                       capture_output=True, text=True, env=env, cwd=REPO)
    assert p.returncode == 2 and "input a:" in p.stderr and "missing" in p.stderr
    assert not (tmp_path / "b").exists()


def test_dag_text_and_mermaid():
    out = cli("dag", "--pipeline", str(TOY / "pipeline.yaml"), "--mermaid")
    assert out.returncode == 0
    assert "a --> b" in out.stdout and "scene_extra -.-> d" in out.stdout
    real = cli("dag")
    assert real.stdout.splitlines()[0].startswith("depth")
