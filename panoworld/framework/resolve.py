"""Stage params of a run: dataclass defaults < pipeline.yaml < preset < scene.yaml < --set, each value checked."""

from __future__ import annotations

from typing import Any

from panoworld.core.errors import PipelineError
from panoworld.framework.dag import DEFAULT_PRESET, Pipeline
from panoworld.framework.scene import SCENE_CONFIG, Scene


def parse_sets(sets: list[str], pipeline: Pipeline) -> dict[str, dict[str, str]]:
    out: dict[str, dict[str, str]] = {}
    for s in sets:
        lhs, eq, value = s.partition("=")
        stage, dot, param = lhs.partition(".")
        if not eq or not dot or not param:
            raise PipelineError(f"--set {s}: expected STAGE.PARAM=VALUE")
        pipeline.check_stage(stage, "--set")
        out.setdefault(stage, {})[param] = value
    return out


def resolve_params(
    pipeline: Pipeline, preset: str | None, scene: Scene | None, sets: dict[str, dict[str, str]], stages: list[str]
) -> dict[str, Any]:
    """Params objects per stage: dataclass defaults < pipeline params < preset < scene.yaml < --set, each value
    checked against its declared type, range and choices (PipelineError naming the param and where it was set)."""
    from panoworld.framework.stage_params import merge, normalize, params_from_normalized

    preset = preset or (scene.config.get("preset") if scene else None) or DEFAULT_PRESET
    if preset not in pipeline.presets:
        raise PipelineError(f"--preset {preset}: unknown preset; known: {', '.join(pipeline.presets)}")
    scene_params = (scene.config.get("params") or {}) if scene else {}
    out = {}
    for name in stages:
        node = pipeline.stages[name]
        layers = [
            (node.params, f"{pipeline.path.name} stages.{name}.params"),
            (node.presets.get(preset, {}), f"{pipeline.path.name} preset {preset}"),
            (scene_params.get(name) or {}, f"{SCENE_CONFIG} params.{name}"),
            (sets.get(name, {}), "--set"),
        ]
        values: dict[str, Any] = {}
        for layer, where in layers:
            if not layer:
                continue
            try:
                layer_values = normalize(node.spec.params_cls, layer, name)
                params_from_normalized(node.spec.params_cls, layer_values, where=name)  # names the layer that brings a bad value
                values = merge(values, layer_values)
            except ValueError as e:
                raise PipelineError(f"{e} (from {where})") from None
        try:
            out[name] = params_from_normalized(node.spec.params_cls, values, where=name)
        except ValueError as e:
            raise PipelineError(str(e)) from None
    return out
