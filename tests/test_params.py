"""Declared params: ranges and choices checked at resolve time, nested backend options, old names, pipeline.yaml."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from panoworld.core import registry as backends
from panoworld.core.params import flatten
from panoworld.framework import pipeline as pl
from panoworld.framework.stage import load_stage
from panoworld.framework.stage_params import merge, normalize, params_from_dict, params_to_dict

REPO = Path(__file__).resolve().parent.parent


def test_pipeline_yaml_only_overrides_defaults():
    """Every value in pipeline.yaml (params and presets) changes what the stage would otherwise get."""
    pipe = pl.Pipeline.load()
    for name, node in pipe.stages.items():
        cls = node.spec.params_cls
        defaults = flatten(params_to_dict(cls()))
        base = flatten(params_to_dict(params_from_dict(cls, node.params, name)))
        for key in flatten(params_to_dict(params_from_dict(cls, node.params, name))):
            if key in {k for k in flatten(normalize(cls, node.params, name))}:
                assert base[key] != defaults[key], f"pipeline.yaml stages.{name}.params.{key} repeats the default"
        for preset, values in node.presets.items():
            assert values, f"pipeline.yaml stages.{name}.presets.{preset} is empty"
            got = flatten(params_to_dict(params_from_dict(cls, merge(normalize(cls, node.params, name),
                                                                           normalize(cls, values, name)), name)))
            for key in flatten(normalize(cls, values, name)):
                assert got[key] != base[key], f"pipeline.yaml stages.{name}.presets.{preset}.{key} changes nothing"


def test_every_default_obeys_its_declared_rule():
    for name, node in pl.Pipeline.load().stages.items():
        params_from_dict(node.spec.params_cls, {}, name)  # validates the defaults


@pytest.mark.parametrize("sets, expect", [
    ({"stride": 3}, "trajectory.stride=3: must be one of 1, 2, 4"),
    ({"frames": 1}, "trajectory.frames=1: must be >= 2"),
    ({"step_m": "nan"}, "trajectory.step_m=nan: must be a finite number"),
    ({"step_m": "inf"}, "trajectory.step_m=inf: must be a finite number"),
    ({"step_m": 0}, "trajectory.step_m=0.0: must be > 0"),
    ({"strde": 2}, "trajectory.strde: unknown param; did you mean stride?"),
])
def test_rules_name_the_param_the_value_and_what_is_allowed(sets, expect):
    with pytest.raises(ValueError) as e:
        params_from_dict(load_stage("trajectory").params_cls, sets, "trajectory")
    assert str(e.value) == expect


def test_video_backends_come_from_the_registry_with_nested_options():
    video = load_stage("video").params_cls
    assert set(backends.names("video")) == {"warp-inpaint", "frame-inpaint", "wan-shortcut"}
    p = params_from_dict(video, {"backend": "wan-shortcut", "wan.steps": "8", "warp": {"max_band_deg": 30}}, "video")
    assert p.wan.steps == 8 and p.warp.max_band_deg == 30.0
    assert backends.get("video", p.backend).options_of(p) is p.wan
    assert params_to_dict(p)["wan"]["steps"] == 8  # nested in the manifest
    with pytest.raises(ValueError, match=r"^video.backend=wan: must be one of frame-inpaint, wan-shortcut, warp-inpaint$"):
        params_from_dict(video, {"backend": "wan"}, "video")
    with pytest.raises(ValueError, match=r"^video.wan.steps=0: must be >= 1$"):
        params_from_dict(video, {"wan": {"steps": 0}}, "video")
    with pytest.raises(ValueError, match=r"^video.wan.stepz: unknown param; did you mean steps\?$"):
        params_from_dict(video, {"wan.stepz": 1}, "video")
    with pytest.raises(ValueError, match=r"^video.wan: expected a mapping of wan options, got 3$"):
        params_from_dict(video, {"wan": 3}, "video")


def test_old_flat_names_still_work():
    video = load_stage("video").params_cls
    p = params_from_dict(video, {"steps": 2, "weights": "/w", "max_band_deg": 10}, "video")
    assert (p.wan.steps, p.wan.weights, p.warp.max_band_deg) == (2, "/w", 10.0)
    assert p == params_from_dict(video, {"wan": {"steps": 2, "weights": "/w"}, "warp.max_band_deg": 10}, "video")


@pytest.mark.parametrize("stage", ["video", "poses", "depth", "gaussians"])
def test_registry_stages_do_not_branch_on_backend_names(stage):
    text = (REPO / "stages" / f"{stage}.py").read_text()
    code = "\n".join(ln for ln in text.splitlines() if " = param(" not in ln and " = options(" not in ln)
    for name in backends.names(stage):  # only the Params declarations name backends (default, options' owner)
        assert f'"{name}"' not in code, f"stages/{stage}.py names backend {name} outside its Params"
    for bad in ("backend ==", "backend !=", "Backend."):
        assert bad not in text, f"stages/{stage}.py: {bad}"


def test_gaussians_backends_nest_their_options_and_keep_the_flat_names():
    gs = load_stage("gaussians").params_cls
    assert set(backends.names("gaussians")) == {"voxel-fusion", "decoder"}
    p = params_from_dict(gs, {"voxel_size": 0.05, "source_height": 320, "weights": "/w"}, "gaussians")
    assert (p.voxel_fusion.voxel_size, p.voxel_fusion.source_height, p.decoder.weights) == (0.05, 320, "/w")
    assert p == params_from_dict(gs, {"voxel_fusion": {"voxel_size": 0.05, "source_height": 320},
                                      "decoder.weights": "/w"}, "gaussians")
    assert "decoder" not in params_to_dict(p)  # voxel-fusion chosen: the decoder's weights are not in the cache key
    with pytest.raises(ValueError, match=r"^gaussians.voxel_fusion.source_tol=0.0: must be > 0$"):
        params_from_dict(gs, {"source_tol": 0}, "gaussians")


def test_stage_help_shows_rules_and_nested_options():
    out = subprocess.run([sys.executable, "-m", "stages.video", "--help"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert "--wan-steps" in out.stdout and "--warp-max-band-deg" in out.stdout and ">= 1" in out.stdout
    assert "{frame-inpaint,wan-shortcut,warp-inpaint}" in out.stdout
    assert dataclasses.is_dataclass(load_stage("video").params_cls().wan)


def test_only_the_chosen_backends_options_enter_the_cache_key():
    video = load_stage("video").params_cls
    warp = params_from_dict(video, {"wan.steps": 8}, "video")
    assert "wan" not in params_to_dict(warp)
    assert params_to_dict(warp)["warp"] == {"max_band_deg": 45.0, "reuse": False, "side_depth_m": 0.0,
                                          "edge_depth_ratio": 0.75, "layout_planes": False, "wall_layout": False,
                                          "color_sigma_px": 0.0, "shadow_ambient": 1.0, "plane_colors": True,
                                          "next_room_colors": False, "depth_fill": True}
    assert params_to_dict(warp) == params_to_dict(params_from_dict(video, {}, "video"))  # no rerun for wan.steps
    depth = load_stage("depth").params_cls
    assert {"provided", "depth_anything"} <= set(params_to_dict(depth()))  # auto: decided by the inputs at run time
