"""Presets and keyword-only parameter dataclasses of the procedural indoor scene generator."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace


class Preset(enum.StrEnum):
    """Named generator settings."""

    CI_TINY = "ci-tiny"
    DEFAULT = "default"


@dataclass(kw_only=True)
class LayoutParams:
    """Floor plan: rooms, walls and doorways."""

    n_rooms: tuple[int, int] = (2, 4)
    """Inclusive range of the number of rooms (1 = a single rectangular or L-shaped room)."""
    room_size_m: tuple[float, float] = (3.0, 6.5)
    """Range of each room's side lengths in metres (before L-shape cut-outs)."""
    l_shape_prob: float = 0.35
    """Probability that a room is L-shaped (a corner rectangle cut away)."""
    ceiling_height_m: tuple[float, float] = (2.6, 3.1)
    """Range of the ceiling height in metres (one value per scene)."""
    door_height_m: tuple[float, float] = (2.15, 2.3)
    """Range of the doorway height in metres (one value per scene)."""
    door_width_m: tuple[float, float] = (1.05, 1.4)
    """Range of doorway widths in metres."""
    wall_thickness_m: float = 0.15
    """Thickness of interior walls in metres (a multiple of cell_m)."""
    cell_m: float = 0.05
    """Size of one floor-plan grid cell in metres; all walls lie on this grid."""


@dataclass(kw_only=True)
class FurnitureParams:
    """Furniture placement."""

    per_room: tuple[int, int] = (3, 7)
    """Inclusive range of the number of furniture placement attempts per room."""
    pictures_per_room: tuple[int, int] = (1, 3)
    """Inclusive range of wall pictures per room."""
    walk_margin_m: float = 0.1
    """Extra free margin kept around furniture footprints beyond the track clearance."""


@dataclass(kw_only=True)
class TrackParams:
    """Ground-truth camera tracks."""

    n_tracks: int = 3
    """Number of tracks per scene."""
    frames: int = 121
    """Frames per track."""
    step_m: float = 0.05
    """Arc length between consecutive frames in metres."""
    camera_height_m: tuple[float, float] = (1.4, 1.7)
    """Range of the camera height above the floor in metres (one value per track)."""
    clearance_m: float = 0.35
    """Minimum 3D distance from every camera centre to any scene geometry in metres."""
    fps: float = 30.0
    """Frame rate used for TUM timestamps."""
    max_attempts: int = 20
    """Waypoint re-draws per track before the scene is rejected."""


@dataclass(kw_only=True)
class RenderParams:
    """Ground-truth renders written into a scene directory."""

    pano_height: int = 720
    """Height of panorama.png / depth.npy (width is twice this)."""
    frame_height: int = 720
    """Height of per-frame renders of the tracks (width is twice this)."""
    supersample: int = 1
    """RGB supersampling factor per axis (1 = off); depth is always the exact centre-ray distance."""
    write_frames: bool = False
    """Write RGB/depth of every track frame into gt/frames (otherwise render on demand with SynthScene.render)."""
    rig: str = "none"
    """Capture rig under the panorama camera: none | tripod | tripod-shadow (panoworld.tools.synth.rig.RigKind). With a
    rig, panorama.png and depth.npy show it; gt/panorama_clean.png, gt/depth_clean.npy and gt/rig_mask.png hold
    the rig-free truth and where the rig is (the scene geometry in gt/ never has it)."""


@dataclass(kw_only=True)
class SynthParams:
    """Everything the generator needs besides the seed."""

    layout: LayoutParams = field(default_factory=LayoutParams)
    """Floor plan parameters."""
    furniture: FurnitureParams = field(default_factory=FurnitureParams)
    """Furniture parameters."""
    tracks: TrackParams = field(default_factory=TrackParams)
    """Camera track parameters."""
    render: RenderParams = field(default_factory=RenderParams)
    """Render parameters."""
    max_scene_attempts: int = 8
    """Scenes re-drawn with derived seeds before generation fails with SceneGenerationError."""


def params_for(preset: Preset | str, *, frames: int | None = None) -> SynthParams:
    """Parameters of a preset, optionally with the frames per track overridden."""
    try:
        preset = Preset(preset)
    except ValueError:
        raise ValueError(f"unknown preset {preset!r}; choose one of {[p.value for p in Preset]}") from None
    if preset is Preset.CI_TINY:
        params = SynthParams(
            layout=LayoutParams(n_rooms=(1, 1), room_size_m=(3.5, 5.0), l_shape_prob=0.5),
            furniture=FurnitureParams(per_room=(3, 5), pictures_per_room=(2, 3)),
            tracks=TrackParams(n_tracks=2, frames=8, step_m=0.08),
            render=RenderParams(pano_height=128, frame_height=128, supersample=1, write_frames=True),
        )
    else:
        params = SynthParams()
    if frames is not None:
        if frames < 1:
            raise ValueError(f"{frames=} but a track needs at least 1 frame")
        params = replace(params, tracks=replace(params.tracks, frames=frames))
    return params
