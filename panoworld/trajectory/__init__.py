"""Camera trajectories on a NavMesh: sector and ring planning, smoothing, uniform re-parameterisation, validation (files: panoworld.io.trajectory)."""

from panoworld.trajectory.common import (
    PathKind,
    Plan,
    TrajectoryParams,
    YawMode,
    planning_hub,
    planning_mesh,
)
from panoworld.trajectory.explore import plan_explore, sector_extent
from panoworld.trajectory.plan import plan_path
from panoworld.trajectory.polyline import (
    polyline_length,
    resample_polyline,
    smooth_polyline,
    subdivide_polyline,
    truncate_polyline,
)
from panoworld.trajectory.poses import (
    CLEARANCE_CAP_M,
    PoseIssue,
    clearance_cap,
    format_issues,
    mesh_clearance,
    path_yaw,
    poses_from_positions,
    step_lengths,
    validate_poses,
    yaw_of_path,
)
from panoworld.trajectory.ring import plan_ring
from panoworld.trajectory.sectors import (
    MIN_SECTOR_DIST_M,
    GeodesicField,
    plan_sector,
    sector_coverage,
    sector_of,
    sector_reach,
    sector_reachability,
)

__all__ = [
    "CLEARANCE_CAP_M", "GeodesicField", "MIN_SECTOR_DIST_M", "PathKind", "Plan", "PoseIssue",
    "TrajectoryParams", "YawMode", "clearance_cap", "format_issues",
    "mesh_clearance", "path_yaw", "plan_explore", "plan_path", "plan_ring", "plan_sector", "planning_hub", "planning_mesh",
    "polyline_length", "poses_from_positions", "resample_polyline",
    "sector_coverage", "sector_extent", "sector_of", "sector_reach", "sector_reachability", "smooth_polyline", "step_lengths", "subdivide_polyline",
    "truncate_polyline", "validate_poses", "yaw_of_path",
]
