"""Depth backends: each gives ERP depth and validity for the (working-size) panorama.

A backend's impl is `impl(job: Job) -> Result`; trait `needs_inputs` names the stage inputs it requires (backend auto
takes the first registered backend whose inputs are all given); trait `preflight(job)` (job.rgb None)
raises the refusal the impl would, without working (a home's panoramas are all checked before any is worked on)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class Job:
    """What a depth backend works from."""

    rgb: np.ndarray | None
    """(H, W, 3) uint8 panorama at the working size (None in a backend's preflight)."""
    depth_file: Path | None
    """The scene's depth file (None when not given)."""
    panorama_file: Path
    options: Any
    """The backend's own options."""
    depth_hint: str = "put a metric depth.npy|exr|png next to the panorama"
    """Where the user would give this panorama's depth (for an error message)."""
    notes: list[str] = field(default_factory=list)
    """Decisions worth telling the user (appended to)."""


@dataclass
class Result:
    depth: np.ndarray
    """(H, W) float depth (metres, or relative when `relative`)."""
    valid: np.ndarray
    """(H, W) bool."""
    relative: bool
    """Depth without a metric scale (a relative monocular model)."""
    info: dict = field(default_factory=dict)


from panoworld.depth.backends import depth_anything, provided  # noqa: E402,F401  (registers them; order = auto's)
