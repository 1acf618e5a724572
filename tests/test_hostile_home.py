"""Hostile and odd inputs, round two (issue #48): the home layout, outputs a user points us at, and the corners. Each
refusal is one line with the documented exit code, no traceback, within 2 s whatever the file's size, writing nothing
outside the scene and corrupting nothing."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from panoworld.core.errors import InputError
from panoworld.core.limits import MAX_POSES_JSON_BYTES, MIN_HEIGHT, LimitError, parse_yaml
from panoworld.framework import execute
from panoworld.framework import pipeline as pl
from panoworld.io import manifest as art
from panoworld.io.safe_write import OutputPathError, atomic_output, check_output_dir, inside, write_text_atomic
from panoworld.register.inputs import find_home_files
from panoworld.register.pair_select import (
    ALL_PAIRS_UP_TO,
    PAIRS_PER_PANORAMA,
    appearance_descriptor,
    bridge_pairs,
    candidate_pairs,
)
from tests.test_hostile_inputs import npy_claiming, png_header_only
from tests.test_runner import REPO, TOY, cli, toy_schemas  # noqa: F401 - toy_schemas: the shared autouse fixture

PIPE = pl.Pipeline.load()


def pano(h: int = 32, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur((rng.random((h, 2 * h, 3)) * 255).astype(np.uint8), (0, 0), 2)


def make_home(d: Path, names=("a", "b", "c"), *, depths: bool = True, poses: bool = True) -> Path:
    """A home of small panoramas (NAME.png), constant 2 m depths and capture points 0.5 m apart along x."""
    (d / "panoramas").mkdir(parents=True)
    if depths:
        (d / "depths").mkdir()
    doc = {}
    for i, n in enumerate(names):
        cv2.imwrite(str(d / "panoramas" / f"{n}.png"), pano(seed=i))
        if depths:
            np.save(d / "depths" / f"{n}.npy", np.full((32, 64), 2.0, np.float32))
        T = np.eye(4)
        T[0, 3] = 0.5 * i
        doc[n] = T.tolist()
    if poses:
        (d / "poses.json").write_text(json.dumps(doc))
    return d


def listing(d: Path) -> dict[str, int]:
    """{relative path: size} of everything under d (a refusal must leave it exactly so)."""
    return {str(p.relative_to(d)): (p.lstat().st_size if not p.is_dir() else -1) for p in sorted(d.rglob("*"))}


def refused(out: subprocess.CompletedProcess, expect: str, code: int = 2) -> str:
    err = out.stderr.strip()
    assert out.returncode == code, (out.returncode, out.stderr)
    assert len(err.splitlines()) == 1 and "Traceback" not in err and expect in err, err
    return err


def open_within_2s(d: Path) -> None:
    """The runner's scene checks (all of them run before anything is hashed or run) refuse d within 2 s, hashing
    nothing (bench/bench_refusals.py prints the times)."""
    def no_hash(*a, **k):
        raise AssertionError("a user file was hashed before it was checked")
    t0 = time.perf_counter()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(art, "file_digest", no_hash)
        with pytest.raises(InputError):
            pl.open_scene(d, PIPE)
    assert time.perf_counter() - t0 < 2.0


# ---------------------------------------------------------------- 1: panorama names


@pytest.mark.parametrize("names, bad, expect", [
    (["-a", "..", "b"], "-a.png", "is not a safe name"),  # panoramas/{-a,...,b}.png of the issue
    (["..", "b"], "...png", "'..' is not a safe name"),
    ([".", "b"], "..png", "'.' is not a safe name"),
    (["a b", "b"], "a b.png", "is not a safe name"),
    ([".hidden", "b"], ".hidden.png", "is not a safe name"),
])
def test_unsafe_panorama_names_are_refused_naming_the_file(tmp_path, names, bad, expect):
    d = make_home(tmp_path / "h", names, poses=False)
    before = listing(d)
    out = cli("run", str(d), "--until", "register")
    err = refused(out, expect)
    assert str(d / "panoramas" / bad) in err
    assert listing(d) == before  # no artifacts/, the depths of the other panoramas untouched
    open_within_2s(d)


@pytest.mark.parametrize("files, expect", [(["a.png", "a.jpg", "b.png"], "is also a.jpg"),
                                           (["a.png", "A.png", "b.png"], "is also A.png")])
def test_two_files_of_one_name_are_refused_not_dropped(tmp_path, files, expect):
    d = tmp_path / "h"
    (d / "panoramas").mkdir(parents=True)
    for i, f in enumerate(files):
        cv2.imwrite(str(d / "panoramas" / f), pano(seed=i))
    if len(list((d / "panoramas").iterdir())) < len(files):  # a case-insensitive file system holds one of them
        pytest.skip("case-insensitive file system")
    refused(cli("run", str(d)), expect)
    assert not (d / "artifacts").exists()


def test_output_paths_are_checked_to_stay_inside_their_artifact(tmp_path):
    assert inside(tmp_path, "a", "b.png") == tmp_path / "a" / "b.png"
    for bad in ("..", "../x", "/etc/passwd", "a/../../x"):
        with pytest.raises(InputError, match="leaves"):
            inside(tmp_path / "art", bad)
    d = make_home(tmp_path / "h", ["b", "x"], poses=False)
    os.rename(d / "panoramas" / "x.png", d / "panoramas" / "...png")
    with pytest.raises(InputError, match="not a safe name"):  # the depth stage run by hand lists the home the same way
        find_home_files(d / "panoramas", d / "depths")


# ---------------------------------------------------------------- 2: outputs a user names


def special_files(tmp_path: Path) -> dict[str, Path]:
    """A FIFO, a character device node (the null device's numbers, in tmp_path), a symbolic link to a file outside,
    a directory and a dangling link: none may be replaced by a regular file."""
    out = {}
    out["fifo"] = tmp_path / "fifo"
    os.mkfifo(out["fifo"])
    if os.geteuid() == 0:
        out["device"] = tmp_path / "null"
        os.mknod(out["device"], 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    target = tmp_path / "victim.txt"
    target.write_text("keep me")
    out["symlink"] = tmp_path / "link.html"
    out["symlink"].symlink_to(target)
    out["dangling"] = tmp_path / "dangling.html"
    out["dangling"].symlink_to(tmp_path / "nowhere" / "x")
    out["directory"] = tmp_path / "adir"
    out["directory"].mkdir()
    return out


def test_report_out_refuses_devices_fifos_links_and_directories(tmp_path):
    scene = tmp_path / "s"
    scene.mkdir()
    cv2.imwrite(str(scene / "panorama.png"), pano(16))
    for kind, path in special_files(tmp_path).items():
        mode = path.lstat().st_mode
        t0 = time.perf_counter()
        out = cli("report", str(scene), "--out", str(path))
        assert time.perf_counter() - t0 < 30  # (a FIFO opened for writing would block forever)
        refused(out, f"{path}: is ")
        assert path.lstat().st_mode == mode, kind  # still what it was
    assert (tmp_path / "victim.txt").read_text() == "keep me"
    assert not [p for p in tmp_path.iterdir() if p.name.endswith((".tmp", ".part"))]
    assert not (scene / "artifacts").exists()


@pytest.mark.parametrize("verb", [["weights", "fetch", "depth-anything-v2-small", "--to"], ["precompute", "DATA", "--out"],
                                  ["train", "video", "--data", "DATA", "--out"], ["synth", "--seed", "0"]])
def test_other_output_paths_refuse_what_is_not_a_directory(tmp_path, verb, capsys):
    """The FIFO through the real CLI (a FIFO opened for writing would block), the others through runner.main."""
    import runner

    (tmp_path / "DATA").mkdir()
    (tmp_path / "specials").mkdir()
    specials = special_files(tmp_path / "specials")
    for kind in ("fifo", "symlink", "device"):
        if kind not in specials:
            continue
        path = specials[kind]
        mode = path.lstat().st_mode
        args = [str(tmp_path / "DATA") if a == "DATA" else a for a in verb] + [str(path)]
        if kind == "fifo":
            refused(cli(*args), f"{path}: is ")
        else:
            code = runner.main(args)
            refused(subprocess.CompletedProcess(args, code, "", capsys.readouterr().err), f"{path}: is ")
        assert path.lstat().st_mode == mode


def test_atomic_output_uses_unpredictable_exclusive_temporaries(tmp_path, monkeypatch):
    target = tmp_path / "r.html"
    write_text_atomic(target, "one")
    seen = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (seen.append(Path(a).name), real(a, b)))
    write_text_atomic(target, "two")
    write_text_atomic(target, "three")
    assert target.read_text() == "three" and len(set(seen)) == 2 and all(s.startswith(".r.html.") for s in seen)
    # A planted link where an old-style temporary would go is never written through.
    (tmp_path / "r.html.tmp").symlink_to(tmp_path / "victim")
    with pytest.raises(RuntimeError), atomic_output(target, "w") as f:
        f.write("half")
        raise RuntimeError("killed mid-write")
    assert target.read_text() == "three" and not (tmp_path / "victim").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.html", "r.html.tmp"]
    with pytest.raises(OutputPathError, match="is a FIFO"):
        os.mkfifo(tmp_path / "f")
        write_text_atomic(tmp_path / "f", "x")
    with pytest.raises(OutputPathError, match="not a directory"):
        check_output_dir(tmp_path / "r.html" / "sub")


# ---------------------------------------------------------------- 3: YAML alias bombs


def alias_bomb(levels: int) -> str:
    text = "a: &a [x, x, x, x, x, x, x, x, x]\n"
    prev = "a"
    for i in range(1, levels):
        name = f"l{i}"
        text += f"{name}: &{name} [{', '.join(['*' + prev] * 9)}]\n"
        prev = name
    return text


def test_yaml_alias_bomb_is_refused_before_it_is_walked(tmp_path):
    t0 = time.perf_counter()
    with pytest.raises(LimitError, match="aliases are expanded"):
        parse_yaml(alias_bomb(9), "s.yaml")
    with pytest.raises(LimitError, match="nested deeper than 32 levels .or recursive"):
        parse_yaml("a: &a [1, *a]", "s.yaml")
    assert time.perf_counter() - t0 < 2.0
    assert parse_yaml("a: &a [1, 2]\nb: *a\n", "s.yaml") == {"a": [1, 2], "b": [1, 2]}  # plain aliases still work
    d = tmp_path / "s"
    d.mkdir()
    cv2.imwrite(str(d / "panorama.png"), pano(16))
    (d / "scene.yaml").write_text(alias_bomb(9))
    assert len(alias_bomb(9)) < 1024
    for args in (["run", str(d)], ["run", str(d), "--dry-run"], ["status", str(d)]):
        refused(cli(*args), "scene.yaml: YAML holds over")
    assert sorted(p.name for p in d.iterdir()) == ["panorama.png", "scene.yaml"]
    (d / "scene.yaml").write_text("params: &p [" + ", ".join(["*q"] * 1) + "]\nq: &q [1]\n")
    refused(cli("status", str(d)), "scene.yaml")


# ---------------------------------------------------------------- 4: checked before hashed; strays ignored


def sparse_npy(path: Path, shape=(100_000, 200_000)) -> None:
    """A .npy whose header claims shape and whose size matches it (80 GB for the default), stored sparse."""
    npy_claiming(path, shape)
    with open(path, "r+b") as f:
        f.truncate(128 + int(np.prod(shape)) * 4)


def test_a_huge_sparse_home_depth_is_refused_before_it_is_hashed(tmp_path):
    d = make_home(tmp_path / "h")
    sparse_npy(d / "depths" / "b.npy")
    assert (d / "depths" / "b.npy").stat().st_size > 7e10
    open_within_2s(d)
    refused(cli("run", str(d)), "b.npy: depth array header claims shape (100000, 200000)")
    assert not (d / "artifacts").exists()


def test_stray_files_are_ignored_by_the_digest_and_reported(tmp_path):
    d = make_home(tmp_path / "h")
    first = cli("run", str(d), "--until", "depth")
    assert first.returncode == 0, first.stderr
    (d / "panoramas" / "notes.txt").write_text("taken on a Sunday")
    (d / "depths" / "README").write_text("metres")
    (d / "panoramas" / ".DS_Store").write_bytes(b"\0" * 10)
    (d / "panoramas" / "._a.png").write_bytes(b"\0\5\26\7" + b"\0" * 80)  # a Mac's AppleDouble file beside a.png
    (d / "depths" / "._a.npy").write_bytes(b"\0\5\26\7" + b"\0" * 80)
    again = cli("run", str(d), "--until", "depth")
    assert again.returncode == 0, again.stderr
    assert re.search(r"^depth +cached +up to date", again.stdout, re.M), again.stdout
    assert "note: ignored panoramas/notes.txt: not a panorama" in again.stderr
    assert "note: ignored depths/README" in again.stderr and "note: ignored panoramas/notes.txt" in again.stdout
    assert "note: ignored panoramas/._a.png: a Mac's metadata file (AppleDouble)" in again.stderr
    assert "note: ignored depths/._a.npy: a Mac's metadata file" in again.stderr


def test_a_depth_or_mask_of_no_panorama_is_refused(tmp_path):
    d = make_home(tmp_path / "h")
    np.save(d / "depths" / "zz.npy", np.full((32, 64), 2.0, np.float32))
    refused(cli("run", str(d)), "zz.npy: depth of no panorama")
    (d / "depths" / "zz.npy").unlink()
    (d / "rig_masks").mkdir()
    cv2.imwrite(str(d / "rig_masks" / "q.png"), np.zeros((32, 64), np.uint8))
    refused(cli("run", str(d)), "q.png: rig mask of no panorama")
    assert not (d / "artifacts").exists()


# ---------------------------------------------------------------- 5: rig masks and EXR headers


def exr_claiming(path: Path, w: int, h: int) -> None:
    """An OpenEXR file whose header's dataWindow claims w x h, with no pixel data."""
    def attr(name: bytes, kind: bytes, value: bytes) -> bytes:
        return name + b"\0" + kind + b"\0" + len(value).to_bytes(4, "little") + value
    window = b"".join(v.to_bytes(4, "little", signed=True) for v in (0, 0, w - 1, h - 1))
    path.write_bytes(b"\x76\x2f\x31\x01" + (2).to_bytes(4, "little") + attr(b"dataWindow", b"box2i", window)
                     + attr(b"displayWindow", b"box2i", window) + b"\0" + bytes(64))


@pytest.mark.parametrize("case, expect", [
    ("single-mask-bomb", "rig_mask.png: pixel bomb: 30000x15000"),
    ("home-mask-bomb", "b.png: pixel bomb: 30000x15000"),
    ("single-exr-bomb", "depth.exr: EXR depth is 20000x10000 = 200 Mpx, beyond the limit"),
    ("home-exr-bomb", "c.exr: EXR depth is 20000x10000 = 200 Mpx, beyond the limit"),
    ("exr-not-exr", "depth.exr: cannot read the EXR depth (not an OpenEXR file)"),
    ("home-mask-small", "a.png: rig mask is 4x2, below the minimum of 16x8"),
])
def test_rig_masks_and_exr_depths_are_checked_from_their_headers(tmp_path, case, expect):
    if case.startswith("home"):
        d = make_home(tmp_path / "h")
        (d / "rig_masks").mkdir()
        if case == "home-mask-bomb":
            png_header_only(d / "rig_masks" / "b.png", 30000, 15000)
        elif case == "home-mask-small":
            cv2.imwrite(str(d / "rig_masks" / "a.png"), np.zeros((2, 4), np.uint8))
        else:
            (d / "depths" / "c.npy").unlink()
            exr_claiming(d / "depths" / "c.exr", 20000, 10000)
    else:
        d = tmp_path / "s"
        d.mkdir()
        cv2.imwrite(str(d / "panorama.png"), pano(16))
        if case == "single-mask-bomb":
            png_header_only(d / "rig_mask.png", 30000, 15000)
        elif case == "single-exr-bomb":
            exr_claiming(d / "depth.exr", 20000, 10000)
        else:
            (d / "depth.exr").write_bytes(b"P6 not an exr at all")
    before = listing(d)
    refused(cli("run", str(d)), expect)
    assert listing(d) == before
    open_within_2s(d)


def test_exr_header_gives_the_size_of_a_real_exr(tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR")
    from panoworld.core.limits import exr_header

    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"Z": np.ones((20, 40), np.float32)}) as f:
        f.write(str(tmp_path / "d.exr"))
    assert exr_header(tmp_path / "d.exr") == (40, 20)
    exr_claiming(tmp_path / "c.exr", 64, 32)
    assert exr_header(tmp_path / "c.exr") == (64, 32)


def test_a_truncated_exr_depth_is_refused_before_any_panorama_is_worked_on(tmp_path, monkeypatch):
    """The last panorama's EXR depth cut short: `runner.py run` refuses the home in one line naming the file, before
    anything is written (its header alone is intact). A file that passed is not decoded again."""
    OpenEXR = pytest.importorskip("OpenEXR")
    from panoworld.io import images

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    d = make_home(tmp_path / "h")
    exr = d / "depths" / "c.exr"
    (d / "depths" / "c.npy").unlink()
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"Z": np.random.default_rng(0).uniform(1, 3, (32, 64)).astype(np.float32)}) as f:
        f.write(str(exr))
    whole = exr.read_bytes()
    assert images.check_depth_file(exr) == (64, 32)
    decoded = []
    monkeypatch.setattr(images, "read_exr", lambda p: decoded.append(p))
    assert images.check_depth_file(exr) == (64, 32) and not decoded  # remembered by path, size, mtime and inode
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    exr.write_bytes(whole[:len(whole) * 3 // 4])
    before = listing(d)
    refused(cli("run", str(d)), "c.exr: cannot read the EXR depth, corrupt or truncated")
    assert listing(d) == before
    open_within_2s(d)


def test_a_home_of_one_panorama_builds_the_scene_of_that_panorama(tmp_path):
    """panoramas/ with a single panorama (a converted dataset's home of one capture) runs like SCENE/panorama.png with
    its depth: the same Gaussians, byte for byte."""
    d = make_home(tmp_path / "h", names=("a",), poses=False)
    s = tmp_path / "s"
    s.mkdir()
    shutil.copy(d / "panoramas" / "a.png", s / "panorama.png")
    shutil.copy(d / "depths" / "a.npy", s / "depth.npy")
    for scene in (d, s):
        out = cli("run", str(scene), "--preset", "ci-tiny")
        assert out.returncode == 0, out.stderr[-2000:]
    placed = json.loads((d / "artifacts" / "register" / "registration.json").read_text())["panoramas"]
    assert placed == {"a": {"registered": True, "source": "estimated", "parent": None}}
    ply = [(x / "artifacts" / "gaussians" / "gaussians.ply").read_bytes() for x in (d, s)]
    assert ply[0] == ply[1]
    empty = make_home(tmp_path / "empty", names=())
    refused(cli("run", str(empty)), "found no panorama; put NAME.png/.jpg there")
    (empty / "panoramas" / "floor1").mkdir()
    cv2.imwrite(str(empty / "panoramas" / "a.webp"), pano())
    refused(cli("run", str(empty)), "found no panorama among a.webp, floor1/; put NAME.png/.jpg there, at its top level")


# ---------------------------------------------------------------- 6: poses.json


def write_poses(d: Path, edit) -> None:
    doc = json.loads((d / "poses.json").read_text())
    edit(doc)
    (d / "poses.json").write_text(json.dumps(doc))


def far(doc, metres):
    doc["c"][0][3] = metres


@pytest.mark.parametrize("case, expect", [
    ("deep", "poses.json: JSON nested"),
    ("far-1e12", "capture point of 'c' is 1e+12 m from 'a''s, beyond the 1000 m limit"),
    ("far-2km", "capture point of 'c' is 2e+03 m from 'a''s"),
    ("huge", f"over the limit of {MAX_POSES_JSON_BYTES // 2**20} MiB"),
    ("strings", "pose of 'b' is not a 4x4 matrix of numbers"),
    ("booleans", "pose of 'b' is not a 4x4 matrix of numbers"),
    ("nan", "pose of 'b' has NaN or infinite entries"),
    ("unknown", "poses for 'zz' but no such panoramas"),
])
def test_poses_json_is_checked_with_limits_before_anything_runs(tmp_path, case, expect):
    d = make_home(tmp_path / "h")
    if case == "deep":
        (d / "poses.json").write_text('{"a": ' + "[" * 100_000 + "]" * 100_000 + "}")
    elif case == "far-1e12":
        write_poses(d, lambda doc: far(doc, 1e12))
    elif case == "far-2km":
        write_poses(d, lambda doc: far(doc, 2000.0))
    elif case == "huge":
        (d / "poses.json").write_text("{" + " " * (MAX_POSES_JSON_BYTES + 10) + "}")
    elif case == "strings":
        write_poses(d, lambda doc: doc.update(b=[[str(x) for x in r] for r in doc["b"]]))
    elif case == "booleans":
        write_poses(d, lambda doc: doc.update(b=[[True, False, False, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
    elif case == "nan":
        (d / "poses.json").write_text((d / "poses.json").read_text().replace('"b": [[1.0', '"b": [[NaN', 1))
    else:
        write_poses(d, lambda doc: doc.update(zz=doc["a"]))
    before = listing(d)
    refused(cli("run", str(d)), expect)
    assert listing(d) == before  # refused before the depth stage ran
    open_within_2s(d)


# ---------------------------------------------------------------- 7: minimum sizes


@pytest.mark.parametrize("case, expect", [
    ("panorama-2x1", "panorama.png: panorama is 2x1, below the minimum of 16x8"),
    ("depth-1x2", "depth.npy: depth is 2x1, below the minimum of 16x8"),
    ("home-panorama", "b.png: panorama is 4x2, below the minimum"),
])
def test_images_below_the_minimum_size_are_refused(tmp_path, case, expect):
    if case == "home-panorama":
        d = make_home(tmp_path / "h")
        cv2.imwrite(str(d / "panoramas" / "b.png"), pano(2))
    else:
        d = tmp_path / "s"
        d.mkdir()
        cv2.imwrite(str(d / "panorama.png"), pano(1 if case == "panorama-2x1" else 16))
        if case == "depth-1x2":
            np.save(d / "depth.npy", np.full((1, 2), 2.0, np.float32))
    refused(cli("run", str(d)), expect)
    assert not (d / "artifacts").exists()
    assert MIN_HEIGHT == 8


def test_read_depth_refuses_a_tiny_depth(tmp_path):
    from panoworld.io.depth import read_depth

    np.save(tmp_path / "d.npy", np.ones((2, 4), np.float32))
    with pytest.raises(LimitError, match="below the minimum"):
        read_depth(tmp_path / "d.npy")


# ---------------------------------------------------------------- 8: environment errors


def test_a_file_where_the_logs_folder_must_be_is_one_line(tmp_path):
    d = tmp_path / "s"
    d.mkdir()
    cv2.imwrite(str(d / "panorama.png"), pano(8)[:, :16])
    (d / "artifacts").mkdir()
    (d / "artifacts" / "logs").write_text("not a folder")
    err = refused(cli("run", str(d), "--pipeline", str(TOY / "pipeline.yaml")), "logs")
    assert "a file is where a folder must be" in err
    assert (d / "artifacts" / "logs").read_text() == "not a folder"


@pytest.mark.parametrize("code, expect, exit_code", [(errno.ENOSPC, "the disk is full", 1),
                                                      (errno.EROFS, "read-only", 2), (errno.EACCES, "permission", 2)])
def test_environment_errors_are_one_line_without_traceback(tmp_path, monkeypatch, capsys, code, expect, exit_code):
    import runner

    def boom(*a, **k):
        raise OSError(code, os.strerror(code), str(tmp_path / "s" / "artifacts" / "x"))
    monkeypatch.setattr(pl, "run", boom)
    (tmp_path / "s").mkdir()
    assert runner.main(["run", str(tmp_path / "s")]) == exit_code
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expect in err and str(tmp_path / "s") in err


def readonly(d: Path, *args: str) -> subprocess.CompletedProcess:
    """runner.py ARGS with d bind-mounted read-only in a private mount namespace (skips where that is not allowed)."""
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True)
    if shutil.which("unshare") is None or probe.returncode:
        pytest.skip("no private mount namespace here (unshare -m)")
    env = dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas"))
    script = f'mount --bind "{d}" "{d}" && mount -o remount,ro,bind "{d}" && exec "$@"'
    return subprocess.run(["unshare", "-m", "sh", "-c", script, "sh", sys.executable, str(REPO / "runner.py"), *args],
                          capture_output=True, text=True, env=env, cwd=REPO)


def test_a_read_only_scene_reports_up_to_date_stages_and_refuses_others_in_one_line(tmp_path):
    from tests.toy.common import toy_scene

    d = toy_scene(tmp_path)
    assert cli("run", str(d), "--pipeline", str(TOY / "pipeline.yaml")).returncode == 0
    before = listing(d)
    ok = readonly(d, "run", str(d), "--pipeline", str(TOY / "pipeline.yaml"))
    assert ok.returncode == 0 and "Traceback" not in ok.stderr, ok.stderr
    assert ok.stdout.count("cached") == 4
    bad = readonly(d, "run", str(d), "--pipeline", str(TOY / "pipeline.yaml"), "--set", "c.n=5")
    assert bad.returncode == 2 and "Traceback" not in bad.stderr, bad.stderr
    assert "read-only" in bad.stderr.strip().splitlines()[-1]  # after the live lines of the cached stages
    assert listing(d) == before
    (tmp_path / "fresh").mkdir()
    fresh = toy_scene(tmp_path / "fresh")
    refused(readonly(fresh, "run", str(fresh), "--pipeline", str(TOY / "pipeline.yaml")), "read-only")


# ---------------------------------------------------------------- 9: view bind failures


@pytest.mark.parametrize("args, expect", [(["--port", "99999"], "--port 99999: expected a TCP port in 1..65535"),
                                          (["--host", "no.such.host.invalid"], "--host no.such.host.invalid: cannot "),
                                          (["--host", "192.0.2.1"], "--host 192.0.2.1: cannot listen")])
def test_view_bind_failures_are_one_line_and_exit(tmp_path, args, expect):
    (tmp_path / "s" / "artifacts").mkdir(parents=True)
    t0 = time.perf_counter()
    out = cli("view", str(tmp_path / "s"), *args, timeout=60)
    assert time.perf_counter() - t0 < 30
    refused(out, expect)


def test_check_bind_answers_within_2s():
    from panoworld.tools.viewer.app import check_bind

    t0 = time.perf_counter()
    for host, port in (("no.such.host.invalid", 8080), ("127.0.0.1", 0), ("192.0.2.1", 8080)):
        with pytest.raises(InputError):
            check_bind(host, port)
    check_bind("127.0.0.1", 8080)
    assert time.perf_counter() - t0 < 6.0  # three refusals, each within 2 s


# ---------------------------------------------------------------- 10: the lock and leftovers


def wait_for(pred, timeout=60.0):
    deadline = time.time() + timeout
    while time.time() < deadline and not pred():
        time.sleep(0.05)
    assert pred()


def test_deleting_the_lock_file_does_not_let_a_second_runner_in(tmp_path):
    from tests.toy.common import toy_scene

    d = toy_scene(tmp_path)
    env = dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas"))
    first = subprocess.Popen([sys.executable, str(REPO / "runner.py"), "run", str(d), "--pipeline",
                              str(TOY / "pipeline.yaml"), "--set", "a.sleep=3"], env=env, cwd=REPO,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_for(lambda: list((d / "artifacts" / "logs").glob(".a.log.*.part")) if (d / "artifacts" / "logs").is_dir()
             else False)
    (d / "artifacts" / ".lock").unlink()
    second = cli("run", str(d), "--pipeline", str(TOY / "pipeline.yaml"))
    refused(second, "another runner is working on this scene")
    out, err = first.communicate(timeout=120)
    assert first.returncode == 0, err  # the first runner was not disturbed and committed every stage
    assert out.count(" ran ") == 4
    assert cli("run", str(d), "--pipeline", str(TOY / "pipeline.yaml"), "--set", "a.sleep=3").stdout.count("cached") == 4


def test_leftovers_of_killed_runs_are_cleaned_on_the_next_run(tmp_path):
    from tests.toy.common import toy_scene

    d = toy_scene(tmp_path)
    pipe = ["--pipeline", str(TOY / "pipeline.yaml")]
    assert cli("run", str(d), *pipe).returncode == 0
    arts = d / "artifacts"
    shutil.copytree(arts / "a", arts / ".old-a-123-456")  # killed after the new artifact was in place
    shutil.copytree(arts / "b", arts / ".tmp-b-123-456")  # killed mid-stage
    (arts / "logs" / ".a.log.123.part").write_text("partial")  # a killed attempt, the log is there
    (arts / "logs" / "c.log").rename(arts / "logs" / ".c.log.123.part")  # killed after commit, before the log moved
    (arts / "variants" / "v").mkdir(parents=True)
    shutil.copytree(arts / "d", arts / "variants" / "v" / ".old-d-1-2")
    second = cli("run", str(d), *pipe)
    assert second.returncode == 0 and second.stdout.count("cached") == 4, second.stdout + second.stderr
    names = {p.relative_to(arts).as_posix() for p in arts.rglob("*")}
    assert not [n for n in names if ".old-" in n or ".tmp-" in n or n.endswith(".part")], names
    assert (arts / "logs" / "c.log").is_file() and (arts / "variants" / "v" / "d").is_dir()


def test_part_logs_are_unique_per_runner():
    log = Path("/x/logs/a.log")
    assert pl.pending_log(log).name == f".a.log.{os.getpid()}.part"


# ---------------------------------------------------------------- 11: partial results and pair cap


def test_a_partial_registration_is_said_on_stderr_and_in_the_table(tmp_path):
    d = make_home(tmp_path / "h", poses=False)  # random textures and flat depths: no pair registers
    out = cli("run", str(d), "--until", "register")
    assert out.returncode == 0, out.stderr
    line = ("home: 1 of 3 panoramas registered (not placed: b, c; see artifacts/register/registration.json; a pose in "
            "poses.json for one panorama of each group places it, `runner.py split` makes each group a home of its own)")
    assert f"note: {line}" in out.stderr and f"note: {line}" in out.stdout
    js = cli("run", str(d), "--until", "register", "--json")
    assert line in json.loads(js.stdout)["notes"] and line in js.stderr
    with open(tmp_path / "run.log", "w+") as log:  # `> run.log 2>&1`: one log hears each note once
        subprocess.run([sys.executable, str(REPO / "runner.py"), "run", str(d), "--until", "register"], stdout=log,
                       stderr=subprocess.STDOUT, cwd=REPO, env=dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas")))
        log.seek(0)
        assert log.read().count(f"note: {line}") == 1
    st = cli("status", str(d))  # status says it as long as the registration is up to date
    assert st.returncode == 0 and f"note: {line}" in st.stdout, st.stdout
    assert json.loads(cli("status", str(d), "--json").stdout)["notes"] == [line]
    # The remedy the note names: each panorama here is a group of its own; those given a pose are placed, and the note
    # names the rest until every group has one.
    poses = {n: np.eye(4).tolist() for n in ("a", "b", "c")}
    poses["b"][0][3], poses["c"][0][3] = 0.5, 1.0
    (d / "poses.json").write_text(json.dumps({n: poses[n] for n in ("b", "c")}))
    out = cli("run", str(d), "--until", "register")
    assert out.returncode == 0 and "home: 2 of 3 panoramas registered (not placed: a;" in out.stderr, out.stderr
    (d / "poses.json").write_text(json.dumps(poses))
    out = cli("run", str(d), "--until", "register")
    assert out.returncode == 0 and "note: home" not in out.stderr, out.stderr
    placed = json.loads((d / "artifacts" / "register" / "panoramas.json").read_text())
    assert sorted(placed) == ["a", "b", "c"]
    assert np.isclose(np.linalg.norm(np.subtract(placed["c"], placed["b"])[:3, 3]), 0.5)


def test_split_makes_each_unplaced_group_a_home_that_runs(tmp_path):
    """`runner.py split HOME`: the groups registration left unplaced (b alone; c with its copy d) become HOME-group2 (one
    panorama's scene) and HOME-group3 (a home) beside HOME, with HOME's scene.yaml, which the runner takes as they are;
    HOME is unchanged. Before registration, onto a directory that exists or after the home changed: exit 2, one line,
    nothing written."""
    d = make_home(tmp_path / "h", poses=False)  # random textures and flat depths: no pair registers
    for src, copy in (("c", "d"), ("a", "e")):  # copies register with their originals; of the two groups of two, the
        shutil.copy(d / "panoramas" / f"{src}.png", d / "panoramas" / f"{copy}.png")  # first by name (a, e) is placed
        shutil.copy(d / "depths" / f"{src}.npy", d / "depths" / f"{copy}.npy")
    (d / "scene.yaml").write_text("params:\n  register:\n    height: 256\n")  # the home's settings go with each group
    refused(cli("split", str(d)), "no registration of this home; run `python runner.py run")
    assert not list(tmp_path.glob("h-group*"))
    assert cli("run", str(d), "--until", "register").returncode == 0
    placed = json.loads((d / "artifacts" / "register" / "panoramas.json").read_text())
    assert sorted(placed) == ["a", "e"]
    before = listing(d)
    out = cli("split", str(d))
    assert out.returncode == 0, out.stderr
    one, two = tmp_path / "h-group2", tmp_path / "h-group3"  # the groups in name order: b, then c and d
    assert f"python runner.py run {two}" in out.stdout and f"python runner.py run {one}" in out.stdout
    src = listing(d)
    assert listing(two) == {"depths": -1, "panoramas": -1, "scene.yaml": src["scene.yaml"],
                            **{f"{k}/{n}.{x}": src[f"{k}/{n}.{x}"] for n in "cd"
                               for k, x in (("depths", "npy"), ("panoramas", "png"))}}
    assert listing(one) == {"depth.npy": src["depths/b.npy"], "panorama.png": src["panoramas/b.png"],
                            "scene.yaml": src["scene.yaml"]}
    assert listing(d) == before
    assert cli("run", str(two), "--until", "register").returncode == 0  # c and d register with each other
    assert sorted(json.loads((two / "artifacts" / "register" / "panoramas.json").read_text())) == ["c", "d"]
    assert art.read_manifest(two / "artifacts" / "register")["params"]["height"] == 256
    done = cli("split", str(two))  # every panorama registered: nothing to write
    assert done.returncode == 0 and "nothing to split" in done.stdout and not list(tmp_path.glob("h-group3-*"))
    assert cli("run", str(one), "--until", "depth").returncode == 0
    refused(cli("split", str(d)), f"{one}: already exists; remove it or give --out DIR")
    shutil.copy(d / "panoramas" / "b.png", d / "panoramas" / "f.png")  # the home changed since its registration
    refused(cli("split", str(d), "--out", str(tmp_path / "elsewhere")), "registered other panoramas than")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["h", "h-group2", "h-group3"]


def test_200_panoramas_are_planned_without_trying_all_pairs():
    rng = np.random.default_rng(0)
    names = [f"p{i:03d}" for i in range(200)]
    looks = {n: appearance_descriptor(rng.integers(0, 255, (32, 64, 3), dtype=np.uint8)) for n in names}
    pairs = candidate_pairs(names, looks)
    assert len(pairs) <= PAIRS_PER_PANORAMA * 200 < 19_900
    assert all(0 <= a < b < 200 for a, b in pairs) and len(set(pairs)) == len(pairs)
    # The chain in capture order keeps every panorama reachable from the first.
    reach, todo = {0}, [0]
    adj = {i: set() for i in range(200)}
    for a, b in pairs:
        adj[a].add(b)
        adj[b].add(a)
    while todo:
        for j in adj[todo.pop()] - reach:
            reach.add(j)
            todo.append(j)
    assert len(reach) == 200
    # Linear growth: twice the panoramas, about twice the pairs.
    names400 = [f"q{i:03d}" for i in range(400)]
    assert len(candidate_pairs(names400, None)) <= 2.05 * len(candidate_pairs(names, None))
    # A small home tries every pair; pairs of two posed panoramas are never tried.
    small = names[:ALL_PAIRS_UP_TO]
    assert len(candidate_pairs(small)) == ALL_PAIRS_UP_TO * (ALL_PAIRS_UP_TO - 1) // 2
    assert (0, 1) not in candidate_pairs(small, given={small[0], small[1]})


def test_groups_left_apart_get_every_pair_across_them_nearest_in_capture_order_first():
    names = [f"p{i:02d}" for i in range(40)]
    group = {n: int(i >= 25) for i, n in enumerate(names)}  # two groups: p00-p24, p25-p39
    tried = set(candidate_pairs(names, None))
    across = {(a, b) for a in range(25) for b in range(25, 40)} - tried
    assert len(bridge_pairs(names, group, tried)) == 8 * 40 < len(across)  # the cap
    assert bridge_pairs(names, group, tried, per_panorama=10) == sorted(across)  # every pair across
    capped = bridge_pairs(names, group, tried, per_panorama=2)
    assert len(capped) == 80 and set(capped) <= across
    near = sorted(across, key=lambda ab: ab[1] - ab[0])
    assert max(b - a for a, b in capped) <= min(b - a for a, b in set(near) - set(capped))
    assert bridge_pairs(names, dict.fromkeys(names, 0), set()) == []  # one group: nothing to bridge


def test_pairs_across_a_floor_edge_the_images_do_not_confirm_are_tried_too():
    """A weak floor fit that the first pairs hold (real east's 14-31 in a home past all_pairs_up_to) is refused by the
    lone-fit rule unless another pair across it agrees: so the pairs across it are bridge pairs."""
    from panoworld.register.graph import FLOOR, Edge, bridging_groups, group_of

    names = [f"p{i:02d}" for i in range(20)]
    edges = [Edge(a=names[i], b=names[i + 1], a_from_b=np.eye(4), kind="depth", inliers=50, info={})
             for i in range(19) if i != 9]
    weak = Edge(a=names[9], b=names[10], a_from_b=np.eye(4), kind=FLOOR, inliers=10, info={}, confirmed=False)
    tried = set(candidate_pairs(names, None, all_up_to=8))  # a home past all_pairs_up_to
    assert len(set(group_of(names, edges + [weak]).values())) == 1  # the edge joins the home ...
    group = bridging_groups(names, edges + [weak])
    assert group[names[0]] == group[names[9]] != group[names[10]] == group[names[19]]  # ... not for bridging
    across = bridge_pairs(names, group, tried)
    assert (8, 13) in across and all((a < 10) != (b < 10) for a, b in across)
    confirmed = Edge(a=names[9], b=names[10], a_from_b=np.eye(4), kind=FLOOR, inliers=10, info={})
    assert bridge_pairs(names, bridging_groups(names, edges + [confirmed]), tried) == []


def test_appearance_neighbours_find_the_same_room_again():
    rng = np.random.default_rng(1)
    base = [rng.integers(0, 255, (32, 64, 3), dtype=np.uint8) for _ in range(20)]
    names = [f"n{i:02d}" for i in range(20)]
    looks = {n: appearance_descriptor(img) for n, img in zip(names, base)}
    looks["n19"] = appearance_descriptor(np.roll(base[3], 17, axis=1))  # n03 again, turned about the vertical
    pairs = candidate_pairs(names, looks)
    assert (3, 19) in pairs  # far apart in name order, found by appearance


def test_a_long_failure_line_is_cut_in_the_table(tmp_path):
    log = tmp_path / "t.log"
    log.write_text("$ cmd\nerror: stage trajectory: " + "x" * 10_000 + "\n")
    line = execute.failure_line(log, "trajectory")
    assert len(line) <= execute.MAX_REASON_CHARS + 20 and line.endswith("(cut)")


def test_sweep_leftovers_restores_an_artifact_caught_mid_swap(tmp_path):
    arts = tmp_path / "artifacts"
    (arts / ".old-a-1-2").mkdir(parents=True)
    (arts / ".old-a-1-2" / "f").write_text("previous")
    found = art.sweep_leftovers(arts)
    assert (arts / "a" / "f").read_text() == "previous" and found == [arts / ".old-a-1-2"]


def test_the_planners_own_failure_is_exit_1_not_a_bad_navmesh(monkeypatch, tmp_path):
    import stages.trajectory as traj
    from panoworld.core.errors import PanoWorldError

    def fail(nav, params):
        raise ValueError("no reachable sector")
    monkeypatch.setattr(traj, "plan_path", fail)

    class Nav:
        info: dict = {}
    with pytest.raises(PanoWorldError, match="no path planned on the NavMesh") as e:
        traj._plan_or_stay(Nav(), traj.Params(), tmp_path / "navmesh" / "navmesh.json")
    assert e.value.exit_code == 1 and not isinstance(e.value, InputError)
