"""`runner.py run/eval DATASET --all`: failures isolated, reruns cached, sweeps share upstream stages, Ray == local."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

import runner
from panoworld.framework.pipeline import Pipeline, PipelineError
from panoworld.tools.batch.run import FAILURES, SUMMARY
from panoworld.tools.batch.variants import parse_sweeps, read_variant

SHARED = ("depth", "mesh", "navmesh")
RUN = ["--preset", "ci-tiny", "--until", "poses", "--sweep", "trajectory.stride=1,2", "--json"]


def _files(scene: Path, variant: str | None = None) -> dict[str, dict[str, str]]:
    """{stage: {file: sha256}} of every artifact of a scene (a variant's tail from its directory): the bytes, which
    must not depend on the executor (timings live only in manifests)."""
    root = scene / "artifacts"
    out = {}
    for stage in ("depth", "mesh", "navmesh", "trajectory", "conditions", "video", "poses"):
        d = root / stage
        if variant and stage not in SHARED:
            d = root / "variants" / variant / stage
        m = json.loads((d / "manifest.json").read_text())
        out[stage] = {k: v["sha256"] for k, v in m["files"].items()}
    return out


def _actions(summary: dict, scene: str, variant: str) -> dict[str, str]:
    res = next(r for r in summary["results"] if r["scene"] == scene)
    run = next(r for r in res["runs"] if r["variant"] == variant)
    return {s["stage"]: s["action"] for s in run["stages"]}


@pytest.fixture(scope="module")
def dataset(synth_dataset, tmp_path_factory):
    """Two ci-tiny scenes and a corrupt one, run once locally with a stride sweep (2 scenes at a time)."""
    root = tmp_path_factory.mktemp("batch") / "data"
    scenes = sorted(p for p in synth_dataset.iterdir() if p.is_dir())[:2]
    for s in scenes:
        shutil.copytree(s, root / s.name, ignore=shutil.ignore_patterns("artifacts"))
    (root / "zz_corrupt").mkdir()
    (root / "zz_corrupt" / "panorama.png").write_bytes(b"not a png")
    pristine = tmp_path_factory.mktemp("batch") / "pristine"
    shutil.copytree(root / scenes[0].name, pristine / scenes[0].name)
    return {"root": root, "scenes": [s.name for s in scenes], "pristine": pristine}


@pytest.fixture(scope="module")
def first_run(dataset):
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = runner.main(["run", str(dataset["root"]), "--all", "--workers", "2", *RUN])
    return code, json.loads(buf.getvalue())


def test_sweep_names_and_tails():
    pipe = Pipeline.load()
    vs = parse_sweeps(["trajectory.stride=1,2,4", "trajectory.kind=ring,sector"], pipe)
    assert [v.name for v in vs][:2] == ["stride-1_kind-ring", "stride-1_kind-sector"] and len(vs) == 6
    assert vs[0].tail(pipe) == ["trajectory", "conditions", "video", "poses", "gaussians", "asset"]
    with pytest.raises(PipelineError, match="expected STAGE.PARAM=V1,V2"):
        parse_sweeps(["trajectory.stride"], pipe)


@pytest.mark.slow
def test_corrupt_scene_fails_alone_and_the_sweep_shares_upstream_stages(dataset, first_run):
    code, summary = first_run
    root = dataset["root"]
    assert code == 1 and summary["scenes_failed"] == ["zz_corrupt"]
    assert summary["scenes_ok"] == 2 and summary["runs"] == 6 and summary["runs_ok"] == 4
    failures = [json.loads(line) for line in (root / FAILURES).read_text().splitlines()]
    assert {f["scene"] for f in failures} == {"zz_corrupt"} and "corrupt or not an image" in failures[0]["error"]
    assert json.loads((root / SUMMARY).read_text())["scenes_failed"] == ["zz_corrupt"]
    for scene in dataset["scenes"]:
        # Variants of a scene run one after the other: the first computes depth/mesh/navmesh, the second reuses them.
        a1, a2 = _actions(summary, scene, "stride-1"), _actions(summary, scene, "stride-2")
        ran_first = {s for s in SHARED if a1[s] == "ran"}
        assert ran_first == set(SHARED) and all(a2[s] == "cached" for s in SHARED), (a1, a2)
        assert a1["trajectory"] == a2["trajectory"] == "ran" and a2["poses"] == "ran"
        assert read_variant(root / scene, "stride-2")["tail"][0] == "trajectory"
        t1 = json.loads((root / scene / "artifacts/variants/stride-1/trajectory/manifest.json").read_text())
        t2 = json.loads((root / scene / "artifacts/variants/stride-2/trajectory/manifest.json").read_text())
        assert (t1["params"]["stride"], t2["params"]["stride"]) == (1, 2)
        assert not (root / scene / "artifacts" / "trajectory").exists()  # the tail never lands in the shared place


@pytest.mark.slow
def test_rerun_is_all_cached_and_eval_aggregates_the_strides(dataset, first_run, capsys):
    root = dataset["root"]
    assert runner.main(["run", str(root), "--all", *RUN]) == 1
    summary = json.loads(capsys.readouterr().out)
    until_poses = len(Pipeline.load().ancestors("poses")) + 1
    assert summary["stages"]["ran"] == 0 and summary["stages"]["cached"] == 2 * 2 * until_poses
    assert runner.main(["eval", str(root), "--all", "--max-frames", "2", "--only", "video", "--only", "poses",
                        "--only", "trajectory"]) == 1  # the corrupt scene has nothing to evaluate
    out = capsys.readouterr().out
    assert "ours (warp-inpaint) r=1 explore [2 scenes]" in out and "ours (warp-inpaint) r=2 explore [2 scenes]" in out
    assert "GT track (ref.) r=2" in out and "FID: lacking in 2 scene(s)" in out
    results = json.loads((root / "eval_results.json").read_text())
    units = {u["unit"]: u for u in results["units"]}
    assert set(units) == {f"{s}/stride-{r}" for s in dataset["scenes"] for r in (1, 2)} | {"zz_corrupt"}
    assert units["zz_corrupt"]["error"].startswith("EvalInputError")
    video = next(t for t in results["tables"] if t["title"].startswith("Panoramic video"))
    row = next(r for r in video["rows"] if r["label"].startswith("ours") and "r=2" in r["label"])
    assert row["cells"]["PSNR"]["n"] == 2 and row["cells"]["ATE"]["mean"] == pytest.approx(0.0, abs=1e-9)
    assert row["cells"]["LPIPS"]["lacking"] == [f"{s}/stride-2" for s in dataset["scenes"]]


@pytest.mark.slow
def test_ray_executor_gives_the_same_artifacts_and_tables(dataset, first_run, tmp_path):
    pytest.importorskip("ray")
    import ray

    from panoworld.tools.eval.cli import EvalParams, evaluate_scene
    from panoworld.tools.eval.tables import build_tables

    scene = dataset["scenes"][0]
    ray_root = tmp_path / "data"
    shutil.copytree(dataset["pristine"], ray_root)
    try:
        code = runner.main(["run", str(ray_root), "--all", "--executor", "ray", "--workers", "2", "--preset", "ci-tiny",
                            "--until", "poses", "--sweep", "trajectory.stride=2", "--json"])
    finally:
        ray.shutdown()
    assert code == 0
    assert _files(ray_root / scene, "stride-2") == _files(dataset["root"] / scene, "stride-2")
    params = EvalParams(max_frames=2)
    tables = []
    for root in (dataset["root"], ray_root):
        rep, errors = evaluate_scene(root / scene, params, variant="stride-2", stages=["video", "poses", "trajectory"])
        assert errors == []
        tables.append("\n".join(t.text() for t in build_tables([{**rep, "unit": f"{scene}/stride-2"}])))
    assert tables[0] == tables[1] and "r=2 explore [1 scenes]" in tables[0]
