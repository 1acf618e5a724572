"""Trajectory params, path kinds, the Plan record and the planning start shared by the planners."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from panoworld.core.limits import MAX_POSES
from panoworld.core.params import param
from panoworld.geometry.navmesh import NavMesh
from panoworld.trajectory.polyline import resample_polyline


class PathKind(enum.StrEnum):
    """Planned path families of the paper."""

    SECTOR = "sector"
    """Out-and-back petals to the farthest reachable point of each directional sector (covers 360 degrees)."""
    RING = "ring"
    """A closed loop through free space that starts and ends at the camera."""
    EXPLORE = "explore"
    """Sector exploration paths: one path per sector from the camera out towards the room's extent (several paths)."""


class YawMode(enum.StrEnum):
    """Camera orientation along the path (always upright: rotation about the gravity axis only)."""

    FIXED = "fixed"
    """Identity rotation for every pose (the panorama's orientation; ERP covers every direction)."""
    FORWARD = "forward"
    """Yaw follows the (smoothed) direction of travel, relative to the initial heading so pose 0 = identity."""


@dataclass(kw_only=True)
class TrajectoryParams:
    """How a trajectory is planned on a NavMesh (canonical frame, metres)."""

    kind: PathKind = PathKind.EXPLORE
    """Path family: explore (one path per sector out to the room's extent), sector (one path of short out-and-back
    petals, 360 degree coverage) or ring (closed loop)."""
    frames: int = param(81, ge=2, le=MAX_POSES)
    """Number of poses N (pose 0 is the source camera)."""
    step_m: float = param(0.05, gt=0, le=5.0)
    """Distance between consecutive poses at stride 1, in metres."""
    stride: int = param(1, choices=(1, 2, 4))
    """Step multiplier r in {1, 2, 4}: the planned path length is (N - 1) * step_m * stride (ring: N * step)."""
    yaw: YawMode = YawMode.FIXED
    """Camera orientation: fixed (identity) or forward (turns with the path; pose 0 stays identity)."""
    sectors: int = param(8, ge=1)
    """Number of directional sectors visited by sector paths."""
    smooth_iterations: int = param(4, ge=0)
    """Chaikin corner-cutting iterations; a cut that would leave the NavMesh keeps its corner."""
    plan_margin_m: float = param(0.03, ge=0)
    """Paths are planned on the NavMesh shrunk by this margin so smoothing and rounding stay inside it."""
    reach_m: float | None = param(None, gt=0)
    """explore: each sector's path walks at most this far from the camera (its target is the farthest floor within);
    None = no cap: the farthest floor of the sector connected to the camera (the room's extent, bounded by max_step_m)."""
    max_step_m: float = param(0.3, gt=0)
    """explore: when the paths together are longer than (N - 1) * max_step_m, the longest are cut to one common length
    (short sectors keep their whole path) so the step the conditions, video and SfM see stays at most this."""
    seed: int = 0
    """Seed of the candidate points used to find each sector's farthest reachable point."""


@dataclass
class Plan:
    """A planned path: positions (N, 2) x,z with position 0 at the start, and facts about it."""

    positions: np.ndarray
    step_m: float
    """Actual spacing (smaller than requested when the room is too small)."""
    info: dict = field(default_factory=dict)
    exempt: list[int] = field(default_factory=lambda: [0])
    """Poses not held to the NavMesh: the start, and the straight way to the NavMesh when the start is off it."""


def planning_mesh(nav: NavMesh, start: np.ndarray, margin: float) -> NavMesh:
    """The NavMesh shrunk by margin (its piece containing or nearest to the start), or itself if nothing is left."""
    if margin <= 0:
        return nav
    try:
        return nav.offset(-margin, keep_xz=start)
    except ValueError:
        return nav


def planning_hub(nav: NavMesh, start: np.ndarray) -> tuple[np.ndarray, float]:
    """Where planning starts: the start itself, or the nearest NavMesh point (and its distance)."""
    if nav.contains(start)[0]:
        return start.copy(), 0.0
    hub = nav.closest_point(start)[0]
    return hub, float(np.linalg.norm(hub - start))


MAX_APPROACH_SHARE = 0.1
"""At most this share of a path's steps walks a camera that stands off the NavMesh onto it (in longer steps)."""


def approach_path(start: np.ndarray, hub: np.ndarray, step: float, n_steps: int) -> np.ndarray:
    """The straight way from the start to the hub, (k + 1, 2) with k steps of `step`, but never more than
    MAX_APPROACH_SHARE of n_steps (the steps are longer then: a rig hiding 1 m of floor costs 8 of 81 poses)."""
    off = float(np.linalg.norm(np.asarray(hub) - np.asarray(start)))
    if off <= 0:
        return np.asarray(start, np.float64)[None]
    k = max(1, min(int(np.ceil(off / step)), int(MAX_APPROACH_SHARE * n_steps)))
    return resample_polyline(np.stack([start, hub]), k + 1)
