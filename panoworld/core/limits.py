"""Limits on user inputs and the readers that enforce them before allocating (JSON/YAML nesting, .npy headers, sizes)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from panoworld.core.errors import InputError

MAX_PIXELS = 16384 * 8192
"""Largest image or depth map (width x height): a 16K panorama; larger ones are refused before decoding."""
MAX_POSES = 10_000
"""Most poses in a user trajectory (the paper's clips are 81; 10 000 frames render for days on a GPU)."""
MAX_TRANSLATION_M = 1000.0
"""Largest |translation| of a user pose in metres (indoor scenes are tens of metres; the NavMesh check refines it)."""
MAX_TRAJECTORY_BYTES = 16 * 2**20
"""Largest user trajectory file (10 000 poses as JSON at full precision take about 4 MB)."""
MAX_CONFIG_BYTES = 2**20
"""Largest scene.yaml."""
MAX_NESTING = 32
"""Deepest nesting of lists/objects in a user JSON or YAML file (a trajectory needs 3)."""


class LimitError(InputError):
    """A user input beyond a documented limit (size, count, nesting, value range)."""


def _depth(doc: Any, limit: int) -> int:
    """Nesting depth of parsed JSON/YAML (iterative: never a RecursionError), stopping once past limit."""
    stack = [(doc, 1)]
    deepest = 0
    while stack:
        node, d = stack.pop()
        if isinstance(node, (list, tuple, dict)):
            deepest = max(deepest, d)
            if deepest > limit:
                return deepest
            stack.extend((v, d + 1) for v in (node.values() if isinstance(node, dict) else node))
    return deepest


def check_size(path: Path, limit: int, what: str) -> int:
    size = Path(path).stat().st_size
    if size > limit:
        raise LimitError(f"{path}: {what} is {size / 2**20:.1f} MiB, over the limit of {limit / 2**20:.0f} MiB; "
                         "give a smaller file (docs/real_inputs.md#limits)")
    return size


def _parse(text: str, where: str, max_nesting: int, kind: str, loads, syntax_errors) -> Any:
    """loads(text) refusing deep nesting in one line (the parser's RecursionError is caught, never shown)."""
    try:
        doc = loads(text)
    except RecursionError:
        raise LimitError(f"{where}: {kind} nested too deep (limit {max_nesting} levels); give a flat document") from None
    except syntax_errors as e:
        raise InputError(f"{where}: invalid {kind} ({' '.join(str(e).split())})") from None
    if _depth(doc, max_nesting) > max_nesting:
        raise LimitError(f"{where}: {kind} nested deeper than {max_nesting} levels; give a flat document")
    return doc


def parse_json(text: str, where: str, max_nesting: int = MAX_NESTING) -> Any:
    """json.loads within the nesting limit; InputError (one line) otherwise."""
    return _parse(text, where, max_nesting, "JSON", json.loads, json.JSONDecodeError)


def parse_yaml(text: str, where: str, max_nesting: int = MAX_NESTING) -> Any:
    """yaml.safe_load within the nesting limit; InputError (one line) otherwise."""
    import yaml

    return _parse(text, where, max_nesting, "YAML", yaml.safe_load, yaml.YAMLError)


def npy_header(path: Path | str, what: str = "array", max_elements: int = MAX_PIXELS * 4,
               kinds: str = "fiub") -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of an untrusted .npy from its header alone, checked against max_elements, the allowed dtype kinds
    and the file's real size; InputError (one line) otherwise. Reads a few hundred bytes."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
            if version not in read_header:
                raise ValueError(f"unsupported .npy version {version}")
            shape, fortran, dtype = read_header[version](f, max_header_size=10_000)
            offset = f.tell()
    except (OSError, ValueError, SyntaxError, TypeError) as e:
        raise InputError(f"{path}: cannot read the {what} ({' '.join(str(e).split())[:160]}); save it with numpy.save") from None
    if dtype.hasobject or dtype.kind not in kinds:
        raise InputError(f"{path}: {what} has dtype {dtype}; save a float32 array")
    count = math.prod(shape)
    if count > max_elements:
        raise LimitError(f"{path}: {what} header claims shape {shape} = {count:.3g} values, over the limit of "
                         f"{max_elements:.3g}; give an (H, W) array of at most 16384x8192")
    if path.stat().st_size < offset + count * dtype.itemsize:
        raise InputError(f"{path}: {what} is truncated: the header claims {shape} {dtype} but the file is "
                         f"{path.stat().st_size} bytes; save it again with numpy.save")
    return shape, dtype


def load_npy(path: Path | str, what: str = "array", max_elements: int = MAX_PIXELS * 4, kinds: str = "fiub") -> np.ndarray:
    """np.load of an untrusted .npy after npy_header's checks (nothing is allocated before them; no pickles)."""
    npy_header(path, what, max_elements, kinds)
    return np.array(np.load(path, mmap_mode="r", allow_pickle=False))


def check_poses_range(poses: np.ndarray, where: str) -> None:
    """At most MAX_POSES poses, translations within MAX_TRANSLATION_M (NaN/inf are checked by the caller)."""
    if len(poses) > MAX_POSES:
        raise LimitError(f"{where}: {len(poses)} poses, over the limit of {MAX_POSES}; give a shorter trajectory")
    with np.errstate(invalid="ignore", over="ignore"):
        far = np.abs(poses[:, :3, 3]).max(axis=1) > MAX_TRANSLATION_M
    if far.any():
        i = int(np.flatnonzero(far)[0])
        raise LimitError(f"{where}: pose {i} is {np.abs(poses[i, :3, 3]).max():.3g} m from the camera, beyond the "
                         f"{MAX_TRANSLATION_M:.0f} m limit for a scene; give poses in metres in the panorama's frame")


def depth_plane(depth: np.ndarray, path: Path | str) -> np.ndarray:
    """The (H, W) plane of a user depth array: (H, W), (H, W, C) or channel-first (C, H, W) with C <= 4 (first channel)."""
    if depth.ndim == 3:
        first, last = depth.shape[0] <= 4, depth.shape[2] <= 4
        if last and not first:
            return depth[..., 0]
        if first and not last:
            return depth[0]
    if depth.ndim != 2 or depth.size == 0:
        raise InputError(f"{path}: depth has shape {depth.shape} but expected (H, W) (or (H, W, C) / (C, H, W) with "
                         "C <= 4 channels, the first one used); save the depth plane alone")
    return depth
