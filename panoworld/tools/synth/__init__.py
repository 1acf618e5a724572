"""Procedural indoor scenes with exact ground truth: meshes, ERP RGB/depth renders and camera tracks."""

from panoworld.tools.synth.appearance import Light, Material, MaterialKind
from panoworld.tools.synth.generate import SceneGenerationError, derive_seed, generate_scene
from panoworld.tools.synth.params import (
    FurnitureParams,
    LayoutParams,
    Preset,
    RenderParams,
    SynthParams,
    TrackParams,
    params_for,
)
from panoworld.tools.synth.scene import SynthScene
from panoworld.tools.synth.tracks import Track
from panoworld.tools.synth.write import write_scene

__all__ = [
    "FurnitureParams", "LayoutParams", "Light", "Material", "MaterialKind", "Preset", "RenderParams",
    "SceneGenerationError", "SynthParams", "SynthScene", "Track", "TrackParams", "derive_seed", "generate_scene",
    "params_for", "write_scene",
]
