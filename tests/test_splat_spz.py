"""gaussians.spz: written with gsply, read back by an independent implementation (PlayCanvas splat-transform, Node)."""

import shutil
import subprocess

import numpy as np
import pytest

from panoworld.io.splat_ply import read_gaussians_ply
from panoworld.io.splat_spz import read_gaussians_spz, write_gaussians_spz
from tests.test_splat_ply import gaussians

SPLAT_TRANSFORM = shutil.which("splat-transform")  # npm install -g @playcanvas/splat-transform (.ci/run does)


def realistic(n: int = 400, sh_k: int = 0):
    """Gaussians whose colours lie in [0, 1] (SPZ stores DC colours in 8 bits over about [-0.1, 1.1])."""
    g = gaussians(n=n, sh_k=sh_k)
    g.sh_dc = np.clip(g.sh_dc, -1.5, 1.5)
    g.sh_rest = np.clip(g.sh_rest, -0.9, 0.9)
    return g


def assert_within_spz_precision(back, g):
    assert len(back) == len(g)
    assert np.abs(back.means - g.means).max() <= 2.0 ** -12  # 24-bit fixed point, 12 fractional bits
    assert np.abs(np.log(back.scales) - np.log(g.scales)).max() <= 1 / 32 + 1e-5  # log scale in 1/16 steps
    assert np.abs(back.opacities - g.opacities).max() <= 1 / 255
    assert np.abs(back.sh_dc - g.sh_dc).max() <= 0.5 / (0.15 * 255) + 1e-5
    assert back.sh_rest.shape == g.sh_rest.shape
    assert np.abs(back.sh_rest - g.sh_rest).max(initial=0) <= 1 / 128 + 1e-6
    q = g.quats / np.linalg.norm(g.quats, axis=1, keepdims=True)
    assert np.abs(np.sum(q * back.quats / np.linalg.norm(back.quats, axis=1, keepdims=True), 1)).min() > 0.9999


@pytest.mark.parametrize("sh_k", [0, 3])
def test_round_trip_within_the_format_precision(tmp_path, sh_k):
    g = realistic(sh_k=sh_k)
    write_gaussians_spz(tmp_path / "g.spz", g)
    assert_within_spz_precision(read_gaussians_spz(tmp_path / "g.spz"), g)
    # 20 bytes per Gaussian before gzip (+ a byte per higher SH coefficient): under a third of the .ply row.
    assert (tmp_path / "g.spz").stat().st_size < (20 + 3 * sh_k) * len(g) + 200


def test_the_same_gaussians_give_the_same_bytes(tmp_path, monkeypatch):
    # gzip stamps the time into its header; the artifact must not depend on when it was written.
    import time

    g = realistic()
    write_gaussians_spz(tmp_path / "a.spz", g)
    monkeypatch.setattr(time, "time", lambda: 2_000_000_000.0)
    write_gaussians_spz(tmp_path / "b.spz", g)
    assert (tmp_path / "a.spz").read_bytes() == (tmp_path / "b.spz").read_bytes()


def test_all_zero_higher_sh_is_not_stored(tmp_path):
    g = realistic(sh_k=15)
    g.sh_rest[:] = 0
    write_gaussians_spz(tmp_path / "g.spz", g)
    assert read_gaussians_spz(tmp_path / "g.spz").sh_degree == 0


def test_not_an_spz_file_is_refused_naming_it(tmp_path):
    bad = tmp_path / "bad.spz"
    bad.write_bytes(b"not a splat")
    with pytest.raises(ValueError, match=r"bad\.spz: not a readable \.spz file"):
        read_gaussians_spz(bad)


@pytest.mark.skipif(SPLAT_TRANSFORM is None or shutil.which("node") is None,
                    reason="needs node and splat-transform (npm install -g @playcanvas/splat-transform)")
@pytest.mark.parametrize("sh_k", [0, 3])
def test_splat_transform_reads_what_we_write(tmp_path, sh_k):
    g = realistic(sh_k=sh_k)
    write_gaussians_spz(tmp_path / "g.spz", g)
    out = subprocess.run([SPLAT_TRANSFORM, "-q", "-w", str(tmp_path / "g.spz"), str(tmp_path / "back.ply")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    back = read_gaussians_ply(tmp_path / "back.ply")
    assert_within_spz_precision(back, g)
    ours = read_gaussians_spz(tmp_path / "g.spz")  # both decoders read the same bytes alike
    assert np.abs(back.means - ours.means).max() < 1e-6 and np.abs(back.sh_dc - ours.sh_dc).max() < 1e-5
