"""Hostile and odd user inputs (issue #24): each refused in one line naming the file, exit code 2, nothing written."""

from __future__ import annotations

import json
import os
import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from panoworld.core.errors import InputError
from panoworld.core.limits import MAX_PIXELS, MAX_POSES, MAX_TRAJECTORY_BYTES, LimitError, parse_json, parse_yaml
from panoworld.io.depth import read_depth, read_panorama
from panoworld.io.images import ImageInputError, check_image
from panoworld.io.trajectory import TrajectoryFileError, read_trajectory_file
from tests.test_runner import TOY, cli, toy_schemas  # noqa: F401 - toy_schemas: the shared autouse fixture


def photo(h: int = 64) -> np.ndarray:
    """A smooth BGR image (JPEG-like content: the entropy coder has real work, corrupting it matters)."""
    rng = np.random.default_rng(0)
    return cv2.GaussianBlur((rng.random((h, 2 * h, 3)) * 255).astype(np.uint8), (0, 0), 2)


def png_header_only(path: Path, w: int, h: int) -> None:
    """A PNG that claims w x h (a pixel bomb's header) and holds no pixel data."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def make_bad_image(path: Path, kind: str) -> None:
    ok, enc = cv2.imencode(path.suffix, photo())
    data = bytearray(enc.tobytes())
    if kind == "truncated":
        data = data[: len(data) // 2]
    elif kind == "corrupt":  # a few flipped bytes in the entropy-coded data: PIL and OpenCV decode it with a warning only
        rng = np.random.default_rng(1)
        for k in rng.integers(len(data) // 3, len(data) - 16, 30):
            data[k] = int(rng.integers(0, 256))
    elif kind == "garbage":  # junk before the end marker: PIL decodes it silently, libjpeg warns
        data = data[:-2] + bytes(np.random.default_rng(2).integers(0, 255, 500, dtype=np.uint8)) + data[-2:]
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("name, kind, expect", [
    ("p.jpg", "truncated", "panorama is truncated"),
    ("p.jpg", "corrupt", "panorama is corrupt"),
    ("p.jpg", "garbage", "panorama is corrupt or truncated (libjpeg: Corrupt JPEG data"),
    ("p.png", "truncated", "panorama is truncated"),
])
def test_truncated_or_corrupt_image_is_refused(tmp_path, name, kind, expect):
    path = tmp_path / name
    make_bad_image(path, kind)
    with pytest.raises(ImageInputError, match="re-export") as e:
        check_image(path, "panorama")
    assert expect in str(e.value) and str(path) in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(InputError):  # the depth stage reads through the same reader
        read_panorama(path)


def test_intact_images_pass_and_report_size(tmp_path):
    for name in ("p.jpg", "p.png"):
        cv2.imwrite(str(tmp_path / name), photo())
        info = check_image(tmp_path / name)
        assert info.oriented == (128, 64)
        assert read_panorama(tmp_path / name).shape == (64, 128, 3)


def test_a_remembered_check_skips_the_decode_until_the_file_changes(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    path = tmp_path / "p.jpg"
    cv2.imwrite(str(path), photo())
    first = check_image(path, "panorama", remember=True)
    import PIL.Image

    def no_decode(*a, **k):
        raise AssertionError("decoded again")
    monkeypatch.setattr(PIL.Image, "open", no_decode)
    assert check_image(path, "panorama", remember=True) == first  # same stat: no decode
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    make_bad_image(path, "garbage")  # rewritten in place: a new mtime, so checked in full and refused
    with pytest.raises(ImageInputError, match="corrupt or truncated"):
        check_image(path, "panorama", remember=True)
    with pytest.raises(ImageInputError):  # a refused check is never remembered
        check_image(path, "panorama", remember=True)


def test_pixel_bomb_is_named_with_the_limit_before_decoding(tmp_path):
    path = tmp_path / "panorama.png"
    png_header_only(path, 20000, 10000)
    with pytest.raises(ImageInputError, match=r"pixel bomb: 20000x10000 = 200 Mpx exceeds the limit of 134 Mpx"):
        check_image(path, "panorama")
    assert 20000 * 10000 > MAX_PIXELS >= 16384 * 8192


@pytest.mark.parametrize("kind", ["truncated", "corrupt", "bomb"])
def test_runner_refuses_bad_panorama_in_one_line_writing_nothing(tmp_path, kind):
    d = tmp_path / "s"
    d.mkdir()
    if kind == "bomb":
        png_header_only(d / "panorama.png", 20000, 10000)
    else:
        make_bad_image(d / "panorama.jpg", kind)
    before = sorted(p.name for p in d.iterdir())
    out = cli("run", str(d), "--pipeline", str(TOY / "pipeline.yaml"))
    assert out.returncode == 2, out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and "panorama" in out.stderr and str(d) in out.stderr
    assert sorted(p.name for p in d.iterdir()) == before  # no artifacts/, no lock, no logs


# ---------------------------------------------------------------- limits (group 2)


def npy_claiming(path: Path, shape, dtype="<f4") -> None:
    """A .npy whose header claims `shape` but which holds 16 bytes of data."""
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": dtype, "fortran_order": False, "shape": shape})
        f.write(bytes(16))


def test_deep_json_and_yaml_are_one_line_refusals():
    deep = "[" * 200_000 + "]" * 200_000
    with pytest.raises(LimitError, match="t.json: JSON nested too deep"):
        parse_json(deep, "t.json")
    with pytest.raises(LimitError, match="nested deeper than 4"):
        parse_json("[[[[[1]]]]]", "t.json", max_nesting=4)
    assert parse_json('{"poses": [[[1, 0], [0, 1]]]}', "t.json", max_nesting=4) == {"poses": [[[1, 0], [0, 1]]]}
    with pytest.raises(LimitError, match="s.yaml: YAML nested"):
        parse_yaml("a: " + "[" * 5000 + "]" * 5000, "s.yaml")


def test_npy_header_is_checked_before_allocation(tmp_path):
    npy_claiming(tmp_path / "bomb.npy", (100_000, 200_000))
    with pytest.raises(LimitError, match=r"bomb.npy: depth array header claims shape \(100000, 200000\) = 2e\+10 values"):
        read_depth(tmp_path / "bomb.npy")
    npy_claiming(tmp_path / "short.npy", (64, 128))
    with pytest.raises(InputError, match="short.npy: depth array is truncated"):
        read_depth(tmp_path / "short.npy")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="obj.npy: depth array has dtype object"):
        read_depth(tmp_path / "obj.npy")
    d = np.random.default_rng(0).uniform(1, 5, (32, 64)).astype(np.float32)
    np.save(tmp_path / "chw.npy", np.stack([d, d * 0, d * 0]))  # channel-first (3, H, W): the first plane
    np.testing.assert_array_equal(read_depth(tmp_path / "chw.npy"), d)
    np.save(tmp_path / "odd.npy", np.zeros((8, 16, 32), np.float32))
    with pytest.raises(InputError, match=r"depth has shape \(8, 16, 32\) but expected \(H, W\)"):
        read_depth(tmp_path / "odd.npy")


def write_traj(path: Path, poses) -> Path:
    path.write_text(json.dumps({"poses": np.asarray(poses).tolist()}))
    return path


@pytest.mark.parametrize("case, expect", [
    ("many", f"{MAX_POSES + 1} poses, over the limit of {MAX_POSES}"),
    ("far", "pose 1 is 1e+300 m from the camera, beyond the 1000 m limit"),
    ("deep", "JSON nested too deep"),
    ("nan", "pose 1 has NaN or inf entries"),
    ("huge-file", "over the limit of 16 MiB"),
    ("tum-many", f"{MAX_POSES + 1} poses, over the limit of {MAX_POSES}"),
])
def test_user_trajectory_limits(tmp_path, case, expect):
    path = tmp_path / ("trajectory.tum" if case == "tum-many" else "trajectory.json")
    eye = np.tile(np.eye(4), (2, 1, 1))
    if case == "many":
        write_traj(path, np.tile(np.eye(4), (MAX_POSES + 1, 1, 1)))
    elif case == "far":
        eye[1, 0, 3] = 1e300
        write_traj(path, eye)
    elif case == "deep":
        path.write_text('{"poses": ' + "[" * 200_000 + "]" * 200_000 + "}")
    elif case == "nan":
        eye[1, 2, 3] = np.nan
        write_traj(path, eye)
    elif case == "huge-file":
        path.write_text(" " * (MAX_TRAJECTORY_BYTES + 1))
    else:
        path.write_text("".join(f"{i} 0 0 0 0 0 0 1\n" for i in range(MAX_POSES + 1)))
    with pytest.raises(TrajectoryFileError, match=re.escape(expect)) as e:
        read_trajectory_file(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def tiny_scene(d: Path) -> Path:
    d.mkdir()
    cv2.imwrite(str(d / "panorama.png"), photo(16))
    return d


@pytest.mark.parametrize("case, expect", [
    ("artifacts-file", "artifacts: exists but is not a directory"),
    ("artifacts-dangling", "artifacts: a dangling symbolic link"),
    ("trajectory-many", "poses, over the limit of 10000"),
    ("trajectory-deep", "JSON nested too deep"),
    ("depth-header", "depth array header claims shape (100000, 200000)"),
    ("yaml-deep", "scene.yaml: YAML nested"),
])
def test_runner_refuses_scene_inputs_in_one_line_writing_nothing(tmp_path, case, expect):
    d = tiny_scene(tmp_path / "s")
    if case == "artifacts-file":
        (d / "artifacts").write_text("oops")
    elif case == "artifacts-dangling":
        (d / "artifacts").symlink_to(tmp_path / "gone")
    elif case == "trajectory-many":
        write_traj(d / "trajectory.json", np.tile(np.eye(4), (MAX_POSES + 1, 1, 1)))
    elif case == "trajectory-deep":
        (d / "trajectory.json").write_text("[" * 200_000 + "]" * 200_000)
    elif case == "depth-header":
        npy_claiming(d / "depth.npy", (100_000, 200_000))
    else:
        (d / "scene.yaml").write_text("params: " + "[" * 100_000 + "]" * 100_000)
    before = sorted(p.name for p in d.iterdir())
    out = cli("run", str(d))
    assert out.returncode == 2, out.stderr
    assert expect in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert sorted(p.name for p in d.iterdir()) == before


# ---------------------------------------------------------------- checkpoints and hub ids (group 3)


class _Planted:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.mkdir, (str(self.marker),))


def test_resume_never_unpickles_code(tmp_path):
    import torch

    from panoworld.tools.train.common import Checkpointer, TrainConfigError

    ckpt = Checkpointer(tmp_path / "run")
    ckpt.dir.mkdir(parents=True)
    marker = tmp_path / "pwned"
    torch.save({"step": 1, "rng": _Planted(marker), "extra": {}, "objects": {}}, ckpt.dir / "step_00000001.pt")
    with pytest.raises(TrainConfigError, match="step_00000001.pt: not a checkpoint of tensors and plain state"):
        ckpt.restore({})
    assert not marker.exists()


def test_rng_state_round_trips_through_a_weights_only_checkpoint(tmp_path):
    import random

    import torch

    from panoworld.tools.train.common import Checkpointer

    class Box:  # an object with state, as the trainers checkpoint them
        def __init__(self):
            self.w = torch.zeros(3)

        def state_dict(self):
            return {"w": self.w}

        def load_state_dict(self, s):
            self.w = s["w"]

    ckpt = Checkpointer(tmp_path / "run")
    box = Box()
    box.w = torch.arange(3.0)
    random.gauss(0, 1)  # a cached gaussian in the python state
    np.random.normal()
    ckpt.save(7, {"box": box}, {"phase": "x"})
    want = (random.random(), random.gauss(0, 1), np.random.random(), np.random.normal(), torch.rand(2))
    fresh = Box()
    step, extra = ckpt.restore({"box": fresh})
    got = (random.random(), random.gauss(0, 1), np.random.random(), np.random.normal(), torch.rand(2))
    assert step == 7 and extra == {"phase": "x"} and torch.equal(fresh.w, torch.arange(3.0))
    assert got[:4] == want[:4] and torch.equal(got[4], want[4])


@pytest.mark.parametrize("spec", ["hf:a/b@..", "hf:org/name//abs"])
def test_runner_refuses_bad_hf_ids_in_one_line(tmp_path, spec):
    d = tiny_scene(tmp_path / "s")
    out = cli("run", str(d), "--set", f"depth.weights={spec}")
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert f"{spec}: expected hf:ORG/NAME[@REVISION][/PATH]" in out.stderr
    assert sorted(p.name for p in d.iterdir()) == ["panorama.png"]


@pytest.mark.parametrize("setting, expect", [
    ("mesh.stride=0", "mesh.stride"), ("mesh.stride=-1", "mesh.stride"), ("navmesh.cell_m=0", "navmesh.cell_m"),
    ("navmesh.cell_m=1e-6", "navmesh.cell_m"), ("mesh.max_edge_ratio=nan", "mesh.max_edge_ratio"),
    ("navmesh.agent_radius_m=-1", "navmesh.agent_radius_m"), ("trajectory.frames=1000000", "trajectory.frames"),
    ("conditions.height=100000", "conditions.height"),
])
def test_runner_refuses_out_of_range_params_in_one_line(tmp_path, setting, expect):
    d = tiny_scene(tmp_path / "s")
    out = cli("run", str(d), "--set", setting)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert expect in out.stderr and "must be" in out.stderr, out.stderr
    assert sorted(p.name for p in d.iterdir()) == ["panorama.png"]
