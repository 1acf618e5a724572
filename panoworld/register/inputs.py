"""The multi-panorama scene layout (SCENE/panoramas/NAME.*, SCENE/depths/NAME.*, SCENE/poses.json) and its checks."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.core.errors import InputError

PANORAMAS_DIR = "panoramas"
DEPTHS_DIR = "depths"
POSES_FILE = "poses.json"
REGISTRATION_JSON = "registration.json"
"""The register artifact's per-panorama quality figures and every pair tried."""
PANORAMA_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".npy", ".exr", ".png")


@dataclass(kw_only=True)
class MultiScene:
    """The files of a multi-panorama scene, in name order (the first name is the world frame)."""

    names: list[str]
    """Panorama names (file stems), sorted."""
    panoramas: dict[str, Path]
    """Panorama file of each name."""
    depths: dict[str, Path]
    """Depth file of each name that has one."""
    poses: Path | None
    """SCENE/poses.json when present."""


def is_multi_scene(scene: Path) -> bool:
    """Whether scene holds a panoramas/ directory (the multi-panorama layout)."""
    return (Path(scene) / PANORAMAS_DIR).is_dir()


def find_multi_scene(scene: Path) -> MultiScene:
    """The panoramas, depths and poses file of scene; InputError (naming the fix) when fewer than 2 panoramas."""
    scene = Path(scene)
    pano_dir = scene / PANORAMAS_DIR
    panos = {p.stem: p for p in sorted(pano_dir.glob("*")) if p.suffix.lower() in PANORAMA_SUFFIXES}
    if len(panos) < 2:
        raise InputError(f"{pano_dir}: found {len(panos)} panoramas; put two or more NAME.png/.jpg there "
                         "(a single panorama goes in SCENE/panorama.png)")
    depths = {}
    for name in panos:
        found = [scene / DEPTHS_DIR / f"{name}{s}" for s in DEPTH_SUFFIXES if (scene / DEPTHS_DIR / f"{name}{s}").is_file()]
        if found:
            depths[name] = found[0]
    poses = scene / POSES_FILE
    return MultiScene(names=sorted(panos), panoramas=panos, depths=depths, poses=poses if poses.is_file() else None)


def read_poses(path: Path, names: list[str], *, tol: float = 1e-4) -> dict[str, np.ndarray]:
    """{NAME: 4x4 world_from_cam} from path, checked: JSON object, every key a panorama, rigid 4x4 rows
    (orthonormal rotation with det +1 within tol, last row 0 0 0 1), finite; InputError naming the file and the fix."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read it as JSON ({e}); write {{NAME: 4x4 world_from_cam}}") from None
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"{path}: expected a JSON object {{NAME: 4x4 world_from_cam}}")
    unknown = sorted(set(doc) - set(names))
    if unknown:
        raise InputError(f"{path}: poses for {unknown} but no such panoramas in panoramas/ (have {names}); "
                         "key each pose by its panorama's file stem")
    out = {}
    for name, value in doc.items():
        try:
            T = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            T = np.zeros(0)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise InputError(f"{path}: pose of {name!r} is not a finite 4x4 matrix; give world_from_cam as 4 rows of 4")
        R = T[:3, :3]
        if (np.abs(R.T @ R - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1) > tol
                or np.abs(T[3] - [0, 0, 0, 1]).max() > tol):
            raise InputError(f"{path}: pose of {name!r} is not rigid (rotation orthonormal with det +1, last row "
                             "0 0 0 1); give world_from_cam in metres without scale")
        out[name] = T
    return out
