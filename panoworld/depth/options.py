"""The depth stage's choices: metric rescaling and what to do with the capture rig."""

from __future__ import annotations

import enum


class Rescale(enum.StrEnum):
    """When to rescale depth so that the floor lies camera_height below the camera."""

    AUTO = "auto"
    """Relative depth, and provided depth whose floor distance is no plausible capture height (unknown units)."""
    NEVER = "never"
    RELATIVE_ONLY = "relative-only"
    """Only depth without a metric scale (relative monocular models); provided depth is trusted as metric."""
    ALWAYS = "always"
    """Also provided depth (unknown units, e.g. raw sensor values) and metric models."""


class RigMode(enum.StrEnum):
    """What the depth stage does with a capture rig (tripod, mount, nadir mask) at the panorama's nadir."""

    AUTO = "auto"
    """Detect it (no weights: panoworld.depth.rig.detect) and remove it: floor inpainted, depth from the floor plane."""
    KEEP = "keep"
    """Leave the panorama and depth as given (a user rig_mask file is ignored too)."""
