"""Trajectory files: trajectory.json, TUM text, user trajectories and their checks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from panoworld.core import conventions, limits
from panoworld.core.conventions import (
    quat_wxyz_from_rotmat,
    quat_wxyz_from_xyzw,
    quat_xyzw_from_wxyz,
    rotmat_from_quat_wxyz,
)
from panoworld.core.errors import InputError

TRAJECTORY_JSON = "trajectory.json"
TRAJECTORY_TUM = "trajectory.tum"
FRAME = "canonical (pose 0 = identity)"


class TrajectoryFileError(InputError):
    """A trajectory file cannot be read or holds no valid SE(3) poses."""


def path_indices(path: dict) -> list[int]:
    """Pose indices of one path of a multi-path trajectory: its predecessor (`from`, default pose 0) and [start, stop).
    A path whose `from` is its own start has no predecessor (it starts there: a home's cut between floors)."""
    prev = int(path.get("from", 0))
    return ([prev] if path["start"] > 0 and prev != path["start"] else []) + list(range(path["start"], path["stop"]))


def check_poses(poses: np.ndarray, where: str = "poses") -> np.ndarray:
    """conventions.check_poses raising TrajectoryFileError (a trajectory file's poses)."""
    try:
        return conventions.check_poses(poses, where)
    except InputError as e:
        raise TrajectoryFileError(str(e)) from None


def read_tum(path: Path) -> np.ndarray:
    """TUM text `timestamp tx ty tz qx qy qz qw` (one pose a line, # comments) -> world_from_cam (N, 4, 4)."""
    rows = []
    for k, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise TrajectoryFileError(f"{path}:{k}: {len(parts)} values but TUM lines are 'timestamp tx ty tz qx qy qz qw'")
        try:
            rows.append([float(x) for x in parts])
        except ValueError:
            raise TrajectoryFileError(f"{path}:{k}: not numbers: {line[:60]!r}") from None
    if not rows:
        raise TrajectoryFileError(f"{path}: no poses")
    a = np.asarray(rows)
    q = quat_wxyz_from_xyzw(a[:, 4:8])
    norm = np.linalg.norm(q, axis=1)
    if (np.abs(norm - 1) > 1e-3).any():
        k = int(np.flatnonzero(np.abs(norm - 1) > 1e-3)[0])
        raise TrajectoryFileError(f"{path}: pose {k} has a quaternion of norm {norm[k]:.4f}, not 1")
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, :3] = rotmat_from_quat_wxyz(q)
    T[:, :3, 3] = a[:, 1:4]
    return T


def write_tum(path: Path, poses: np.ndarray, fps: float) -> None:
    q = quat_xyzw_from_wxyz(quat_wxyz_from_rotmat(poses[:, :3, :3]))
    lines = ["# timestamp tx ty tz qx qy qz qw  (world_from_cam, canonical frame: pose 0 = identity; OpenCV camera axes)"]
    for i, (T, qi) in enumerate(zip(poses, q)):
        t = T[:3, 3]
        lines.append(f"{i / fps:.6f} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {qi[0]:.9f} {qi[1]:.9f} {qi[2]:.9f} {qi[3]:.9f}")
    Path(path).write_text("\n".join(lines) + "\n")


def read_trajectory_file(path: Path) -> np.ndarray:
    """A user trajectory: JSON ({"poses": [4x4, ...]} or a plain list of 4x4) or TUM text -> (N, 4, 4), within the
    limits of panoworld.core.limits (file size, pose count, nesting, translations)."""
    path = Path(path)
    try:
        limits.check_size(path, limits.MAX_TRAJECTORY_BYTES, "trajectory file")
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise TrajectoryFileError(f"{path}: unreadable ({e})") from None
    except InputError as e:
        raise TrajectoryFileError(str(e)) from None
    if path.suffix.lower() == ".json" or text.lstrip().startswith(("{", "[")):
        try:
            data = limits.parse_json(text, str(path), max_nesting=8)
        except InputError as e:
            raise TrajectoryFileError(str(e)) from None
        if isinstance(data, dict):
            if "poses" not in data:
                raise TrajectoryFileError(f"{path}: JSON object without a 'poses' list of 4x4 world_from_cam matrices")
            data = data["poses"]
        if isinstance(data, list) and len(data) > limits.MAX_POSES:
            raise TrajectoryFileError(f"{path}: {len(data)} poses, over the limit of {limits.MAX_POSES}; give a shorter trajectory")
        poses = check_poses(data, str(path))
    else:
        poses = check_poses(read_tum(path), str(path))
    try:
        limits.check_poses_range(poses, str(path))
    except InputError as e:
        raise TrajectoryFileError(str(e)) from None
    return poses


def load_trajectory(path: Path | str) -> np.ndarray:
    """world_from_cam poses (N, 4, 4) from a trajectory artifact directory, trajectory.json or a TUM file."""
    path = Path(path)
    if path.is_dir():
        path = path / TRAJECTORY_JSON
    return read_trajectory_file(path)


def read_trajectory_doc(path: Path | str, *, missing_ok: bool = False) -> dict:
    """The whole trajectory.json document (poses and metadata: fps, paths, kind, ...) of a trajectory artifact
    directory or file; {} for a TUM file (no metadata), and for a missing one when missing_ok."""
    path = Path(path)
    doc_path = path / TRAJECTORY_JSON if path.is_dir() else path
    if doc_path.suffix.lower() != ".json" or (missing_ok and not doc_path.is_file()):
        return {}
    try:
        doc = limits.parse_json(doc_path.read_text(), str(doc_path), max_nesting=8)
    except (OSError, UnicodeDecodeError) as e:
        raise TrajectoryFileError(f"{doc_path}: unreadable ({e}); rerun the trajectory stage") from None
    except InputError as e:
        raise TrajectoryFileError(str(e)) from None
    return doc if isinstance(doc, dict) else {"poses": doc}


def load_clips(path: Path | str, n_poses: int) -> list[list[int]]:
    """Pose indices of each clip of a trajectory artifact (directory or trajectory.json): one per path of a multi-path
    trajectory (its predecessor and its own poses, see path_indices), else one clip of all n_poses poses."""
    path = Path(path)
    doc_path = path / TRAJECTORY_JSON if path.is_dir() else path
    paths = read_trajectory_doc(path, missing_ok=True).get("paths")
    if not isinstance(paths, list) or not paths:
        return [list(range(n_poses))]
    clips = [path_indices(p) for p in paths]
    if sorted({i for c in clips for i in c}) != list(range(n_poses)):
        raise TrajectoryFileError(f"{doc_path}: its paths do not cover the {n_poses} poses exactly; rerun the trajectory stage")
    return clips


def write_trajectory(out_dir: Path, poses: np.ndarray, clearance: np.ndarray, *, fps: float, **meta) -> list[str]:
    """Write trajectory.json ({"poses", "clearance_m", "frame", "fps", **meta}) and trajectory.tum."""
    out_dir = Path(out_dir)
    doc = {
        "poses": np.asarray(poses, np.float64).tolist(),
        "clearance_m": np.asarray(clearance, np.float64).round(6).tolist(),
        "frame": FRAME,
        "convention": "world_from_cam 4x4, OpenCV camera axes (x right, y down, z forward), world up = -Y, metres",
        "fps": fps,
        **meta,
    }
    (out_dir / TRAJECTORY_JSON).write_text(json.dumps(doc))
    write_tum(out_dir / TRAJECTORY_TUM, poses, fps)
    return [TRAJECTORY_JSON, TRAJECTORY_TUM]
