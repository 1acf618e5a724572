"""A scene folder as the runner sees it: its files found and checked, scene.yaml read, where each stage's artifact lives."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from panoworld.core.errors import InputError, PipelineError
from panoworld.core.params import suggest
from panoworld.framework.dag import Pipeline, StageNode, cached_yaml, text_digest
from panoworld.io import manifest as art

ARTIFACTS_DIRNAME = art.ARTIFACTS_DIRNAME
VARIANTS_DIRNAME = art.VARIANTS_DIRNAME
SCENE_CONFIG = art.SCENE_CONFIG


@dataclass
class Scene:
    root: Path
    files: dict[str, Path | None]
    config: dict[str, Any]
    variant: str | None = None
    """A named variant of the DAG's tail (panoworld.tools.batch.variants): its `tail` stages live in
    artifacts/variants/NAME/, the shared upstream stages stay in artifacts/."""
    tail: frozenset[str] = frozenset()
    notes: list[str] = field(default_factory=list)
    """What the runner says about the scene's files without refusing them (files it leaves out of the inputs)."""
    config_digest: str | None = None
    """text_digest of scene.yaml as read (None: no scene.yaml)."""

    @property
    def artifacts(self) -> Path:
        return self.root / ARTIFACTS_DIRNAME

    def _home(self, stage: str) -> Path:
        return self.artifacts / VARIANTS_DIRNAME / self.variant if self.variant and stage in self.tail else self.artifacts

    def artifact_dir(self, stage: str) -> Path:
        return self._home(stage) / stage

    def log_file(self, stage: str) -> Path:
        return self._home(stage) / "logs" / f"{stage}.log"


def open_scene(scene_dir: Path | str, pipeline: Pipeline) -> Scene:
    """Find the scene files and check the panorama (exists, readable, 2:1) without writing anything."""
    from panoworld.core import limits  # the image and home readers import numpy: a replayed run needs neither
    from panoworld.io.images import check_image
    from panoworld.register.inputs import check_home, is_multi_scene

    root = Path(scene_dir).absolute()  # stages run from the repository root: a relative path would not hold there
    if not root.is_dir():
        raise PipelineError(f"{scene_dir}: scene directory not found")
    files: dict[str, Path | None] = {}
    for key, names in pipeline.scene_files.items():
        files[key] = next((root / n for n in names if (root / n).exists()), None)
    pano = files.get("panorama")
    if is_multi_scene(root) and (pano or files.get("depth")):
        raise PipelineError(f"{root}: holds both panoramas/ (a home) and {(pano or files['depth']).name} (one "
                            "panorama); keep one layout (docs/multi.md)")
    notes: list[str] = []
    if pano is None and is_multi_scene(root):  # a home: SCENE/panoramas/ (docs/multi.md)
        try:
            home = check_home(root)
        except InputError as e:
            raise PipelineError(str(e)) from None
        panos = list(home.panoramas.values())
        notes += [f"ignored {p.relative_to(root)}: "
                  + ("a Mac's metadata file (AppleDouble)" if limits.is_appledouble(p)
                     else "not a panorama, depth or rig mask of this home") for p in home.ignored]
    elif pano is None:
        names = pipeline.scene_files.get("panorama", [])
        raise PipelineError(f"{root}: no panorama; expected one of {', '.join(names)}, or panoramas/ (docs/multi.md)")
    else:
        panos = [pano]
    for pano in panos:
        try:  # fully decoded here, so a truncated or corrupt panorama is refused before anything is written
            w, h = check_image(pano, "panorama", remember=True).oriented  # the depth stage applies EXIF orientation too
            limits.check_image_size(pano, w, h, "panorama")
        except InputError as e:
            raise PipelineError(str(e)) from None
        if w != 2 * h:
            raise PipelineError(f"{pano}: {w}x{h} is not an equirectangular panorama (width must be exactly 2x height)")
    config: dict[str, Any] = {}
    config_digest = None
    cfg_path = root / SCENE_CONFIG
    try:
        check_scene_inputs(root, files)
        if cfg_path.is_file():
            limits.check_size(cfg_path, limits.MAX_CONFIG_BYTES, SCENE_CONFIG)
            text = cfg_path.read_text(errors="replace")
            config_digest = text_digest(text)
            config = cached_yaml(text, lambda text: limits.parse_yaml(text, str(cfg_path))) or {}
    except InputError as e:
        raise PipelineError(str(e)) from None
    check_scene_config(config, cfg_path, pipeline)
    return Scene(root, files, config, notes=notes, config_digest=config_digest)


def check_scene_inputs(root: Path, files: dict[str, Path | None]) -> None:
    """The cheap checks of the scene's other user files, before anything is written or hashed: artifacts/ usable, the
    depth's header and the rig mask within limits, a user trajectory readable and within limits. InputError (one
    line) otherwise."""
    from panoworld.io.images import check_depth_file, check_mask_file

    arts = root / ARTIFACTS_DIRNAME
    if arts.is_symlink() and not arts.exists():
        raise InputError(f"{arts}: a dangling symbolic link; remove it (or point it at a directory)")
    if arts.exists() and not arts.is_dir():
        raise InputError(f"{arts}: exists but is not a directory; move it away, the runner keeps its artifacts there")
    for sub in ("logs", VARIANTS_DIRNAME):
        if (arts / sub).is_symlink() or ((arts / sub).exists() and not (arts / sub).is_dir()):
            raise InputError(f"{arts / sub}: a file is where a folder must be; move it away (the runner keeps its "
                             f"{sub} there)")
    if files.get("depth") is not None:
        check_depth_file(files["depth"])
    if files.get("rig_mask") is not None:
        check_mask_file(files["rig_mask"])
    if files.get("trajectory") is not None:
        from panoworld.io.trajectory import read_trajectory_file

        read_trajectory_file(files["trajectory"])


SCENE_CONFIG_KEYS = ("preset", "params")


def check_scene_config(config: Any, path: Path, pipeline: Pipeline) -> None:
    """scene.yaml's schema: {preset: NAME, params: {STAGE: {PARAM: VALUE}}}; PipelineError (one line, with a
    "did you mean") for unknown keys, stages and params and for wrong shapes. Values are checked at resolve time."""
    if not isinstance(config, dict):
        raise PipelineError(f"{path}: expected a mapping with keys 'preset' and/or 'params', got {_short(config)}")
    for key in config:
        if key not in SCENE_CONFIG_KEYS:
            raise PipelineError(f"{path}: unknown key {key!r}{suggest(str(key), SCENE_CONFIG_KEYS)}")
    if config.get("preset") is not None and not isinstance(config["preset"], str):
        raise PipelineError(f"{path}: preset: expected a preset name ({', '.join(pipeline.presets)}), got {_short(config['preset'])}")
    params = config.get("params")
    if params is None:
        return
    from panoworld.framework.stage_params import normalize, shown_name

    if not isinstance(params, dict):
        raise PipelineError(f"{path}: params: expected a mapping of stage: {{param: value}}, got {_short(params)}")
    for stage, values in params.items():
        if stage not in pipeline.stages:
            raise PipelineError(f"{path}: params.{shown_name(str(stage))}: unknown stage"
                                f"{suggest(str(stage), pipeline.order)}")
        if values is None:
            continue
        try:
            normalize(pipeline.stages[stage].spec.params_cls, values, stage)
        except ValueError as e:
            raise PipelineError(f"{path}: {e}") from None


def _short(value: Any) -> str:
    """repr of a user value, shortened (reprlib): a huge or aliased document never makes a huge message."""
    import reprlib

    return reprlib.repr(value)


def input_paths(node: StageNode, scene: Scene) -> dict[str, Path | None]:
    """{input name: the scene file or the upstream artifact folder, None where it is absent (no manifest yet)}."""
    out = {}
    for ref in node.inputs:
        if ref.source == "scene":
            out[ref.name] = scene.files.get(ref.target)
        else:
            d = scene.artifact_dir(ref.target)
            out[ref.name] = d if (d / art.MANIFEST).is_file() else None
    return out
