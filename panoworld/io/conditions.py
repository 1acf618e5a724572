"""The conditions artifact: the frame a pose renders from the scene mesh (RGB, depth, mask) and its reader
(conditions.json and per-frame PNGs, read lazily); written by panoworld.conditions.warp."""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.core.conventions import DEPTH_PNG_SCALE, check_poses
from panoworld.io.depth_png import metres_from_png

CONDITIONS_JSON = "conditions.json"
DEPTH_SCALE = DEPTH_PNG_SCALE
"""Metres per unit of the uint16 depth PNGs (millimetres; 0 = nothing, saturates at 65.535 m)."""


@dataclass
class WarpedFrame:
    """One pose rendered from the mesh: what the generator is conditioned on."""

    rgb: np.ndarray
    """(H, W, 3) uint8 interpolated vertex colour; 0 where mask is False."""
    depth: np.ndarray
    """(H, W) float32 ray distance in metres; 0 where mask is False."""
    mask: np.ndarray
    """(H, W) bool: True = the pixel sees a valid face; False = no geometry or a stretched face (to be generated)."""


class FrameStack:
    """Lazy (N, ...) stack of per-frame PNGs: index it for one frame, slice it or np.asarray it for many."""

    def __init__(self, root: Path, paths: list[str], shape: tuple[int, ...], dtype, decode):
        self.root = root
        self.paths = paths
        self.shape = (len(paths), *shape)
        self.dtype = np.dtype(dtype)
        self._decode = decode

    def __len__(self) -> int:
        return len(self.paths)

    def _read(self, k: int) -> np.ndarray:
        import cv2

        path = self.root / self.paths[k]
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{path}: missing or not a readable PNG; rerun the conditions stage")
        out = self._decode(img)
        if out.shape != self.shape[1:]:
            raise ValueError(f"{path}: {out.shape=} but expected {self.shape[1:]} from conditions.json")
        return out

    def __getitem__(self, idx):
        if isinstance(idx, (int, np.integer)):
            k = int(idx)
            if not -len(self) <= k < len(self):
                raise IndexError(f"frame {k} out of range for {len(self)} frames")
            return self._read(k % len(self))
        ks = range(len(self))[idx] if isinstance(idx, slice) else np.arange(len(self))[idx]
        out = np.empty((len(ks), *self.shape[1:]), self.dtype)
        for i, k in enumerate(ks):
            out[i] = self._read(int(k))
        return out

    def __iter__(self):
        return (self._read(k) for k in range(len(self)))

    def __array__(self, dtype=None, copy=None):
        arr = self[:]
        return arr if dtype is None else arr.astype(dtype)


def _decode_rgb(img: np.ndarray) -> np.ndarray:
    import cv2

    if img.ndim != 3 or img.dtype != np.uint8 or img.shape[2] != 3:
        return np.empty((0,))
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _decode_mask(img: np.ndarray) -> np.ndarray:
    return img > 127 if img.dtype == np.uint8 and img.ndim == 2 else np.empty((0,))


def _decode_depth(img: np.ndarray) -> np.ndarray:
    if img.dtype != np.uint16 or img.ndim != 2:
        return np.empty((0,))
    return metres_from_png(img, DEPTH_SCALE)


@dataclass
class LoadedConditions:
    """A conditions directory: lazy frame stacks plus the poses they were rendered at."""

    root: Path
    height: int
    width: int
    poses: np.ndarray
    """(N, 4, 4) world_from_cam in the mesh's canonical frame."""
    rgb: FrameStack
    """(N, H, W, 3) uint8."""
    mask: FrameStack
    """(N, H, W) bool, True = valid warped geometry."""
    depth: FrameStack | None
    """(N, H, W) float32 metres (0 = nothing), or None when the stage ran with write_depth off."""

    def __len__(self) -> int:
        return len(self.poses)

    def frame(self, k: int) -> WarpedFrame:
        depth = self.depth[k] if self.depth is not None else np.zeros((self.height, self.width), np.float32)
        return WarpedFrame(self.rgb[k], depth, self.mask[k])

    def iter_frames(self, *, ahead: int = 2) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
        """(rgb, mask, depth or None) of every frame in order, read `ahead` frames ahead by a background thread that
        starts at once (before the first frame is asked for): PNG decoding (OpenCV releases the GIL) overlaps the
        caller's work."""

        def read(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
            return self.rgb[k], self.mask[k], None if self.depth is None else self.depth[k]

        n = len(self)
        pool = ThreadPoolExecutor(max_workers=1)
        pending = deque(pool.submit(read, k) for k in range(min(ahead, n)))

        def frames() -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
            try:
                for k in range(n):
                    if k + ahead < n:
                        pending.append(pool.submit(read, k + ahead))
                    yield pending.popleft().result()
            finally:
                pool.shutdown(cancel_futures=True)

        return frames()


def load_conditions(path: Path | str) -> LoadedConditions:
    """Open a conditions directory (or its conditions.json); frames are read lazily when indexed."""
    path = Path(path)
    root = path.parent if path.is_file() else path
    doc_path = root / CONDITIONS_JSON
    try:
        doc = json.loads(doc_path.read_text())
        height, width, n = int(doc["height"]), int(doc["width"]), int(doc["num_frames"])
        entries = doc["frames"]
        poses = check_poses(np.asarray(doc["poses"], np.float64), f"{doc_path} poses")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{doc_path}: not a readable conditions index ({e}); rerun the conditions stage") from None
    if len(entries) != n or len(poses) != n:
        raise ValueError(f"{doc_path}: num_frames={n} but {len(entries)} frames and {len(poses)} poses listed")
    if float(doc.get("depth_scale", DEPTH_SCALE)) != DEPTH_SCALE:
        raise ValueError(f"{doc_path}: depth_scale {doc['depth_scale']} but this reader expects {DEPTH_SCALE}")
    has_depth = n > 0 and all("depth" in e for e in entries)
    return LoadedConditions(
        root=root,
        height=height,
        width=width,
        poses=poses,
        rgb=FrameStack(root, [e["rgb"] for e in entries], (height, width, 3), np.uint8, _decode_rgb),
        mask=FrameStack(root, [e["mask"] for e in entries], (height, width), bool, _decode_mask),
        depth=FrameStack(root, [e["depth"] for e in entries], (height, width), np.float32, _decode_depth)
        if has_depth else None,
    )
