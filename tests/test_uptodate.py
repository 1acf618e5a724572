"""Up-to-date records: a plain run with nothing changed replays the last no-op; any edit falls back to the decisions."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from panoworld.framework import pipeline as pl
from tests.test_runner_core import HELPER, STAGE
from tests.toy.common import toy_scene, use_toy_schemas

TOY = Path(__file__).parent / "toy"
REPO = Path(__file__).resolve().parent.parent



@pytest.fixture
def setup(tmp_path, monkeypatch):
    """(scene, pipeline.yaml): the toy DAG a -> b -> c, a -> d plus stage x of a package outside the repository,
    schemas copied beside them, a user cache of its own."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    use_toy_schemas(monkeypatch)
    shutil.copytree(TOY / "schemas", tmp_path / "schemas")
    monkeypatch.setenv("PANOWORLD_SCHEMA_PATH", str(tmp_path / "schemas"))
    pkg = tmp_path / "code" / "uptoy"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "stage_x.py").write_text(STAGE.replace("cdtoy", "uptoy"))
    (pkg / "helper.py").write_text(HELPER)
    for name in [m for m in sys.modules if m.partition(".")[0] == "uptoy"]:  # another test's package
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(tmp_path / "code"))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path / "code"), os.environ.get("PYTHONPATH", "")]))
    pipe = tmp_path / "pipeline.yaml"
    pipe.write_text((TOY / "pipeline.yaml").read_text()
                    + "  x: {module: uptoy.stage_x, inputs: {panorama: scene.panorama}}\n")
    return toy_scene(tmp_path), pipe


def decide(monkeypatch) -> list[str]:
    """The stages whose state the runner decides from here on (a replayed run decides none)."""
    decided, real = [], pl.stage_state
    monkeypatch.setattr(pl, "stage_state", lambda node, *a: decided.append(node.name) or real(node, *a))
    return decided


def run(scene: Path, pipe: Path, **kw) -> list[tuple[str, str, str]]:
    return [(r.stage, r.action, r.reason) for r in pl.run(scene, pipeline=pl.Pipeline.load(pipe), **kw).results]


def rewrite(path: Path, text: str) -> None:
    """New content of the same size with the old mtime put back: only the ctime tells."""
    st = path.stat()
    path.write_text(text)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_a_noop_is_replayed_and_reports_what_the_decisions_report(setup, monkeypatch):
    scene, pipe = setup
    assert {a for _, a, _ in run(scene, pipe)} == {"ran"}
    decided = decide(monkeypatch)
    full = run(scene, pipe, dry_run=True)  # decides every stage, never replays
    assert len(decided) == 5 and [a for _, a, _ in full] == ["cached"] * 5
    decided.clear()
    assert run(scene, pipe) == full and run(scene, pipe) == full
    assert decided == []  # the run that ran the stages recorded the no-op that follows it
    assert run(scene, pipe, sets=["b.n=1"]) == full and len(decided) == 5  # other arguments: decided, then recorded
    decided.clear()
    assert run(scene, pipe, sets=["b.n=1"]) == full and decided == []


EDITS = {
    "artifact file": lambda s, p: (s / "artifacts/b/out.txt").write_text((s / "artifacts/b/out.txt").read_text().replace("b", "x")),
    "manifest": lambda s, p: (s / "artifacts/c/manifest.json").write_text(
        (s / "artifacts/c/manifest.json").read_text().replace('"n": 1', '"n": 2')),
    "scene input": lambda s, p: Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(s / "panorama.png"),
    "new optional input": lambda s, p: (s / "extra.txt").write_text("x"),
    "scene.yaml": lambda s, p: (s / "scene.yaml").write_text("params: {c: {n: 3}}\n"),
    "pipeline.yaml": lambda s, p: p.write_text(p.read_text().replace("params: {}", "params: {n: 2}")),
    "stage code": lambda s, p: (p.parent / "code/uptoy/helper.py").write_text(HELPER.replace('"one"', '"two"')),
    "schema": lambda s, p: (p.parent / "schemas/toy.schema.json").write_text(
        json.dumps(json.loads((p.parent / "schemas/toy.schema.json").read_text()), indent=4)),
}


@pytest.mark.parametrize("edit", EDITS)
def test_any_edit_falls_back_to_the_decisions(setup, monkeypatch, edit):
    scene, pipe = setup
    run(scene, pipe)
    decided = decide(monkeypatch)
    assert run(scene, pipe) == run(scene, pipe, dry_run=True) and decided == list("abcdx")  # the dry run's
    EDITS[edit](scene, pipe)
    decided.clear()
    dry = run(scene, pipe, dry_run=True)
    got = run(scene, pipe)
    assert len(decided) == 10 + 5 * any(a == "ran" for _, a, _ in got)  # a run that ran stages decides again after
    for (stage, action, why), (_, dry_action, dry_why) in zip(got, dry):
        if not dry_why.startswith("upstream will rerun"):  # decided on its own, not after its upstream reran
            assert (action, why) == ("ran" if dry_action == "would-run" else dry_action, dry_why), stage
    if edit != "schema":  # a schema reformatted accepts the same manifests
        assert any(a == "ran" for _, a, _ in got)
    decided.clear()
    assert {a for _, a, _ in run(scene, pipe)} == {"cached"} and decided == []


def test_an_input_edited_in_place_with_its_size_and_mtime_kept_reruns(setup, monkeypatch):
    scene, pipe = setup
    (scene / "extra.txt").write_text("x")
    run(scene, pipe)
    decided = decide(monkeypatch)
    assert {a for _, a, _ in run(scene, pipe)} == {"cached"} and decided == []
    rewrite(scene / "extra.txt", "y")
    assert ("d", "ran", "input changed: extra") in run(scene, pipe)


def test_a_file_changed_while_deciding_leaves_no_record(setup, monkeypatch):
    scene, pipe = setup
    run(scene, pipe)
    (scene / "notes.txt").write_text("a file of the user's: the record no longer holds")
    decided, real = [], pl.stage_state

    def state(node, *a):  # the panorama written again, same bytes, while the runner decides
        if not decided:
            (scene / "panorama.png").write_bytes((scene / "panorama.png").read_bytes())
        decided.append(node.name)
        return real(node, *a)

    monkeypatch.setattr(pl, "stage_state", state)
    assert {a for _, a, _ in run(scene, pipe)} == {"cached"} and len(decided) == 5  # the same content: up to date
    assert {a for _, a, _ in run(scene, pipe)} == {"cached"} and len(decided) == 10  # but not replayed
    assert {a for _, a, _ in run(scene, pipe)} == {"cached"} and len(decided) == 10


def test_a_replay_holds_the_scene_lock(setup):
    scene, pipe = setup
    run(scene, pipe)
    fd = os.open(scene / "artifacts", os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(pl.PipelineError, match="another runner is working on this scene"):
            run(scene, pipe)
    finally:
        os.close(fd)


def test_a_replayed_cli_run_imports_no_stage_and_no_numpy(setup):
    scene, pipe = setup
    probe = ("import sys, runner; code = runner.main(sys.argv[1:]); "
             "print(sorted({m.split('.')[0] for m in sys.modules} & {'numpy', 'yaml', 'jsonschema', 'uptoy', 'tests'})); "
             "sys.exit(code)")
    cmd = [sys.executable, "-c", probe, "run", str(scene), "--pipeline", str(pipe), "--json"]
    first = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    second = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    assert "numpy" in first.stdout.splitlines()[-1]  # it decided: the stages' imports
    assert second.stdout.splitlines()[-1] == "[]"
    assert [s["action"] for s in json.loads(second.stdout.rsplit("\n", 2)[0])["stages"]] == ["cached"] * 5


def test_code_rewritten_unchanged_is_not_parsed_again_and_an_edit_is(tmp_path, monkeypatch):
    """A checkout, merge or copy that rewrites files without changing them costs a read and a hash per file (the
    digest by text, shared by every checkout), not a parse; an edited file is parsed and its digest moves."""
    from panoworld.framework import code_digest

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(code_digest, "_by_text", None)
    (tmp_path / "one").mkdir()
    (tmp_path / "one/mod.py").write_text(HELPER)
    parsed, real = [], code_digest._imports
    monkeypatch.setattr(code_digest, "_imports", lambda tree, *a: parsed.append(a[0]) or real(tree, *a))
    first = code_digest.file_digest(tmp_path / "one/mod.py", "mod")
    shutil.copytree(tmp_path / "one", tmp_path / "two")  # another checkout: other paths, other mtimes
    code_digest._save_disk_cache()
    monkeypatch.setattr(code_digest, "_by_text", None)  # a new process
    assert code_digest.file_digest(tmp_path / "two/mod.py", "mod") == first and parsed == ["mod"]
    (tmp_path / "two/mod.py").write_text(HELPER.replace('"one"', '"two"'))
    assert code_digest.file_digest(tmp_path / "two/mod.py", "mod")[0] != first[0] and parsed == ["mod", "mod"]


def test_records_are_bounded_and_a_broken_one_is_decided_again(setup, monkeypatch):
    from panoworld.framework import uptodate

    scene, pipe = setup
    monkeypatch.setattr(uptodate, "KEEP", 2)
    for n in (1, 2, 3):  # three argument lists, three records: the two newest kept
        run(scene, pipe, sets=[f"a.n={n}"])
    folder = uptodate.user_cache_path(uptodate.RECORD_DIR)
    assert len(list(folder.glob("*.json"))) == 2
    decided = decide(monkeypatch)
    assert {a for _, a, _ in run(scene, pipe, sets=["a.n=3"])} == {"cached"} and decided == []
    for record in folder.glob("*.json"):
        record.write_text('{"paths": [], "stats": [], "results": [{"stage": "a"}]}')  # not one the runner wrote
    assert {a for _, a, _ in run(scene, pipe, sets=["a.n=3"])} == {"cached"} and len(decided) == 5
