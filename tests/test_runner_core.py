"""Runner core: code digests in the cache key, no orphan stage processes, nothing written on bad input."""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from panoworld.framework import code_digest
from panoworld.framework import pipeline as pl
from panoworld.io import manifest as art
from tests.toy.common import toy_scene, use_toy_schemas

TOY = Path(__file__).parent / "toy"
REPO = Path(__file__).resolve().parent.parent

STAGE = '''
"""Toy stage whose output comes from a helper module."""
import sys
from dataclasses import dataclass

from panoworld.framework.stage import Input
from panoworld.framework.stage_cli import stage_main
from cdtoy.helper import word

NAME, VERSION, ARTIFACT = "x", "1", "toy"
INPUTS = {"panorama": Input("file")}


@dataclass(kw_only=True)
class Params:
    n: int = 1
    """A number."""


def run(inputs, params, out_dir):
    (out_dir / "out.txt").write_text(word())
    return {}


if __name__ == "__main__":
    sys.exit(stage_main(__name__))
'''
HELPER = '''
"""Helper the toy stage imports."""


def word():
    """The word."""
    return "one"  # a comment
'''


toy_schemas = pytest.fixture(autouse=True, name="toy_schemas")(use_toy_schemas)
scene = pytest.fixture(name="scene")(toy_scene)


def _touch_later(path: Path, text: str) -> None:
    """Rewrite a file so that its mtime moves even on coarse-clock file systems."""
    st = path.stat()
    path.write_text(text)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))


def test_library_edit_reruns_the_stage_naming_the_file_and_comment_edit_does_not(scene, tmp_path, monkeypatch):
    pkg = tmp_path / "code" / "cdtoy"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "stage_x.py").write_text(STAGE)
    (pkg / "helper.py").write_text(HELPER)
    (tmp_path / "pipeline.yaml").write_text(
        "version: 1\nscene_files: {panorama: [panorama.png]}\npresets: [default]\n"
        "stages:\n  x: {module: cdtoy.stage_x, inputs: {panorama: scene.panorama}}\n")
    monkeypatch.syspath_prepend(str(tmp_path / "code"))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path / "code"), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))

    def run():
        r = pl.run(scene, pipeline=pl.Pipeline.load(tmp_path / "pipeline.yaml")).results[0]
        return r.action, r.reason

    assert run() == ("ran", "no artifact yet")
    files = art.read_manifest(scene / "artifacts/x")["code"]["files"]
    assert {"cdtoy/stage_x.py", "cdtoy/helper.py", "cdtoy/__init__.py", "panoworld/framework/stage.py"} <= set(files)
    assert run() == ("cached", "up to date")
    _touch_later(pkg / "helper.py", HELPER.replace("# a comment", "# another comment")
                 .replace('"""The word."""', '"""The word, documented again."""'))
    assert run() == ("cached", "up to date")
    _touch_later(pkg / "helper.py", HELPER.replace('return "one"', 'return "two"'))
    assert pl.status(scene, pipeline=pl.Pipeline.load(tmp_path / "pipeline.yaml"))[0]["reason"] == \
        "code changed: cdtoy/helper.py"
    assert run() == ("ran", "code changed: cdtoy/helper.py")
    assert (scene / "artifacts/x/out.txt").read_text() == "two"
    assert run() == ("cached", "up to date")


def test_code_digest_ignores_docstrings_and_comments_only():
    src = 'def f(x):\n    """Doc."""\n    return x + 1  # c\n'
    trees = [src, src.replace('"""Doc."""', '"""Other doc."""').replace("# c", "# d"), src.replace("x + 1", "x + 2")]
    digests = []
    for i, text in enumerate(trees):
        p = Path(f"/tmp/_cd_{os.getpid()}_{i}.py")
        p.write_text(text)
        digests.append(code_digest.file_digest(p, "m")[0])
        p.unlink()
    assert digests[0] == digests[1] != digests[2]


def test_a_run_digests_the_backend_it_uses_not_the_others():
    # An edit to the decoder backend (or the network it loads) does not rerun voxel-fusion Gaussians, and the other
    # way round; `auto` may pick any backend, so it digests them all.
    from panoworld.framework.stage import load_stage, stage_code

    spec = load_stage("gaussians")
    fusion = stage_code(spec, spec.params_cls(backend="voxel-fusion"))
    decoder = stage_code(spec, spec.params_cls(backend="decoder"))
    assert "panoworld/gaussians/backends/voxel_fusion.py" in fusion and "panoworld/gaussians/fusion.py" in fusion
    assert not {"panoworld/gaussians/backends/decoder.py", "panoworld/models/panovggt.py"} & set(fusion)
    assert {"panoworld/gaussians/backends/decoder.py", "panoworld/models/panovggt.py"} <= set(decoder)
    assert "panoworld/gaussians/backends/voxel_fusion.py" not in decoder
    assert stage_code(spec) == stage_code(spec, None)  # no params: every backend, as before
    assert set(fusion) | set(decoder) <= set(stage_code(spec))
    depth = load_stage("depth")
    auto = stage_code(depth, depth.params_cls())
    assert depth.params_cls().backend == "auto"
    assert {"panoworld/depth/backends/provided.py", "panoworld/depth/backends/depth_anything.py"} <= set(auto)


def toy_cli(*args) -> subprocess.CompletedProcess:
    env = dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas"))
    return subprocess.run([sys.executable, str(REPO / "runner.py"), *args, "--pipeline", str(TOY / "pipeline.yaml")],
                          capture_output=True, text=True, env=env, cwd=REPO)


def test_bad_input_found_by_a_stage_exits_2_and_leaves_nothing_behind(scene):
    before = sorted(p.name for p in scene.iterdir())
    out = toy_cli("run", str(scene), "--set", "a.refuse=true")
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip().splitlines()[-1] == (
        "error: stage a failed: bad input: toy stage a refuses its input on purpose; unset a.refuse")
    assert sorted(p.name for p in scene.iterdir()) == before  # no artifacts/, no lock, no log
    # On a scene with artifacts: the refusing stage's previous artifact and log stay, no new log is written.
    assert toy_cli("run", str(scene)).returncode == 0
    log = scene / "artifacts/logs/b.log"
    old_log, old_out = log.read_text(), (scene / "artifacts/b/out.txt").read_text()
    out = toy_cli("run", str(scene), "--set", "b.refuse=true", "--set", "b.n=3")
    assert out.returncode == 2, out.stderr
    assert log.read_text() == old_log and (scene / "artifacts/b/out.txt").read_text() == old_out
    assert not list((scene / "artifacts").rglob(".*.part")) and not list((scene / "artifacts").rglob(".params-*"))


def _children(pid: int) -> list[int]:
    import psutil

    return [c.pid for c in psutil.Process(pid).children(recursive=True)]


def test_sigkill_of_the_runner_alone_leaves_no_stage_process_and_commits_nothing(scene, tmp_path):
    import psutil

    env = dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas"), TMPDIR=str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    runner = subprocess.Popen(
        [sys.executable, str(REPO / "runner.py"), "run", str(scene), "--pipeline", str(TOY / "pipeline.yaml"),
         "--set", "a.sleep=3"], env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    log = scene / f"artifacts/logs/.a.log.{runner.pid}.part"
    deadline = time.time() + 60
    while time.time() < deadline and not (log.is_file() and "sleeping" in log.read_text()):
        time.sleep(0.05)
    stage_pids = _children(runner.pid)
    assert stage_pids, "the stage should be running"
    assert list((scene / "artifacts/logs").glob(".params-*.json")), "the params file lives beside the log"
    os.kill(runner.pid, signal.SIGKILL)  # the runner alone, not its process group
    runner.wait()
    deadline = time.time() + 10
    while time.time() < deadline and any(psutil.pid_exists(p) and psutil.Process(p).status() != "zombie"
                                         for p in stage_pids):
        time.sleep(0.05)
    assert not any(psutil.pid_exists(p) and psutil.Process(p).status() != "zombie" for p in stage_pids)
    time.sleep(3.5)  # past the stage's sleep: an orphan would have committed by now
    assert not (scene / "artifacts/a").exists()
    assert not list((tmp_path / "tmp").iterdir()), "nothing leaks into the temp directory"
    # The next run cleans up after the killed one and runs normally.
    assert toy_cli("run", str(scene)).returncode == 0
    assert not list((scene / "artifacts").rglob(".params-*")) and not list((scene / "artifacts").glob(".tmp-*"))


def test_a_stage_does_not_commit_for_a_runner_that_no_longer_holds_the_lock(scene, monkeypatch):
    from panoworld.core.errors import PipelineError
    from panoworld.framework.stage import LOCK_ENV, RUNNER_PID_ENV, execute_stage, load_stage
    from panoworld.framework.stage_params import params_from_dict

    spec = load_stage("tests.toy.a")
    (scene / "artifacts").mkdir()
    (scene / "artifacts/.lock").write_text("pid 999999 since 2026-01-01 00:00:00")
    monkeypatch.setenv(LOCK_ENV, str(scene / "artifacts/.lock"))
    monkeypatch.setenv(RUNNER_PID_ENV, str(os.getppid()))  # our parent, but the lock names another runner
    with pytest.raises(PipelineError, match="no longer holds"):
        execute_stage(spec, {"panorama": scene / "panorama.png"}, params_from_dict(spec.params_cls, {}),
                      scene / "artifacts/a")
    assert not (scene / "artifacts/a").exists() and not list((scene / "artifacts").glob(".tmp-*"))
    (scene / "artifacts/.lock").write_text(f"pid {os.getppid()} since 2026-01-01 00:00:00")
    with pytest.raises(PipelineError, match="no longer holds"):  # named, but nobody holds the flock on artifacts/
        execute_stage(spec, {"panorama": scene / "panorama.png"}, params_from_dict(spec.params_cls, {}),
                      scene / "artifacts/a")
    held = os.open(scene / "artifacts", os.O_RDONLY | os.O_DIRECTORY)  # the runner's flock (another open file)
    fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
    execute_stage(spec, {"panorama": scene / "panorama.png"}, params_from_dict(spec.params_cls, {}), scene / "artifacts/a")
    assert (scene / "artifacts/a/out.txt").is_file()
    os.close(held)


def test_code_digest_cache_keeps_what_other_processes_wrote(tmp_path, monkeypatch):
    """A checkout's runner and stages share its ~/.cache/panoworld/code_digests-*.json: a process saving its digests
    must not drop those another wrote meanwhile (a no-op would parse them all again: seconds on a busy machine)."""
    from panoworld.framework import code_digest
    from panoworld.io.user_cache import read_user_cache, write_user_cache

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(code_digest, "_memo", {"/ours.py": (1, 2, "d1", [])})
    monkeypatch.setattr(code_digest, "_disk_loaded", True)
    write_user_cache(code_digest._CACHE_FILE, {"/theirs.py": [3, 4, "d2", ["x"]], "/ours.py": [0, 0, "old", []]})
    code_digest._save_disk_cache()
    doc = read_user_cache(code_digest._CACHE_FILE)
    assert doc["/theirs.py"] == [3, 4, "d2", ["x"]] and doc["/ours.py"] == [1, 2, "d1", []]
    monkeypatch.setattr(code_digest, "_CACHE_KEEP", 1)
    code_digest._save_disk_cache()
    assert list(read_user_cache(code_digest._CACHE_FILE)) == ["/ours.py"]  # bounded, the newest kept


def test_yaml_documents_are_cached_by_their_text(tmp_path, monkeypatch):
    """An unchanged pipeline.yaml / scene.yaml is read back from the user cache; an edited one is parsed again, a
    document JSON cannot keep exactly (a date) is never cached, and a broken one fails every time."""
    import datetime

    import yaml

    from panoworld.framework.dag import cached_yaml

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    calls: list[str] = []

    def parse(text):
        calls.append(text)
        return yaml.safe_load(text)

    assert cached_yaml("preset: ci-tiny\n", parse) == {"preset": "ci-tiny"}
    assert cached_yaml("preset: ci-tiny\n", parse) == {"preset": "ci-tiny"} and len(calls) == 1
    assert cached_yaml("preset: default\n", parse) == {"preset": "default"} and len(calls) == 2
    assert cached_yaml("day: 2026-01-02\n", parse) == {"day": datetime.date(2026, 1, 2)}
    assert cached_yaml("day: 2026-01-02\n", parse) == {"day": datetime.date(2026, 1, 2)} and len(calls) == 4
    for _ in range(2):
        with pytest.raises(yaml.YAMLError):
            cached_yaml("a: [1, 2\n", parse)
    assert len(calls) == 6


def test_stage_processes_get_one_blas_thread_but_depth_and_a_set_value(tmp_path):
    """stages/__init__ (loaded before numpy in `python -m stages.NAME`): OPENBLAS_NUM_THREADS=1 in a stage process,
    unset for the depth stage and for a process that only imports the package (the runner), a user's value kept."""
    pkg = tmp_path / "stages"
    pkg.mkdir()
    (pkg / "__init__.py").write_text((REPO / "stages" / "__init__.py").read_text())
    probe = 'import os; print(os.environ.get("OPENBLAS_NUM_THREADS"))'
    for name in ("mesh", "depth"):
        (pkg / f"{name}.py").write_text(probe)
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}

    def threads(args, **extra):
        return subprocess.run([sys.executable, *args], cwd=tmp_path, env={**env, **extra}, capture_output=True,
                              text=True, check=True).stdout.strip()

    assert threads(["-m", "stages.mesh", "--out", "x"]) == "1"
    assert threads(["-m", "stages.depth"]) == "None"
    assert threads(["-c", f"import stages; {probe}"]) == "None"
    assert threads(["-m", "stages.mesh"], OPENBLAS_NUM_THREADS="2") == "2"
