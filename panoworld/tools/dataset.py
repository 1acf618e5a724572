"""Reading dataset scenes in the ground-truth layout (gt/gt.json with tracks and per-frame RGB + depth)."""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path

import numpy as np

from panoworld.core.errors import DataError, InputError
from panoworld.io.images import read_image


class DatasetError(DataError):
    """A dataset scene is missing files or has an unreadable gt.json."""


class DatasetScene:
    """One scene directory: `gt/gt.json` lists tracks (poses JSON) and, optionally, rendered frames per track.

    Frames come from the files named by each track's `frames` patterns (RGB PNG, float32 depth .npy); when a
    track has none and the scene is a synthetic one, they are rendered exactly on demand.
    """

    def __init__(self, root: Path):
        self.root = Path(root)
        self.gt_dir = self.root / "gt"
        path = self.gt_dir / "gt.json"
        try:
            self.index = json.loads(path.read_text())
        except FileNotFoundError:
            raise DatasetError(f"{path}: missing; a dataset scene needs gt/gt.json (see docs/precompute.md)") from None
        except (OSError, json.JSONDecodeError) as e:
            raise DatasetError(f"{path}: unreadable ({e})") from None
        if not self.index.get("tracks"):
            raise DatasetError(f"{path}: lists no tracks")
        self.name = self.root.name

    @classmethod
    def from_gt_index(cls, gt_json: Path) -> DatasetScene:
        return cls(Path(gt_json).resolve().parent.parent)

    @property
    def n_tracks(self) -> int:
        return len(self.index["tracks"])

    def n_frames(self, track: int) -> int:
        return int(self.index["tracks"][track]["n_frames"])

    def poses(self, track: int) -> np.ndarray:
        """world_from_cam (N, 4, 4) of one track."""
        entry = self.index["tracks"][track]
        path = self.gt_dir / entry["poses"]
        try:
            doc = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise DatasetError(f"{path}: unreadable track ({e})") from None
        poses = np.asarray(doc["world_from_cam"] if isinstance(doc, dict) else doc, np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise DatasetError(f"{path}: poses have shape {poses.shape} but expected (N, 4, 4)")
        return poses

    def frame_files(self, track: int, i: int) -> tuple[Path, Path] | None:
        frames = self.index["tracks"][track].get("frames")
        if not frames:
            return None
        return self.gt_dir / frames["rgb"].format(i), self.gt_dir / frames["depth"].format(i)

    @cached_property
    def _synth(self):
        from panoworld.tools.synth import SynthScene

        return SynthScene.load(self.gt_dir)

    def frame(self, track: int, i: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """RGB (H, W, 3) uint8 and ray-distance depth (H, W) float32 of track frame i at ERP height `height`."""
        import cv2

        files = self.frame_files(track, i)
        if files is None:
            if self.index.get("format", "").startswith("panoworld-synth"):
                return self._synth.render(self.poses(track)[i], height, 2 * height)
            raise DatasetError(f"{self.gt_dir / 'gt.json'}: track {track} lists no frame files and the scene is not synthetic")
        rgb_path, depth_path = files
        try:
            bgr = read_image(rgb_path, cv2.IMREAD_COLOR, what="frame")
        except InputError as e:
            raise DatasetError(str(e)) from None
        try:
            depth = np.load(depth_path).astype(np.float32)
        except (OSError, ValueError) as e:
            raise DatasetError(f"{depth_path}: missing or unreadable depth ({e})") from None
        rgb = bgr[..., ::-1]
        if rgb.shape[0] != height:
            rgb = cv2.resize(rgb, (2 * height, height), interpolation=cv2.INTER_AREA)
        if depth.shape[0] != height:
            depth = cv2.resize(depth, (2 * height, height), interpolation=cv2.INTER_NEAREST)
        return np.ascontiguousarray(rgb), depth
