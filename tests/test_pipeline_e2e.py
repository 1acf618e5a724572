"""The real pipeline end to end on a ci-tiny synthetic scene: every stage runs, then caches, reruns in isolation."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from panoworld.framework import pipeline as pl
from panoworld.io import manifest as art
from tests.test_report import pipeline_scene  # noqa: F401 - the shared session fixture (ci-tiny, every stage run)

REPO = Path(__file__).resolve().parent.parent
HEAVY = ("torch", "numba", "trimesh", "pycolmap", "diffusers", "transformers", "embreex", "ray", "cv2", "scipy")


@pytest.mark.parametrize("stage", [*pl.Pipeline.load().order, "register", "<runner>"])
def test_stage_modules_import_light(stage):
    """The runner imports every stage module for its params: heavy libraries must be imported inside run()."""
    module = "panoworld.framework.pipeline" if stage == "<runner>" else f"stages.{stage}"
    code = f"import sys, {module}; print([m for m in {HEAVY!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", f"{module} imports {out.stdout.strip()} at module level"


def _artifact_bytes(scene: Path, stages: list[str]) -> dict[str, str]:
    """{path: sha256} of every file of the stages' artifacts (manifests and logs excepted: timings live there)."""
    root = scene / "artifacts"
    return {p.relative_to(root).as_posix(): art.file_digest(p) for s in stages for p in sorted((root / s).rglob("*"))
            if p.is_file() and p.name != art.MANIFEST}


@pytest.mark.slow
def test_full_pipeline_runs_caches_and_reruns_one_stage(synth_scene, pipeline_scene, tmp_path):  # noqa: F811
    import yaml

    from panoworld.framework.stage_params import params_to_dict

    scene = tmp_path / "scene"
    shutil.copytree(synth_scene, scene, ignore=shutil.ignore_patterns("artifacts"))
    order = pl.Pipeline.load().order

    # The demo on an existing scene runs it at its preset and remembers the preset in scene.yaml ...
    import runner

    assert runner.main(["demo", str(tmp_path), "--preset", "ci-tiny"]) == 0
    assert yaml.safe_load((scene / "scene.yaml").read_text()) == {"preset": "ci-tiny"}
    # The default trajectory holds several paths (one per sector); every downstream stage consumed all its poses.
    traj = art.read_manifest(scene / "artifacts" / "trajectory")["info"]
    assert traj["kind"] == "explore" and traj["paths"] > 1
    assert len(json.loads((scene / "artifacts" / "poses" / "poses.json").read_text())["poses"]) == traj["frames"]
    # warp-inpaint renders every frame at its planned pose, so the poses stage's auto takes the plan and says why.
    poses = art.read_manifest(scene / "artifacts" / "poses")["info"]
    assert poses["backend"] == "planned" and poses["backend_requested"] == "auto"
    assert "video backend warp-inpaint renders every frame at its planned pose" in poses["decisions"][0]
    for name in order:
        m = art.read_manifest(scene / "artifacts" / name)
        assert m["stage"] == name and m["peak_rss_mb"] > 0 and m["params"] == params_to_dict(
            pl.resolve_params(pl.Pipeline.load(), "ci-tiny", None, {}, [name])[name])
    # Two runs of the pipeline on the same scene (this one and the session's shared run) give byte-identical artifacts.
    ours, shared = _artifact_bytes(scene, order), _artifact_bytes(pipeline_scene, order)
    assert {"navmesh/navmesh.json", "gaussians/gaussians.ply"} <= set(ours)
    assert ours.keys() == shared.keys()
    assert [k for k in ours if ours[k] != shared[k]] == []

    # ... so that status and run without --preset agree with it, and a demo of another preset is refused.
    assert {r["state"] for r in pl.status(scene)} == {"up-to-date"}, pl.status(scene)
    second = pl.run(scene)
    assert [r.action for r in second.results] == ["cached"] * len(order), second.table()
    assert runner.main(["demo", str(tmp_path), "--preset", "default"]) == 2

    out = subprocess.run([sys.executable, "runner.py", "run", str(scene), "--preset", "ci-tiny", "--only", "video",
                          "--force", "--json"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    actions = {s["stage"]: s["action"] for s in json.loads(out.stdout)["stages"]}
    assert actions["video"] == "ran"
    assert all(a == "skipped" for s, a in actions.items() if s != "video")

    third = pl.run(scene, preset="ci-tiny", sets=["trajectory.stride=2"], until="trajectory")
    acts = {r.stage: r.action for r in third.results}
    assert [acts[s] for s in ("depth", "mesh", "navmesh")] == ["cached"] * 3
    assert acts["trajectory"] == "ran"
    assert next(r for r in third.results if r.stage == "trajectory").reason.startswith("params changed: trajectory.stride 1 -> 2")
