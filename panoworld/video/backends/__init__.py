"""Video backends: each fills the disoccluded pixels of the warped conditions, frame by frame.

A backend's impl is `impl(job: Job) -> (frames, info)`: `frames` yields (rgb, depth or None, fill or None) per pose,
`info` is merged into the manifest; trait `has_depth` says whether it yields depth, trait `renders_plan` whether every
frame is rendered exactly at its planned pose (the poses stage's auto then takes the plan instead of recovering it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class Job:
    """What a video backend works from."""

    cond: Any
    """The conditions (panoworld.io.conditions.load_conditions)."""
    poses: np.ndarray
    """(N, 4, 4) world_from_camera of the trajectory."""
    mesh_dir: Path | None
    """The mesh artifact the conditions were rendered from (None when not given)."""
    options: Any
    """The backend's own options (None for a backend without options)."""
    inpaint_radius: float
    """Telea inpainting radius in pixels (shared by the backends that inpaint in 2D)."""
    clips: list[list[int]] = field(default_factory=list)
    """Pose indices of each clip (one per path of a multi-path trajectory, panoworld.trajectory.load_clips); empty =
    one clip of every pose. Clip generators (wan-shortcut) generate each alone; frame-by-frame backends ignore it."""


from panoworld.video.backends import frame_inpaint, wan_shortcut, warp_inpaint  # noqa: E402,F401  (registers them)
