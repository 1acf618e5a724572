"""Pose backends: each estimates per-frame canonical poses of the video.

A backend's impl is `impl(job: Job) -> PoseEstimate` (panoworld.poses.estimate); trait `needs_plan` says whether it needs
the planned poses whatever the alignment (without it, only alignment none works without a plan), `recovers` whether
it estimates poses from the frames (rather than copying the plan), `weights` whether it needs its options' weights."""

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


def pick(name: str, video_backend: str | None, params: Any) -> tuple[Any, list[str]]:
    """The backend `name` stands for (auto: choose_auto) and the decisions to record."""
    from panoworld.core import registry as backends

    if name != "auto":
        return backends.get("poses", name), []
    backend, why = choose_auto(video_backend, params)
    return backend, [f"backend auto: {backend.name} ({why})"]


def choose_auto(video_backend: str | None, params: Any) -> tuple[Any, str]:
    """The backend `auto` stands for, and why: the plan's copier when the video backend renders every frame at its
    planned pose (trait renders_plan), else a recovering backend whose weights are given, else one needing none."""
    from panoworld.core import registry as backends

    video = backends.backends("video").get(video_backend) if video_backend else None
    poses = backends.backends("poses").values()
    if video is not None and video.traits.get("renders_plan"):
        return (backends.with_trait("poses", "copies_plan"),
                f"video backend {video.name} renders every frame at its planned pose")
    origin = f"video backend {video.name}" if video is not None else f"unknown video backend {video_backend!r}"
    for b in poses:
        if b.traits.get("recovers") and b.traits.get("weights") and getattr(b.options_of(params), "weights", None):
            return b, f"{origin} does not follow the plan exactly; {b.name} weights given"
    b = next(b for b in poses if b.traits.get("recovers") and not b.traits.get("weights"))
    return b, f"{origin} does not follow the plan exactly"


from panoworld.poses.backends import colmap, planned, vggt  # noqa: E402,F401  (registers them)
