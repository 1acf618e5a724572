"""The multi-panorama scene layout (SCENE/panoramas/NAME.*, SCENE/depths/NAME.*, SCENE/poses.json) and its checks."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from panoworld.core import limits
from panoworld.core.errors import InputError

PANORAMAS_DIR = "panoramas"
DEPTHS_DIR = "depths"
POSES_FILE = "poses.json"
REGISTRATION_JSON = "registration.json"
"""The register artifact's per-panorama quality figures and every pair tried."""
PANORAMA_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".npy", ".exr", ".png")
RIG_MASKS_DIR = "rig_masks"
RIG_MASK_SUFFIXES = (".png",)
SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")
"""A panorama's name (its file stem; also the name of its folders in the artifacts): letters, digits, `_`, `.`, `-`,
not starting with `.` or `-`, at most 128 characters, unique ignoring case across the suffixes."""
MAX_HOME_PANORAMAS = 1000
"""Most panoramas in a home (registration tries a bounded number of pairs per panorama; docs/real_inputs.md#limits)."""


def list_named(folder: Path, suffixes: tuple[str, ...], what: str) -> tuple[dict[str, Path], list[Path]]:
    """({NAME: file} of folder's files with one of suffixes, other entries ignored, as are macOS's AppleDouble files
    `._NAME` that some disks hold beside each file); InputError (one line naming the file) for a name outside SAFE_NAME
    or two files of one name (a.png and A.jpg)."""
    named: dict[str, Path] = {}
    seen: dict[str, Path] = {}
    other: list[Path] = []
    for p in sorted(Path(folder).iterdir()):
        if p.suffix.lower() not in suffixes or limits.is_appledouble(p):
            other.append(p)
            continue
        stem = p.name[: -len(p.suffix)]
        if not SAFE_NAME.fullmatch(stem):
            raise InputError(f"{p}: {what} name {stem!r} is not a safe name; rename it to letters, digits, '_', '.', '-' "
                             "(not starting with '.' or '-', at most 128 characters)")
        if stem.lower() in seen:
            raise InputError(f"{p}: {what} name {stem!r} is also {seen[stem.lower()].name}; give each {what} its own "
                             "name (names are compared ignoring case and suffix)")
        seen[stem.lower()] = p
        named[stem] = p
    return named, other


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
    rig_masks: dict[str, Path] = field(default_factory=dict)
    """Rig mask of each name that has one."""
    ignored: list[Path] = field(default_factory=list)
    """Files in panoramas/, depths/ and rig_masks/ that are none of the home's inputs (left out of its digests)."""


def is_multi_scene(scene: Path) -> bool:
    """Whether scene holds a panoramas/ directory (the multi-panorama layout)."""
    return (Path(scene) / PANORAMAS_DIR).is_dir()


def find_multi_scene(scene: Path) -> MultiScene:
    """The panoramas, depths, rig masks and poses file of scene (find_home_files)."""
    scene = Path(scene)
    home = find_home_files(scene / PANORAMAS_DIR, scene / DEPTHS_DIR, scene / RIG_MASKS_DIR)
    poses = scene / POSES_FILE
    home.poses = poses if poses.is_file() else None
    return home


def check_home(scene: Path) -> MultiScene:
    """find_multi_scene, then every depth and rig mask checked from its header (size, format, minimum size) and
    poses.json read with its limits: all before anything is hashed or run; InputError (one line) otherwise."""
    from panoworld.io.images import check_depth_file, check_mask_file

    home = find_multi_scene(scene)
    for path in home.depths.values():
        check_depth_file(path)
    for path in home.rig_masks.values():
        check_mask_file(path)
    if home.poses is not None:
        read_poses(home.poses, home.names)
    return home


def find_home_files(pano_dir: Path, depth_dir: Path | None = None, mask_dir: Path | None = None) -> MultiScene:
    """The panoramas, depths and rig masks of a home; InputError (naming the file and the fix) for no
    panorama, more than MAX_HOME_PANORAMAS, an unsafe or repeated name, a depth or mask of no panorama."""
    pano_dir = Path(pano_dir)
    panos, ignored = list_named(pano_dir, PANORAMA_SUFFIXES, "panorama")
    if not panos:
        held = [p.name + "/" * p.is_dir() for p in ignored]
        what = f" among {', '.join(held[:3])}{' ...' if len(held) > 3 else ''}" if held else ""
        raise InputError(f"{pano_dir}: found no panorama{what}; put NAME.png/.jpg there, at its top level "
                         "(a single panorama may also go in SCENE/panorama.png)")
    if len(panos) > MAX_HOME_PANORAMAS:
        raise InputError(f"{pano_dir}: {len(panos)} panoramas, over the limit of {MAX_HOME_PANORAMAS}; split the home "
                         "(docs/real_inputs.md#limits)")
    extra: list[dict[str, Path]] = []
    for folder, suffixes, what in ((depth_dir, DEPTH_SUFFIXES, "depth"), (mask_dir, RIG_MASK_SUFFIXES, "rig mask")):
        if folder is None or not Path(folder).is_dir():
            extra.append({})
            continue
        files, other = list_named(Path(folder), suffixes, what)
        ignored += other
        if orphans := sorted(set(files) - set(panos)):
            raise InputError(f"{files[orphans[0]]}: {what} of no panorama in {pano_dir}; name each {what} after its "
                             "panorama's file stem (NAME.png -> NAME" + suffixes[0] + ")")
        extra.append(files)
    return MultiScene(names=sorted(panos), panoramas=panos, depths=extra[0], rig_masks=extra[1], poses=None,
                      ignored=ignored)


def read_poses(path: Path, names: list[str], *, tol: float = 1e-4) -> dict[str, np.ndarray]:
    """{NAME: 4x4 world_from_cam} from path, checked before use: at most MAX_POSES_JSON_BYTES, nesting within
    limits, a JSON object keyed by panorama names, 4 rows of 4 numbers (never strings or booleans), finite, rigid
    (orthonormal rotation with det +1 within tol, last row 0 0 0 1), each capture point within MAX_TRANSLATION_M of
    the first one's; InputError naming the file and the fix."""
    path = Path(path)
    try:
        limits.check_size(path, limits.MAX_POSES_JSON_BYTES, POSES_FILE)
        text = path.read_text(errors="replace")
    except OSError as e:
        raise InputError(f"{path}: cannot read it ({e.strerror}); write {{NAME: 4x4 world_from_cam}}") from None
    doc = limits.parse_json(text, str(path), max_nesting=4)
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"{path}: expected a JSON object {{NAME: 4x4 world_from_cam}}")
    unknown = sorted(set(doc) - set(names))
    if unknown:
        shown = ", ".join(repr(u[:40]) for u in unknown[:3]) + (f" (+{len(unknown) - 3} more)" if len(unknown) > 3 else "")
        raise InputError(f"{path}: poses for {shown} but no such panoramas in panoramas/ ({len(names)} panoramas, "
                         f"e.g. {names[0]!r}); key each pose by its panorama's file stem")
    out = {}
    for name, value in doc.items():
        rows = value if isinstance(value, list) and len(value) == 4 else None
        if rows is None or not all(isinstance(r, list) and len(r) == 4 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in r) for r in rows):
            raise InputError(f"{path}: pose of {name!r} is not a 4x4 matrix of numbers; give world_from_cam as 4 rows "
                             "of 4 numbers")
        T = np.asarray(rows, dtype=np.float64)
        if not np.isfinite(T).all():
            raise InputError(f"{path}: pose of {name!r} has NaN or infinite entries; give finite numbers")
        R = T[:3, :3]
        if (np.abs(R.T @ R - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1) > tol
                or np.abs(T[3] - [0, 0, 0, 1]).max() > tol):
            raise InputError(f"{path}: pose of {name!r} is not rigid (rotation orthonormal with det +1, last row "
                             "0 0 0 1); give world_from_cam in metres without scale")
        out[name] = T
    first = min(out)
    for name, T in out.items():
        far = float(np.linalg.norm(T[:3, 3] - out[first][:3, 3]))
        if far > limits.MAX_TRANSLATION_M:
            raise limits.LimitError(f"{path}: capture point of {name!r} is {far:.3g} m from {first!r}'s, beyond the "
                                    f"{limits.MAX_TRANSLATION_M:.0f} m limit for a home; give translations in metres")
    return out
