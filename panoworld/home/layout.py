"""Artifacts of a home: the depth artifact's per-panorama folders and the register artifact's capture points."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.errors import InputError
from panoworld.io.jsonio import read_json
from panoworld.register.inputs import PANORAMAS_JSON

HOME_DIR = "panoramas"
"""A home's depth artifact: panoramas/NAME/{depth.npy, valid.png, panorama.png} per panorama; the top-level files are
those of the first panorama (so a single-panorama reader sees the world-frame panorama)."""
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
