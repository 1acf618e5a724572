"""Camera trajectories on a NavMesh: sector and ring planning, smoothing, uniform re-parameterisation, I/O, validation."""

from panoworld.trajectory.common import (
    FRAME,
    TRAJECTORY_JSON,
    TRAJECTORY_TUM,
    PathKind,
    Plan,
    TrajectoryFileError,
    TrajectoryParams,
    YawMode,
    planning_hub,
    planning_mesh,
)
from panoworld.trajectory.explore import plan_explore, sector_extent
from panoworld.trajectory.files import (
    check_poses,
    load_clips,
    load_trajectory,
    read_trajectory_doc,
    read_trajectory_file,
    read_tum,
    write_trajectory,
    write_tum,
)
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
    path_indices,
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
    "CLEARANCE_CAP_M", "FRAME", "GeodesicField", "MIN_SECTOR_DIST_M", "TRAJECTORY_JSON", "TRAJECTORY_TUM", "PathKind", "Plan", "PoseIssue",
    "TrajectoryFileError", "TrajectoryParams", "YawMode", "check_poses", "clearance_cap", "format_issues",
    "load_clips", "load_trajectory", "read_trajectory_doc", "mesh_clearance", "path_indices", "path_yaw", "plan_explore", "plan_path", "plan_ring", "plan_sector", "planning_hub", "planning_mesh",
    "polyline_length", "poses_from_positions", "read_trajectory_file", "read_tum", "resample_polyline",
    "sector_coverage", "sector_extent", "sector_of", "sector_reach", "sector_reachability", "smooth_polyline", "step_lengths", "subdivide_polyline",
    "truncate_polyline", "validate_poses", "write_trajectory", "write_tum", "yaw_of_path",
]
