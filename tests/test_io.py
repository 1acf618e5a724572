"""The artifact I/O layer (panoworld/io) and check_shape: round trips, one non-finite policy, one-line errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from panoworld.core.errors import InputError
from panoworld.core.shapes import check_shape
from panoworld.io.depth_png import read_depth_png, write_depth_png
from panoworld.io.jsonio import read_json, to_jsonable, write_json
from panoworld.io.video import load_video, read_video_doc
from panoworld.io.video_writer import write_video


def test_json_non_finite_is_null_and_strict(tmp_path):
    doc = {"a": float("nan"), "b": [np.float32(1.5), np.inf, -np.inf], "c": np.arange(3), "d": np.int64(7)}
    path = write_json(tmp_path / "x.json", doc)
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    back = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert back == {"a": None, "b": [1.5, None, None], "c": [0, 1, 2], "d": 7} == read_json(path)
    assert to_jsonable(math.nan) is None
    assert read_json(tmp_path / "missing.json", default={}) == {}
    with pytest.raises(OSError):
        read_json(tmp_path / "missing.json")


def test_depth_png_unknown_is_zero_and_values_round_trip_to_the_millimetre(tmp_path):
    d = np.array([[0.0, 1.2345], [np.nan, 70.0], [np.inf, 0.001]], np.float32)
    write_depth_png(tmp_path / "d.png", d)
    back = read_depth_png(tmp_path / "d.png")
    assert back.dtype == np.float32 and back.shape == d.shape
    np.testing.assert_allclose(back, [[0, 1.234], [0, 65.535], [0, 0.001]], atol=1e-6)
    with pytest.raises(InputError, match="not a single-channel uint16 depth PNG"):
        read_depth_png(tmp_path / "nothing.png")


def test_video_json_has_one_parser_for_paths_and_frames(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (3, 8, 16, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 5, (3, 8, 16)).astype(np.float32)
    depth[0, 0, 0] = 0.0
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0, 0.1, 0.2]
    write_video(tmp_path / "v", frames, depth, poses, fps=8.0, preview=False, mcap=False)
    doc = read_video_doc(tmp_path / "v")
    assert (doc.height, doc.width, doc.num_frames, doc.fps, doc.has_depth) == (8, 16, 3, 8.0, True)
    np.testing.assert_array_equal(doc.poses, poses)
    v = load_video(tmp_path / "v")
    np.testing.assert_array_equal(v.frames, frames)
    np.testing.assert_allclose(v.depth, np.round(depth * 1000) / 1000, atol=1e-6)
    assert v.depth[0, 0, 0] == 0.0  # unknown stays 0 through the same decoder
    for i, f in enumerate(doc.depth):
        np.testing.assert_array_equal(read_depth_png(f, doc.depth_scale), v.depth[i])
    (tmp_path / "v" / "video.json").write_text(json.dumps({"height": 8, "width": 10, "frames": []}))
    with pytest.raises(InputError, match=r"video.json: frames are 10x8 \(WxH\) but ERP frames must be 2:1"):
        read_video_doc(tmp_path / "v")


@pytest.mark.parametrize("arr, spec, kw, message", [
    (np.zeros((6, 12, 1)), "H W", {}, "depth.shape=(6, 12, 1) but expected (H, W)"),
    (np.zeros((8, 15, 3)), "H W 3", {"dims": {"H": 8, "W": 16}}, "depth.shape=(8, 15, 3) but expected (8, 16, 3)"),
    (np.zeros((2, 4, 4), np.float32), "N 4 4", {"dtype": np.uint8},
     "depth.shape=(2, 4, 4) float32 but expected (N, 4, 4) uint8"),
    (np.zeros((5, 2, 3)), "... 3 3", {}, "depth.shape=(5, 2, 3) but expected (..., 3, 3)"),
    (np.zeros((2, 3)), "N N", {}, "depth.shape=(2, 3) but expected (N, N)"),
])
def test_check_shape_refuses_in_one_line(arr, spec, kw, message):
    with pytest.raises(InputError) as e:
        check_shape("depth", arr, spec, **kw)
    assert str(e.value) == message


def test_check_shape_binds_dims_across_arrays():
    dims = check_shape("rgb", np.zeros((4, 8, 3), np.uint8), "H W 3", dtype=np.uint8)
    assert dims == {"H": 4, "W": 8}
    assert check_shape("depth", np.zeros((4, 8)), "H W", dims=dims, dtype=np.floating) is dims
    check_shape("poses", np.zeros((7, 2, 4, 4)), "... 4 4")
    check_shape("any", np.zeros((3, 5)), "* 5")
    with pytest.raises(InputError, match=r"^mask.shape=\(4, 9\) but expected \(4, 8\)$"):
        check_shape("mask", np.zeros((4, 9)), "H W", dims=dims)
