"""Property-based tests (hypothesis) over user inputs: scene.yaml, trajectory files, --set values, depth arrays. Never a
traceback (only the project's one-line errors), never a corrupted artifact or cache (issue #24)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from panoworld.core.errors import PanoWorldError
from panoworld.core.limits import MAX_POSES, MAX_TRANSLATION_M
from panoworld.framework import pipeline as pl
from panoworld.framework.stage import execute_stage, load_stage
from panoworld.framework.stage_params import params_from_dict
from panoworld.io import manifest as art
from panoworld.io.trajectory import TrajectoryFileError, read_trajectory_file

FAST = settings(max_examples=int(os.environ.get("PANOWORLD_FUZZ_EXAMPLES", 25)), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                      HealthCheck.too_slow])
PIPE = pl.Pipeline.load()

numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**30, 10**30), st.booleans(),
                    st.none(), st.text(max_size=8))
json_values = st.recursive(numbers, lambda kids: st.one_of(st.lists(kids, max_size=5),
                                                           st.dictionaries(st.text(max_size=6), kids, max_size=4)),
                           max_leaves=30)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("fuzz") / "scene"
    d.mkdir()
    cv2.imwrite(str(d / "panorama.png"), np.full((16, 32, 3), 128, np.uint8))
    return d


def listing(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*"))


# ---------------------------------------------------------------- scene.yaml and --set


param_names = st.sampled_from(sorted({f"{s}.{f}" for s, n in PIPE.stages.items() for f in
                                      n.spec.params_cls.__dataclass_fields__}))


@FAST
@given(doc=st.one_of(json_values, st.dictionaries(st.sampled_from(["preset", "params"]), json_values, max_size=2),
                     st.fixed_dictionaries({"params": st.dictionaries(st.sampled_from(sorted(PIPE.stages)),
                                                                      st.dictionaries(st.text(max_size=12), numbers,
                                                                                      max_size=3), max_size=3)})),
       raw=st.one_of(st.none(), st.text(max_size=200)))
@example(doc={"params": {"asset": {"\n": None}}}, raw=None)  # a key that is a newline: one line, the key repr'd
@example(doc={"params": {"\n": {"x": 1}}}, raw=None)
def test_scene_yaml_never_tracebacks(scene_dir, doc, raw):
    cfg = scene_dir / pl.SCENE_CONFIG
    try:
        cfg.write_text(raw if raw is not None else yaml.safe_dump(doc, allow_unicode=True))
        before = listing(scene_dir)
        try:
            scene = pl.open_scene(scene_dir, PIPE)
            pl.resolve_params(PIPE, None, scene, {}, list(PIPE.order))
        except PanoWorldError as e:
            assert "\n" not in str(e).strip()
        assert listing(scene_dir) == before  # reading a scene writes nothing
    finally:
        cfg.unlink(missing_ok=True)


@FAST
@given(name=param_names, value=st.one_of(st.text(max_size=40), numbers.map(str), st.sampled_from(
    ["0", "-1", "1e-6", "nan", "inf", "-inf", "1e300", "", "[]", "{a: 1}", "hf:a/b@..", "hf:org/name//abs",
     "../../etc/passwd", "true", "0x10"])))
def test_set_values_never_traceback(scene_dir, name, value):
    before = listing(scene_dir)
    try:
        sets = pl.parse_sets([f"{name}={value}"], PIPE)
        scene = pl.open_scene(scene_dir, PIPE)
        params = pl.resolve_params(PIPE, None, scene, sets, list(PIPE.order))
        from panoworld.framework.hub import resolve as hub

        for stage in PIPE.order:
            hub.check_params_weights(params[stage], where=f"{stage}.")
    except PanoWorldError as e:
        assert "\n" not in str(e).strip()
    assert listing(scene_dir) == before


# ---------------------------------------------------------------- trajectory files


poses_like = hnp.arrays(np.float64, st.tuples(st.integers(1, 6), st.sampled_from([3, 4]), st.sampled_from([3, 4, 5])),
                        elements=st.floats(allow_nan=True, allow_infinity=True, width=64))


@FAST
@given(kind=st.sampled_from(["json-doc", "json-array", "tum", "bytes"]), doc=json_values, arr=poses_like,
       blob=st.binary(max_size=300), scale=st.sampled_from([1.0, 1e3, 1e300]))
def test_trajectory_files_never_traceback(tmp_path_factory, kind, doc, arr, blob, scale):
    path = tmp_path_factory.mktemp("traj") / ("trajectory.tum" if kind == "tum" else "trajectory.json")
    if kind == "json-doc":
        path.write_text(json.dumps({"poses": doc}))
    elif kind == "json-array":
        rigid = np.tile(np.eye(4), (len(arr), 1, 1))
        rigid[:, :3, 3] = np.nan_to_num(arr[:, 0, :3], posinf=1, neginf=-1) * scale
        path.write_text(json.dumps((rigid if arr.shape[1:] == (4, 4) else arr).tolist()))
    elif kind == "tum":
        path.write_text("\n".join(" ".join(repr(float(x)) for x in row[:8]) for row in arr.reshape(len(arr), -1)))
    else:
        path.write_bytes(blob)
    try:
        poses = read_trajectory_file(path)
    except TrajectoryFileError as e:
        assert str(path) in str(e) and "\n" not in str(e)
        return
    assert 1 <= len(poses) <= MAX_POSES and np.isfinite(poses).all()
    assert np.abs(poses[:, :3, 3]).max() <= MAX_TRANSLATION_M


# ---------------------------------------------------------------- depth arrays through the depth stage


depth_arrays = hnp.arrays(
    st.sampled_from([np.float32, np.float64, np.float16, np.int32, np.uint16, np.int8, np.bool_, np.complex64]),
    st.one_of(st.just((16, 32)), st.just((8, 16)), st.just((32, 64)), st.just((3, 16, 32)), st.just((16, 32, 2)),
              st.just((16, 16)), st.just((0, 0)), st.just((4, 8, 16))))


@settings(max_examples=int(os.environ.get("PANOWORLD_FUZZ_EXAMPLES", 20)), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(arr=depth_arrays, extreme=st.sampled_from([None, "nan", "inf", "neg", "huge", "spikes", "zeros"]))
def test_depth_arrays_never_traceback_or_corrupt_the_artifact(tmp_path_factory, arr, extreme):
    root = tmp_path_factory.mktemp("depth")
    cv2.imwrite(str(root / "panorama.png"), np.full((16, 32, 3), 100, np.uint8))
    spec = load_stage("depth")
    params = params_from_dict(spec.params_cls, {})
    out = root / "artifacts" / "depth"
    good = np.full((16, 32), 2.0, np.float32)
    np.save(root / "good.npy", good)
    execute_stage(spec, {"panorama": root / "panorama.png", "depth": root / "good.npy"}, params, out)
    before = (out / "depth.npy").read_bytes()
    a = arr.copy()
    if a.size and a.dtype.kind == "f":
        flat = a.reshape(-1)
        if extreme == "nan":
            flat[::3] = np.nan
        elif extreme == "inf":
            flat[::2] = np.inf
        elif extreme == "neg":
            flat[:] = -np.abs(flat)
        elif extreme == "huge":
            flat[:] = np.finfo(a.dtype).max
        elif extreme == "spikes":
            flat[:] = 2.0
            flat[::17] = 1e6
        elif extreme == "zeros":
            flat[:] = 0
    np.save(root / "depth.npy", a)
    try:
        manifest = execute_stage(spec, {"panorama": root / "panorama.png", "depth": root / "depth.npy"}, params, out)
    except PanoWorldError as e:
        assert "\n" not in str(e).strip()
        assert (out / "depth.npy").read_bytes() == before  # the previous artifact is untouched ...
        assert art.verify_files(out, art.read_manifest(out, "depth")) is None  # ... and still valid
        return
    assert art.verify_files(out, art.read_manifest(out, "depth")) is None
    depth = np.load(out / "depth.npy")
    valid = cv2.imread(str(out / "valid.png"), cv2.IMREAD_GRAYSCALE) > 127
    assert depth.shape == (16, 32) and np.isfinite(depth).all() and (depth[valid] > 0).all() and (depth[~valid] == 0).all()
    rec = manifest["info"]["outliers"]  # what is left is within the far threshold it applied (before the rescale)
    assert rec["max_depth_after"] is None or rec["max_depth_after"] <= rec["far_threshold"]
    shutil.rmtree(out)
