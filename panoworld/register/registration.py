"""The result of registering a home's panoramas: poses and what each rests on."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(kw_only=True)
class Registration:
    """Poses in the first registered panorama's frame and what each estimate rests on."""

    world_from_cam: dict[str, np.ndarray]
    """Registered panoramas only."""
    panoramas: dict[str, dict]
    """Per panorama: registered, source ('given' / 'estimated' / None), parent, inliers, overlap, consistency,
    residual (of the edge that placed it), reason when not registered."""
    pairs: list[dict] = field(default_factory=list)
    """Every pair tried: names, matches, inliers, overlap, consistency, residual, accepted."""
