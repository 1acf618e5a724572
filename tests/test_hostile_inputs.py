"""Hostile and odd user inputs (issue #24): each refused in one line naming the file, exit code 2, nothing written."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from panoworld import artifacts as art
from panoworld.depth import read_panorama
from panoworld.errors import InputError
from panoworld.image_io import MAX_PIXELS, ImageInputError, check_image

TOY = Path(__file__).parent / "toy"
REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def toy_schemas(monkeypatch):
    monkeypatch.setenv("PANOWORLD_SCHEMA_PATH", str(TOY / "schemas"))
    art.load_schema.cache_clear()
    art._validator.cache_clear()


def cli(*args) -> subprocess.CompletedProcess:
    env = dict(os.environ, PANOWORLD_SCHEMA_PATH=str(TOY / "schemas"))
    return subprocess.run([sys.executable, str(REPO / "runner.py"), *args], capture_output=True, text=True, env=env, cwd=REPO)


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
