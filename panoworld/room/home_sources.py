"""A home's registered panoramas as the mesh and the Gaussians build on them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.core.parallel import cpu_threads
from panoworld.io.home import load_sources
from panoworld.room.plausible import drop_near_captures


def home_sources(dirs: dict[str, Path], world_from_cam: dict[str, np.ndarray]
                 ) -> tuple[list[str], dict[str, np.ndarray], dict[str, np.ndarray], dict[str, int]]:
    """(registered names in order, cleaned RGB, depth (0 = none), {NAME: pixels dropped}) of a home's depth artifact
    (dirs: NAME -> its per-panorama directory) at the poses world_from_cam (4, 4), a surface through another capture
    point dropped (room.plausible.drop_near_captures, on at most 2 threads)."""
    names, rgbs, depths = load_sources(dirs, world_from_cam)
    return names, rgbs, depths, drop_near_captures(depths, world_from_cam, workers=cpu_threads(2))
