"""Pose backends: each estimates per-frame canonical poses of the video.

A backend's impl is `impl(job: Job) -> PoseEstimate` (panoworld.poses.estimate); trait `needs_plan` says whether it needs the
planned poses whatever the alignment (without it, only alignment none works without a plan)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class Job:
    """What a pose backend works from."""

    video: Any
    """The video frames (panoworld.io.video.read_video_frames)."""
    planned: np.ndarray | None
    """(N, 4, 4) planned world_from_camera, or None."""
    align: Any
    """How estimates enter the canonical frame (panoworld.poses.options.Alignment)."""
    options: Any
    """The backend's own options (None for a backend without options)."""


from panoworld.poses.backends import colmap, planned, vggt  # noqa: E402,F401  (registers them)
