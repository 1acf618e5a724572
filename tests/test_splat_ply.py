"""INRIA 3DGS .ply and point cloud .ply: standard layout, exact round trips, identical renders after reload."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData

from panoworld.io.gaussian_set import Gaussians
from panoworld.io.splat_ply import (
    GAUSSIAN_FIELDS,
    gaussian_fields,
    read_gaussians_ply,
    read_points_ply,
    write_gaussians_ply,
    write_points_ply,
)
from panoworld.render.splats import render_perspective

torch.set_num_threads(1)


def gaussians(n: int = 200, sh_k: int = 0, seed: int = 1) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Gaussians(
        means=(rng.uniform(-1, 1, (n, 3)) + [0, 0, 3]).astype(np.float32),
        scales=rng.uniform(0.01, 0.2, (n, 3)).astype(np.float32),
        quats=q.astype(np.float32),
        opacities=rng.uniform(0.05, 0.95, n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(size=(n, sh_k, 3)).astype(np.float32),
    )


@pytest.mark.parametrize("full_sh", [False, True])
def test_standard_inria_layout(tmp_path, full_sh):
    g = gaussians()
    path = tmp_path / "gaussians.ply"
    write_gaussians_ply(path, g, full_sh=full_sh)
    ply = PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    v = ply["vertex"]
    # Degree-0 colours: no f_rest_* and no normals (14 properties), or the full layout (62) for tools that insist.
    fields = GAUSSIAN_FIELDS if full_sh else gaussian_fields(0, normals=False)
    assert [p.name for p in v.properties] == fields and len(fields) == (62 if full_sh else 14)
    assert all(p.val_dtype in ("f4", "float32", "<f4") for p in v.properties)
    assert len(v.data) == len(g)
    # Stored activations: logit opacity, log scales, (w, x, y, z) rotations, zero f_rest for degree 0.
    assert np.allclose(1 / (1 + np.exp(-v["opacity"])), g.opacities, atol=1e-6)
    assert np.allclose(np.exp(v["scale_1"]), g.scales[:, 1], rtol=1e-6)
    assert np.allclose(v["rot_0"], g.quats[:, 0])
    assert all(np.all(v[f"f_rest_{i}"] == 0) for i in range(45 if full_sh else 0))
    assert path.stat().st_size < 4 * len(fields) * len(g) + 2000  # 4 bytes per property and Gaussian + header
    if full_sh:
        normal = np.stack([v["nx"], v["ny"], v["nz"]], 1)
        assert np.allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-5)  # the surfel's thinnest axis


def test_round_trip_and_identical_render(tmp_path):
    g = gaussians(sh_k=3)
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, g)
    back = read_gaussians_ply(path)
    assert back.sh_rest.shape == (len(g), 3, 3) and np.array_equal(back.sh_rest, g.sh_rest)  # the degree used
    write_gaussians_ply(tmp_path / "full.ply", g, full_sh=True)
    full = read_gaussians_ply(tmp_path / "full.ply")
    assert full.sh_rest.shape == (len(g), 15, 3)
    assert np.array_equal(full.sh_rest[:, :3], g.sh_rest) and not full.sh_rest[:, 3:].any()
    for name in ("means", "quats", "sh_dc"):
        assert np.array_equal(getattr(back, name), getattr(g, name))
    assert np.allclose(back.scales, g.scales, rtol=1e-6)
    assert np.allclose(back.opacities, g.opacities, atol=1e-6)
    args = (np.eye(4), 40.0, 40.0, 24.0, 16.0, 32, 48)
    a = render_perspective(g, *args)
    b = render_perspective(back, *args)
    assert (a.rgb - b.rgb).abs().max() < 1e-5 and (a.alpha - b.alpha).abs().max() < 1e-5


def test_f_rest_is_channel_major_like_inria(tmp_path):
    g = gaussians(n=3, sh_k=15)
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, g)
    v = PlyData.read(str(path))["vertex"]
    # INRIA flattens features_rest (N, 3 channels, 15 coefficients): f_rest_{c * 15 + k}.
    assert np.array_equal(v["f_rest_16"], g.sh_rest[:, 1, 1])
    assert np.array_equal(v["f_rest_44"], g.sh_rest[:, 14, 2])


def test_degree_one_colours_load_as_the_reference_implementation_loads_them(tmp_path):
    # The colour fit's view-dependent colours (degree 1): INRIA's load_ply sorts f_rest_* by number and reshapes them
    # to (N, 3 channels, (degree + 1)^2 - 1); our zero-padded degree-3 file (full_sh) gives it the degree-1 terms in
    # place, and a file of degree 1 as INRIA writes it (f_rest_0..8) reads back the same.
    g = gaussians(n=50, sh_k=3)
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, g, full_sh=True)
    v = PlyData.read(str(path))["vertex"].data
    names = sorted((p for p in v.dtype.names if p.startswith("f_rest_")), key=lambda p: int(p.split("_")[-1]))
    extra = np.stack([v[p] for p in names], 1).reshape(len(g), 3, -1).transpose(0, 2, 1)  # INRIA's features_rest
    assert extra.shape == (len(g), 15, 3)
    assert np.array_equal(extra[:, :3], g.sh_rest) and not extra[:, 3:].any()
    inria = np.empty(len(g), [(p, "<f4") for p in ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
                              + [f"f_rest_{i}" for i in range(9)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
                              + [f"rot_{i}" for i in range(4)]])
    for p in inria.dtype.names:
        inria[p] = v[p] if not p.startswith("f_rest_") else g.sh_rest[:, int(p[7:]) % 3, int(p[7:]) // 3]
    from plyfile import PlyElement

    PlyData([PlyElement.describe(inria, "vertex")]).write(str(tmp_path / "deg1.ply"))
    back = read_gaussians_ply(tmp_path / "deg1.ply")
    assert back.sh_degree == 1 and np.array_equal(back.sh_rest, g.sh_rest)


def test_points_ply_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    write_points_ply(tmp_path / "p.ply", xyz, rgb)
    x2, c2 = read_points_ply(tmp_path / "p.ply")
    assert np.array_equal(x2, xyz) and np.array_equal(c2, rgb)
    write_points_ply(tmp_path / "f.ply", xyz, np.full((50, 3), 0.5))
    assert np.all(read_points_ply(tmp_path / "f.ply")[1] == 128)


def test_bad_files_raise_naming_the_problem(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    with pytest.raises(ValueError, match="not a readable .ply"):
        read_gaussians_ply(bad)
    xyz = np.zeros((4, 3), np.float32)
    write_points_ply(tmp_path / "pts.ply", xyz, np.zeros((4, 3), np.uint8))
    with pytest.raises(ValueError, match="opacity"):
        read_gaussians_ply(tmp_path / "pts.ply")
    with pytest.raises(ValueError, match=r"^rgb.shape=\(3, 3\) but expected \(4, 3\)$"):  # N bound by xyz
        write_points_ply(tmp_path / "x.ply", xyz, np.zeros((3, 3)))


def test_asset_stage_and_ply_reader_import_without_torch_or_scipy():
    # torch and scipy cost the asset stage ~3-7 CPU-s per run in imports alone; it needs neither.
    code = ("import sys, stages.asset, panoworld.asset, panoworld.io.splat_ply, panoworld.geometry.erp_mesh, panoworld.navmesh, "
            "panoworld.trajectory; print(sorted(m for m in ('torch', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parent.parent)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
