"""Artifacts of a home: the depth artifact's per-panorama folders, the register artifact's capture points, the mesh
artifact's sources."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.core.conventions import pose_from_rt
from panoworld.core.errors import InputError
from panoworld.io.jsonio import read_json, write_json

PANORAMAS_JSON = "panoramas.json"
"""The register artifact's {NAME: 4x4 world_from_cam} of the registered panoramas."""


HOME_MESH_JSON = "home.json"
"""In a home's mesh artifact: {"sources": [{name, world_from_cam, vertex_start, grid: [h, w], near_capture_px (its
pixels dropped as a surface through another capture point)}]}; the fused mesh's
vertices are each source's ERP grid (h * w + 2 poles, world frame) one after the other."""
HOME_DIR = "panoramas"
"""A home's depth artifact: panoramas/NAME/{depth.npy, valid.png, panorama.png} per panorama; the top-level files are
those of the first panorama (so a single-panorama reader sees the world-frame panorama)."""
RIG_MASK_PNG = "rig_mask.png"
"""In a depth artifact's folder (top level or panoramas/NAME/): the detected or given capture rig (ERP, white = rig),
written only where a rig was found."""
HOME_INFO = "home"
"""The depth manifest's info key listing the home's panoramas: {"names": [...], "dirs": {NAME: relative dir}}."""


def home_depth_dirs(depth_artifact: Path) -> dict[str, Path] | None:
    """{NAME: directory holding depth.npy, valid.png, panorama.png} of a home's depth artifact, in name order; None
    for a single-panorama depth artifact."""
    depth_artifact = Path(depth_artifact)
    info = read_json(depth_artifact / "manifest.json", default={}).get("info", {}).get(HOME_INFO)
    if not info:
        return None
    return {n: depth_artifact / info["dirs"][n] for n in info["names"]}


def _levels(depth_artifact: Path) -> dict[str, dict]:
    """{NAME: the depth manifest's info.level} of the panoramas the depth stage levelled (a single panorama's as
    "panorama")."""
    info = read_json(Path(depth_artifact) / "manifest.json", default={}).get("info", {})
    home = info.get(HOME_INFO)
    each = home.get("panoramas", {}) if isinstance(home, dict) else {"panorama": info}
    return {n: lev for n, i in each.items()
            if isinstance(i, dict) and isinstance(lev := i.get("level"), dict) and lev.get("level_from_cam")}


def levelled_panoramas(depth_artifact: Path) -> dict[str, np.ndarray]:
    """{NAME: (3, 3) level_from_cam} of the panoramas the depth stage levelled (taken off level; the depth manifest's
    info.level, per panorama of a home), a single panorama's as "panorama"; {} when none was (or no manifest)."""
    return {n: np.asarray(lev["level_from_cam"], np.float64) for n, lev in _levels(depth_artifact).items()}


def to_levelled(world_from_cam: dict[str, np.ndarray], level_from_cam: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """{NAME: (4, 4)} poses of the cameras as taken turned to their levelled cameras' where a levelling (3, 3) is
    given (world_from_levelled = world_from_cam @ cam_from_levelled); the others as they are."""
    return {n: T @ pose_from_rt(level_from_cam[n].T, np.zeros(3)) if n in level_from_cam else T
            for n, T in world_from_cam.items()}


def level_note(depth_artifact: Path) -> str | None:
    """"taken off level: pano_01 2.0°, ...; levelled, the scene is built level (docs/conventions.md)" when the depth
    stage levelled any panorama; None otherwise."""
    tilts = [f"{n} {float(lev.get('tilt_deg', 0.0)):.1f}°" for n, lev in _levels(depth_artifact).items()]
    if not tilts:
        return None
    return f"taken off level: {first_few(tilts)}; levelled, the scene is built level (docs/conventions.md)"


def first_few(items: list[str], k: int = 5) -> str:
    """The first k items joined by commas, "+N more" after them when there are more (a note's list of panoramas)."""
    return ", ".join(items[:k]) + (f" +{len(items) - k} more" if len(items) > k else "")


def capture_poses(register_artifact: Path | None) -> dict[str, np.ndarray]:
    """{NAME: world_from_cam (4, 4)} of the registered panoramas (register artifact's panoramas.json); {} without
    one. A single-panorama scene has one capture point, the identity."""
    if register_artifact is None:
        return {}
    path = Path(register_artifact) / PANORAMAS_JSON
    try:
        doc = read_json(path)
        return {n: np.asarray(T, np.float64).reshape(4, 4) for n, T in doc.items()}
    except (OSError, ValueError, TypeError) as e:
        raise InputError(f"{path}: cannot read the capture poses ({e}); rerun the register stage") from None


def is_home(register_artifact: Path | None) -> bool:
    """Whether the register artifact places two or more panoramas (a home rather than one panorama)."""
    return len(capture_poses(register_artifact)) >= 2


def load_sources(dirs: dict[str, Path], world_from_cam: dict[str, np.ndarray]
                 ) -> tuple[list[str], dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(registered names in order, cleaned RGB, depth with invalid pixels 0) of the home's panoramas."""
    from panoworld.io.depth import load_depth_artifact  # cv2

    names = [n for n in dirs if n in world_from_cam]
    rgbs, depths = {}, {}
    for n in names:
        depth, valid, rgb = load_depth_artifact(dirs[n])
        depths[n], rgbs[n] = np.where(valid, depth, 0.0).astype(np.float32), rgb
    return names, rgbs, depths


def write_home_mesh_info(out_dir: Path, sources: list[dict]) -> None:
    write_json(Path(out_dir) / HOME_MESH_JSON, {"sources": sources})


def read_home_sources(mesh_artifact: Path) -> list[dict] | None:
    """The sources of a home's mesh artifact (HOME_MESH_JSON), None for a single panorama's mesh."""
    doc = read_json(Path(mesh_artifact) / HOME_MESH_JSON, default=None)
    return None if doc is None else doc["sources"]
