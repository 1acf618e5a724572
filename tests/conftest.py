"""Shared pytest setup: single-threaded torch (2-core machines) and a session cache of synthetic scenes."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")


def pytest_configure(config):
    try:
        import torch
    except ImportError:
        return
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def synth_dataset(tmp_path_factory):
    """Three ci-tiny synthetic scenes (seeded), generated once per test session."""
    from panoworld.tools.synth.cli import main as synth_main

    root = tmp_path_factory.mktemp("synth") / "dataset"
    assert synth_main([str(root), "--seed", "11", "--scenes", "3", "--preset", "ci-tiny"]) == 0
    return root


@pytest.fixture(scope="session")
def synth_scene(synth_dataset):
    """One ci-tiny synthetic scene directory (pipeline input layout + gt/)."""
    return sorted(p for p in synth_dataset.iterdir() if p.is_dir())[0]


@pytest.fixture(scope="session")
def cond_dir(synth_dataset, tmp_path_factory):
    """A precompute output of synth_dataset: 2 clips per scene, 5 frames, 32 x 64 (the video trainer's tests)."""
    from panoworld.tools.precompute.run import main as precompute_main

    out = tmp_path_factory.mktemp("cond") / "cond"
    assert precompute_main([str(synth_dataset), "--out", str(out), "--clips-per-scene", "2", "--frames", "5",
                            "--strides", "1", "--height", "32", "--workers", "1", "--json"]) == 0
    return out


HOME_HEIGHT = 384
"""Rows of the test home's panoramas: SIFT finds too few matches on the small ci-tiny textures at 256 rows."""


@pytest.fixture(scope="session")
def home_dir(tmp_path_factory):
    """A ci-tiny home (seed 7) of >= 3 rooms captured by 3 panoramas at HOME_HEIGHT rows, with gt/poses.json."""
    from dataclasses import replace

    from panoworld.tools.synth.home import generate_home, home_params, write_home

    params = home_params("ci-tiny")
    params = replace(params, render=replace(params.render, pano_height=HOME_HEIGHT))
    return write_home(generate_home(7, 3, "ci-tiny", params=params), tmp_path_factory.mktemp("home") / "scene", params)
