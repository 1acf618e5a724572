"""Dataset precomputation: clip sampling distribution, caching, resume, failures, local vs Ray equality."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from panoworld.io import manifest as art
from panoworld.tools.precompute.run import (
    INDEX,
    ClipSampling,
    PrecomputeParams,
    clip_span,
    main,
    precompute,
    sample_clips,
)

ARGS = ["--clips-per-scene", "2", "--frames", "4", "--min-frames", "2", "--height", "32", "--strides", "1,2"]


def _uniform_within_5_sigma(counts: np.ndarray) -> bool:
    expected = counts.sum() / len(counts)
    return bool(np.all(np.abs(counts - expected) < 5 * np.sqrt(expected)))


def test_traversal_sampling_has_fixed_frames_and_uniform_scale():
    """The paper: every clip has the configured frame count; the traversal scale is uniform (stride set or continuous)."""
    p = PrecomputeParams(clips_per_scene=3000, strides=(1, 2, 4), frames=81)
    assert p.sampling == ClipSampling.TRAVERSAL  # the default
    tracks = [200, 321, 400]  # the 200-frame track only fits scales 1 and 2
    clips = sample_clips("scene_x", tracks, p)
    assert {c.length for c in clips} == {81}
    counts = Counter(c.stride for c in clips)
    assert set(counts) == {1, 2, 4} and _uniform_within_5_sigma(np.array(list(counts.values()))), counts
    for c in clips:
        assert 0 <= c.start and c.start + clip_span(c.length, c.stride) <= tracks[c.track]
        assert c.stride < 4 or c.track != 0
    cont = sample_clips("scene_x", tracks, PrecomputeParams(clips_per_scene=3000, frames=81, continuous_scale=True))
    scales = np.array([c.stride for c in cont])
    assert {c.length for c in cont} == {81} and scales.min() >= 1 and scales.max() <= 4
    hist, _ = np.histogram(scales, bins=12, range=(1, 4))
    assert _uniform_within_5_sigma(hist), hist
    with pytest.raises(ValueError, match=r"too short for 81 frames at traversal scale .*synth --frames 321"):
        sample_clips("short", [121], PrecomputeParams(clips_per_scene=50, frames=81))


def test_clip_lengths_and_strides_follow_the_documented_distribution():
    p = PrecomputeParams(clips_per_scene=3000, strides=(1, 2, 4), frames=81, min_frames=5, sampling=ClipSampling.LENGTH)
    clips = sample_clips("scene_x", [800, 800], p)
    lengths = np.array([c.length for c in clips])
    assert lengths.min() >= 5 and lengths.max() <= 81
    hist = np.bincount(lengths - 5, minlength=77)
    expected = len(clips) / 77
    # each length bin within 5 sigma of a uniform distribution
    assert np.all(np.abs(hist - expected) < 5 * np.sqrt(expected)), hist
    strides = Counter(c.stride for c in clips)
    assert set(strides) == {1, 2, 4}
    assert all(abs(v - len(clips) / 3) < 5 * np.sqrt(len(clips) / 3) for v in strides.values())
    tracks = Counter(c.track for c in clips)
    assert abs(tracks[0] - tracks[1]) < 5 * np.sqrt(len(clips) / 2)
    for c in clips:
        assert 0 <= c.start and c.start + (c.length - 1) * c.stride < 800


def test_sampling_is_stable_when_adding_clips_and_short_tracks_are_capped():
    few = sample_clips("s", [50], PrecomputeParams(clips_per_scene=3, frames=81, sampling=ClipSampling.LENGTH))
    more = sample_clips("s", [50], PrecomputeParams(clips_per_scene=6, frames=81, sampling=ClipSampling.LENGTH))
    assert more[:3] == few
    assert all(c.start + (c.length - 1) * c.stride < 50 for c in more)


def _index(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / INDEX).read_text().splitlines()]


def _digests(out: Path) -> dict[str, str]:
    return {p.relative_to(out).as_posix(): art.file_digest(p) for p in sorted(out.rglob("*"))
            if p.is_file() and p.name not in ("manifest.json", "summary.json")}


@pytest.fixture(scope="module")
def first_run(synth_dataset, tmp_path_factory):
    """The synthetic dataset plus a scene with a corrupt gt.json, precomputed once locally (2 workers); the index and
    the file digests as that run left them (the cache test goes on to change the output)."""
    data = tmp_path_factory.mktemp("precompute") / "data"
    shutil.copytree(synth_dataset, data)
    (data / "zz_corrupt" / "gt").mkdir(parents=True)
    (data / "zz_corrupt" / "gt" / "gt.json").write_text("{not json")
    out = data.parent / "out"
    code = main([str(data), "--out", str(out), *ARGS, "--workers", "2", "--json"])
    return {"data": data, "out": out, "code": code, "index": (out / INDEX).read_bytes(), "digests": _digests(out)}


@pytest.mark.slow
def test_precompute_cache_resume_failures(synth_dataset, first_run):
    data, out = first_run["data"], first_run["out"]
    assert first_run["code"] == 1  # the corrupt scene fails
    index = _index(out)
    assert len(index) == 6 and {r["scene"] for r in index} == {p.name for p in synth_dataset.iterdir()}
    failures = [json.loads(x) for x in (out / "failures.jsonl").read_text().splitlines()]
    assert [f["scene"] for f in failures] == ["zz_corrupt"] and "gt.json" in failures[0]["error"]
    for row in index:
        clip = json.loads((out / row["clip_json"]).read_text())
        cond = json.loads((out / row["conditions"]).read_text())
        assert cond["num_frames"] == clip["length"] == row["length"] == 4  # traversal sampling: fixed frame count
        np.testing.assert_allclose(clip["poses"][0], np.eye(4), atol=1e-9)
        assert art.read_manifest(out / row["path"], "clip")["digest"] == row["digest"]

    params = PrecomputeParams(clips_per_scene=2, frames=4, min_frames=2, height=32, strides=(1, 2))
    again = precompute(data, out, params, workers=2, progress=False)
    assert again["rendered"] == 0 and again["cached"] == 6

    victim = out / index[3]["path"]
    shutil.rmtree(victim)
    third = precompute(data, out, params, workers=1, progress=False)
    assert third["rendered"] == 1 and third["cached"] == 5
    assert _index(out) == index

    changed = precompute(data, out, PrecomputeParams(**{**params.__dict__, "write_depth": False}), workers=2, progress=False)
    assert changed["rendered"] == 6


@pytest.mark.slow
def test_local_and_ray_give_identical_outputs(first_run, tmp_path):
    pytest.importorskip("ray")
    ray_out = tmp_path / "ray"
    assert main([str(first_run["data"]), "--out", str(ray_out), *ARGS, "--workers", "2", "--executor", "ray", "--json"]) == 1
    assert (ray_out / INDEX).read_bytes() == first_run["index"]
    assert _digests(ray_out) == first_run["digests"]  # the corrupt scene's failure line included


def test_bad_arguments_are_one_line_errors(tmp_path, capsys):
    assert main([str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "dataset directory not found" in capsys.readouterr().err
    assert main([str(tmp_path), "--out", str(tmp_path / "o"), "--height", "32", "--width", "48"]) == 2
    assert "must be 2:1" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.timeout(120)
def test_local_pool_survives_a_busy_opencv_thread_pool_in_the_parent():
    """A child forked after OpenCV's thread pool ran hangs in cv2.setNumThreads; the pool must spawn instead."""
    import cv2

    from panoworld.tools.precompute.run import LocalExecutor

    img = np.random.default_rng(0).random((1500, 1500), dtype=np.float32)
    for _ in range(3):
        cv2.GaussianBlur(img, (31, 31), 5)
    assert sorted(LocalExecutor(2).imap_unordered(abs, [-1, -2, -3])) == [1, 2, 3]


def test_a_home_in_a_dataset_is_a_failure_naming_what_precompute_takes(home_dir, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(home_dir, data / "home", ignore=shutil.ignore_patterns("artifacts"))
    summary = precompute(data, tmp_path / "out", PrecomputeParams(clips_per_scene=1, frames=4, height=32),
                         progress=False)
    failures = [json.loads(x) for x in (tmp_path / "out" / "failures.jsonl").read_text().splitlines()]
    assert summary["failed"] == 1 and summary["clips"] == 0 and [f["scene"] for f in failures] == ["home"]
    assert "a home of several panoramas" in failures[0]["error"] and "--scenes K --frames N" in failures[0]["error"]
