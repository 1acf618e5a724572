"""Kernel precompilation: the listed signatures are the ones the stages call; the runner starts one background
compilation per cold cache (none when the stamp is current, another process compiles, or it is switched off)."""

from __future__ import annotations

import fcntl
import json
import os
import sys

import numpy as np
import pytest

from panoworld.framework import kernels


def _listed(name: str) -> set:
    return {tuple(sig) for _, _, fn, sig in kernels.kernel_specs() if fn == name}


def test_listed_signatures_are_the_ones_the_renderers_call():
    """ErpRasterizer (conditions) and the background layer's stretch (video) call their kernels with exactly the
    listed signatures, one each (dtype casts at the entry points), whatever dtypes the caller passes."""
    from panoworld.render import raster_kernels as rk
    from panoworld.render.rasterize import ErpRasterizer
    from panoworld.video import background_layer as bl

    rng = np.random.default_rng(0)
    verts = rng.normal(size=(40, 3))  # float64 and int64 in: the entry points cast
    faces = rng.integers(0, 40, size=(60, 3))
    r = ErpRasterizer(verts, faces, colors=np.full((40, 3), 200))
    r.render(np.eye(4), 16, 32)
    r.render_erp(np.eye(4), 16, 32)
    bl._stretch(verts.astype(np.float32), faces.astype(np.int32))
    for name, fn in [("_vertex_pass", rk._vertex_pass), ("_raster_pass", rk._raster_pass),
                     ("_resolve_shaded", rk._resolve_shaded), ("_resolve_hits", rk._resolve_hits),
                     ("_stretch_kernel", bl._stretch_kernel)]:
        assert {tuple(s) for s in fn.signatures} == _listed(name), name


def test_listed_signatures_are_the_ones_the_culled_rasterizer_calls():
    """ErpRasterizer's occlusion culling (a mesh of CULL_MIN_FACES and more; here any) calls its kernels with exactly the
    listed signatures: a small sphere inside a large one, the second pose rasterising the clusters the first hid."""
    import trimesh

    from panoworld.render import cull_kernels as ck
    from panoworld.render import raster_kernels as rk
    from panoworld.render.rasterize import ErpRasterizer

    inner, outer = trimesh.creation.icosphere(subdivisions=3), trimesh.creation.icosphere(subdivisions=3)
    verts = np.concatenate([outer.vertices * 5.0, inner.vertices * 0.5 + [2.0, 0.0, 0.0]])
    faces = np.concatenate([outer.faces, inner.faces + len(outer.vertices)])
    r = ErpRasterizer(verts, faces, colors=np.full((len(verts), 3), 200), cull_cluster=16, cull_min_faces=0)
    pose = np.eye(4)
    r.render(pose, 32, 64)
    pose[0, 3] = 0.2
    r.render(pose, 32, 64)
    for fn in (ck._morton_keys, ck._cluster_vertices, ck._cluster_spheres, ck._tile_far, ck._may_show,
               ck._seen_clusters, rk._vertex_pass_clusters, rk._raster_clusters):
        assert {tuple(s) for s in fn.signatures} == _listed(fn.py_func.__name__), fn.py_func.__name__


def test_listed_signatures_are_the_ones_the_capture_fits_operator_calls():
    """The home's capture fit builds pruned render operators and multiplies through them with the listed signatures."""
    import torch

    from panoworld.io.gaussian_set import Gaussians
    from panoworld.render import erp_operator as eo

    rng = np.random.default_rng(1)
    n = 200
    g = Gaussians(means=rng.uniform(-2, 2, (n, 3)).astype(np.float32), scales=np.full((n, 3), 0.3, np.float32),
                  quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), opacities=np.full(n, 0.5, np.float32),
                  sh_dc=np.zeros((n, 3), np.float32))
    op = eo.ErpColorOperator(g, np.eye(4), 16, 32, prune=0.01)
    op.adjoint(op(torch.rand(n, 3)))
    for fn in (eo._prune_rows, eo._csr_times, eo._csr_times_t):
        assert {tuple(s) for s in fn.signatures} == _listed(fn.py_func.__name__), fn.py_func.__name__


def test_every_listed_kernel_exists_with_numba_cache():
    import importlib

    for _, module, name, _sig in kernels.kernel_specs():
        assert module in kernels.KERNEL_MODULES
        fn = getattr(importlib.import_module(module), name)
        assert fn._cache.__class__.__name__ == "FunctionCache", f"{module}.{name} is not cache=True"


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba"))
    monkeypatch.delenv(kernels.DISABLE_ENV, raising=False)
    started = []

    class FakePopen:
        def __init__(self, cmd, **kw):
            started.append((cmd, kw))

    monkeypatch.setattr(kernels.subprocess, "Popen", FakePopen)
    return tmp_path / "numba", started


def test_background_compile_starts_once_per_cold_cache(cache, monkeypatch):
    where, started = cache
    assert not kernels.is_compiled()
    assert kernels.start_background_compile() is not None
    cmd, kw = started[0]
    assert cmd[1:] == ["-m", "panoworld.framework.kernels", "--locked"] and len(kw["pass_fds"]) == 1
    # the stamp of the current sources: nothing to do
    (where / kernels.STAMP).write_text(json.dumps({"key": kernels.cache_key()}))
    assert kernels.is_compiled() and kernels.start_background_compile() is None
    # a kernel module edited since (numba's own invalidation: size and mtime): compile again
    monkeypatch.setattr(kernels, "cache_key", lambda: "other sources")
    assert not kernels.is_compiled() and kernels.start_background_compile() is not None
    assert len(started) == 2


def test_a_home_compiles_the_home_only_kernels_a_one_panorama_run_leaves_out(cache, monkeypatch):
    """A one-panorama scene's background compilation leaves the HOME_ONLY groups out (its stamp says so); a home's
    run then compiles again, with them."""
    where, started = cache
    assert kernels.start_background_compile(home=False) is not None
    assert started[0][0][-1] == "--locked"
    where.mkdir(exist_ok=True)
    (where / kernels.STAMP).write_text(json.dumps({"key": kernels.cache_key(), "home": False}))
    assert kernels.is_compiled(home=False) and not kernels.is_compiled(home=True)
    assert kernels.start_background_compile(home=False) is None
    assert kernels.start_background_compile(home=True) is not None and started[1][0][-2:] == ["--locked", "--home"]
    (where / kernels.STAMP).write_text(json.dumps({"key": kernels.cache_key(), "home": True}))
    assert kernels.is_compiled(home=True) and kernels.start_background_compile(home=True) is None
    # what the one-panorama compilation runs: every kernel but the home-only groups
    assert set(kernels.HOME_ONLY) <= {stage for stage, *_ in kernels.kernel_specs()}
    monkeypatch.setattr(kernels, "kernel_specs", lambda: [("conditions", "no_such.module", "a", ()),
                                                          ("culling", "no_such.module", "b", ())])
    assert [r["stage"] for r in kernels.compile_kernels(home=False)] == ["conditions"]
    assert [r["stage"] for r in kernels.compile_kernels()] == ["conditions", "culling"]


def test_no_background_compile_while_another_runs_or_when_off(cache, monkeypatch):
    where, started = cache
    where.mkdir()
    with open(where / kernels.LOCK, "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert kernels.start_background_compile() is None
    monkeypatch.setenv(kernels.DISABLE_ENV, "0")
    assert kernels.start_background_compile() is None
    assert started == []


def test_cache_key_follows_python_and_sources(tmp_path, monkeypatch):
    monkeypatch.setattr(kernels, "REPO_ROOT", tmp_path)
    monkeypatch.setattr(kernels, "KERNEL_MODULES", ("pkg.mod",))
    (tmp_path / "pkg").mkdir()
    src = tmp_path / "pkg" / "mod.py"
    src.write_text("x = 1\n")
    k1 = kernels.cache_key()
    assert kernels.cache_key() == k1
    src.write_text("x = 22\n")
    assert kernels.cache_key() != k1
    monkeypatch.setattr(sys, "version", sys.version + " other")
    k2 = kernels.cache_key()
    src.write_text("x = 22\n")
    os.utime(src, ns=(1, 1))
    assert kernels.cache_key() != k2


def test_a_kernel_that_does_not_compile_is_reported_and_the_stamp_still_written(tmp_path, monkeypatch):
    """A wrong listed signature must not make every later run start the compilation again."""
    from numba import types

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(kernels, "kernel_specs", lambda: [
        ("video", "panoworld.video.background_layer", "_stretch_kernel", (types.unicode_type,)),
        ("video", "panoworld.video.no_such_module", "_k", ()),
    ])
    rows = kernels.compile_and_stamp()
    assert [r["error"] is not None for r in rows] == [True, True]
    assert "ModuleNotFoundError" in rows[1]["error"]
    assert kernels.is_compiled()
    assert kernels.main([]) == 1


def test_a_stage_waits_for_its_kernels_not_for_the_others(tmp_path, monkeypatch):
    import subprocess

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    # a stand-in compilation: conditions done at once, then a long compile of the rest
    proc = subprocess.Popen([sys.executable, "-c", f"import time; open({str(tmp_path / kernels.PROGRESS)!r}, 'a')"
                             f".write('conditions\\n'); time.sleep(30)"])
    try:
        assert kernels.wait_for_stage(proc, "depth") == 0.0  # no kernels: never waits
        assert kernels.wait_for_stage(proc, "conditions", poll_s=0.01) < 10
        assert kernels.wait_for_stage(proc, "gaussians", poll_s=0.01, max_s=0.3) >= 0.3  # still compiling
    finally:
        proc.kill()
        proc.wait()
    assert kernels.wait_for_stage(proc, "gaussians") < 1  # the compilation ended: go ahead
    assert kernels.wait_for_stage(None, "gaussians") == 0.0

