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
APPLEDOUBLE = "._"
"""The prefix of the metadata files macOS writes beside each file on disks without its attributes (`._pano.jpg`, never
an image): a home's folders and a stage's input folders leave them out (is_appledouble)."""


def is_appledouble(path: Path) -> bool:
    """Whether path is a macOS AppleDouble metadata file (APPLEDOUBLE), not the image or array its suffix names."""
    return path.name.startswith(APPLEDOUBLE)

MAX_POSES = 10_000
"""Most poses in a user trajectory (the paper's clips are 81; 10 000 frames render for days on a GPU)."""
MAX_TRANSLATION_M = 1000.0
"""Largest |translation| of a user pose in metres (indoor scenes are tens of metres; the NavMesh check refines it)."""
MAX_TRAJECTORY_BYTES = 16 * 2**20
"""Largest user trajectory file (10 000 poses as JSON at full precision take about 4 MB)."""
MAX_FLOOR_CELLS = 40_000_000
"""Most cells of a NavMesh floor grid (about 190 m x 190 m at 3 cm; a few bytes a cell in each of its layers): a floor
spread wider is refused before the grid is allocated (capture points hundreds of metres apart are not one home)."""
MAX_CONFIG_BYTES = 2**20
"""Largest scene.yaml."""
MAX_NESTING = 32
"""Deepest nesting of lists/objects in a user JSON or YAML file (a trajectory needs 3)."""
MAX_NODES = 1_000_000
"""Most values in a user JSON or YAML document once YAML aliases are expanded (an alias bomb of 1 KB expands to
billions; a 10 000-pose trajectory has 170 000)."""
MAX_POSES_JSON_BYTES = 4 * 2**20
"""Largest poses.json of a home (1000 capture points at full precision take about 400 KB)."""
MIN_HEIGHT = 8
"""Fewest rows of a panorama, depth map or rig mask (16x8): below that no stage has pixels to work with."""


class LimitError(InputError):
    """A user input beyond a documented limit (size, count, nesting, value range)."""


def _depth(doc: Any, limit: int, max_nodes: int = MAX_NODES) -> tuple[int, int]:
    """(nesting depth, number of values) of parsed JSON/YAML with shared nodes (YAML aliases) counted once per use,
    each node walked once (memoised: an alias chain costs its size in nodes, not its expansion); stops early, with
    values > max_nodes or depth > limit, once past a limit. A node that contains itself counts as too deep."""
    memo: dict[int, tuple[int, int]] = {}
    busy: set[int] = set()
    stack: list[tuple[Any, bool]] = [(doc, False)]
    while stack:
        node, done = stack.pop()
        if not isinstance(node, (list, tuple, dict)):
            continue
        key = id(node)
        kids = list(node.values() if isinstance(node, dict) else node)
        if done:
            busy.discard(key)
            sub = [memo.get(id(k), (0, 1)) for k in kids]
            d = 1 + max((x[0] for x in sub), default=0)
            n = 1 + sum(x[1] for x in sub)
            memo[key] = (d, n)
            if d > limit or n > max_nodes:
                return d, n
            continue
        if key in memo:
            continue
        if key in busy:  # a recursive alias (&a [*a])
            return limit + 1, 0
        busy.add(key)
        stack.append((node, True))
        stack.extend((k, False) for k in kids if isinstance(k, (list, tuple, dict)) and id(k) not in memo)
    return memo.get(id(doc), (0, 1))


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
    depth, nodes = _depth(doc, max_nesting)
    if depth > max_nesting:
        raise LimitError(f"{where}: {kind} nested deeper than {max_nesting} levels (or recursive); give a flat document")
    if nodes > MAX_NODES:
        raise LimitError(f"{where}: {kind} holds over {MAX_NODES} values once its aliases are expanded (an alias bomb?); "
                         "give a plain document (docs/real_inputs.md#limits)")
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


def exr_header(path: Path | str, what: str = "EXR depth") -> tuple[int, int]:
    """(width, height) of an untrusted OpenEXR file from its header's dataWindow (reads at most 64 KB), checked
    against MAX_PIXELS and MIN_HEIGHT; InputError (one line) otherwise."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError as e:
        raise InputError(f"{path}: cannot read the {what} ({e.strerror})") from None
    if head[:4] != b"\x76\x2f\x31\x01":
        raise InputError(f"{path}: cannot read the {what} (not an OpenEXR file); save the depth as EXR or .npy")
    pos, window = 8, None
    while pos < len(head) and head[pos] != 0:
        name_end = head.find(b"\0", pos)
        type_end = head.find(b"\0", name_end + 1)
        if name_end < 0 or type_end < 0 or type_end + 4 > len(head):
            break
        size = int.from_bytes(head[type_end + 1:type_end + 5], "little")
        value = head[type_end + 5:type_end + 5 + size]
        if head[pos:name_end] == b"dataWindow" and len(value) == 16:
            window = [int.from_bytes(value[i:i + 4], "little", signed=True) for i in range(0, 16, 4)]
            break
        pos = type_end + 5 + size
    if window is None:
        raise InputError(f"{path}: cannot read the {what} (its header has no dataWindow: corrupt or truncated); save it "
                         "again")
    w, h = window[2] - window[0] + 1, window[3] - window[1] + 1
    check_image_size(path, w, h, what)
    return w, h


def check_image_size(path: Path | str, w: int, h: int, what: str) -> None:
    """w x h within MAX_PIXELS and at least MIN_HEIGHT rows; LimitError naming the file and the limit otherwise."""
    if w <= 0 or h <= 0 or w * h > MAX_PIXELS:
        raise LimitError(f"{path}: {what} is {w}x{h} = {max(w, 0) * max(h, 0) / 1e6:.0f} Mpx, beyond the limit of "
                         f"{MAX_PIXELS / 1e6:.0f} Mpx (16384x8192); give a smaller one (docs/real_inputs.md#limits)")
    if h < MIN_HEIGHT or w < MIN_HEIGHT:
        raise LimitError(f"{path}: {what} is {w}x{h}, below the minimum of {2 * MIN_HEIGHT}x{MIN_HEIGHT}; give a "
                         "larger one (docs/real_inputs.md#limits)")
