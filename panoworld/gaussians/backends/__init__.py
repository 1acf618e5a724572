"""Gaussian backends: each turns the registered video frames (and, for a home, its anchored panoramas) into Gaussians.

A backend's impl is `impl(job: Job) -> FusionResult` (panoworld.gaussians.fusion); trait `weights` says whether it needs
trained weights."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass
class Job:
    """What a Gaussian backend works from."""

    frames: Any
    """The registered frames, streamed from disk (panoworld.gaussians.fusion.ContextSource)."""
    options: Any
    """The backend's own options."""
    depth: Path | None = None
    """A home: the depth artifact whose panoramas are anchored (None for a single panorama)."""
    register: Path | None = None
    """A home: the register artifact placing those panoramas."""
    navmesh: Path | None = None
    """The NavMesh artifact (the walkable floor; voxel_fusion.back_sides)."""
    progress: bool = True
    """Show a progress bar on long fusions."""


from panoworld.gaussians.backends import decoder, voxel_fusion  # noqa: E402,F401  (registers them)
