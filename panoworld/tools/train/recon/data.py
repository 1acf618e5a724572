"""Training batches from scenes with ground-truth frames, depth and poses: one scene, 2-32 frames of one track."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.tools.dataset import DatasetError, DatasetScene


@dataclass
class Batch:
    """Frames of one track of one scene, poses relative to the first frame (its camera = the canonical world)."""

    scene: str
    track: int
    frames: list[int]
    """Track frame numbers, ascending."""
    rgb: np.ndarray
    """(S, H, W, 3) uint8."""
    depth: np.ndarray
    """(S, H, W) float32 ray distance in metres (0 = invalid)."""
    world_from_cam: np.ndarray
    """(S, 4, 4) float64, frame 0 = identity."""


def list_scenes(data_dir: Path) -> list[Path]:
    """Scene directories (holding gt/gt.json) of a dataset directory, sorted by name; the directory itself if it is one."""
    data_dir = Path(data_dir)
    if (data_dir / "gt" / "gt.json").is_file():
        return [data_dir]
    scenes = sorted(p for p in data_dir.iterdir() if (p / "gt" / "gt.json").is_file()) if data_dir.is_dir() else []
    if not scenes:
        raise DatasetError(f"{data_dir}: no scene directory with gt/gt.json; make one with "
                           f"`python runner.py synth {data_dir} --seed 0 --scenes 20 --preset ci-tiny`")
    return scenes


def split_scenes(scenes: list[Path], val_scenes: int) -> tuple[list[Path], list[Path]]:
    """(train, validation): the last `val_scenes` scenes by name validate and never train."""
    if len(scenes) <= val_scenes:
        raise DatasetError(f"{len(scenes)} scene(s) but val_scenes={val_scenes} must leave at least one to train on; "
                           "add scenes or lower val_scenes")
    return (scenes[:-val_scenes], scenes[-val_scenes:]) if val_scenes > 0 else (scenes, [])


class SceneFrames:
    """Scenes with an in-memory cache of frames at one ERP height (synthetic frames are rendered once)."""

    def __init__(self, scenes: list[Path], height: int):
        self.scenes = [DatasetScene(p) for p in scenes]
        self.height = height
        self._poses: dict[tuple[int, int], np.ndarray] = {}
        self._cache: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.scenes)

    def poses(self, s: int, track: int) -> np.ndarray:
        if (s, track) not in self._poses:
            self._poses[(s, track)] = self.scenes[s].poses(track)
        return self._poses[(s, track)]

    def frame(self, s: int, track: int, i: int) -> tuple[np.ndarray, np.ndarray]:
        key = (s, track, i)
        if key not in self._cache:
            rgb, depth = self.scenes[s].frame(track, i, self.height)
            depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
            self._cache[key] = (rgb, depth)
        return self._cache[key]

    def sample(self, rng: np.random.Generator, min_frames: int, max_frames: int, scene: int | None = None,
               yaw_augment: str = "none") -> Batch:
        """One scene (uniform, or `scene`), one track, S ~ U{min_frames..max_frames} distinct frames (capped at the
        track length), sorted; poses made relative to the first of them. yaw_augment ("none", "shared", "per-frame",
        config.YawAugment) turns the cameras about their vertical axes by random whole numbers of pixel columns, one
        turn for the whole batch or one per frame (exact for ERP: roll_yaw)."""
        s = int(rng.integers(len(self.scenes))) if scene is None else scene
        sc = self.scenes[s]
        track = int(rng.integers(sc.n_tracks))
        n = sc.n_frames(track)
        k = int(min(n, rng.integers(min_frames, max_frames + 1)))
        idx = np.sort(rng.choice(n, size=k, replace=False))
        poses = self.poses(s, track)[idx]
        rgb, depth = map(np.stack, zip(*(self.frame(s, track, int(i)) for i in idx)))
        if yaw_augment not in ("none", "shared", "per-frame"):
            raise ValueError(f"{yaw_augment=} but expected none, shared or per-frame")
        if yaw_augment != "none":
            shifts = rng.integers(0, rgb.shape[2], size=1 if yaw_augment == "shared" else len(idx))
            shifts = np.broadcast_to(shifts, len(idx))
            rgb, depth, poses = map(np.stack, zip(*(roll_yaw(*f, int(k)) for *f, k in zip(rgb, depth, poses, shifts))))
        rel = np.linalg.inv(poses[0]) @ poses
        rel[0] = np.eye(4)
        return Batch(sc.name, track, idx.tolist(), rgb, depth, rel)


def roll_yaw(rgb: np.ndarray, depth: np.ndarray, world_from_cam: np.ndarray, k: int):
    """The same panorama from a camera turned about its y axis: columns rolled by k (W = image width) <=> the camera
    rotated by R_y(-2 pi k / W) (a pixel's longitude grows by 2 pi k / W, conventions.md's ERP mapping)."""
    a = -2.0 * np.pi * k / rgb.shape[1]
    R = np.array([[np.cos(a), 0.0, np.sin(a), 0.0], [0.0, 1.0, 0.0, 0.0], [-np.sin(a), 0.0, np.cos(a), 0.0],
                  [0.0, 0.0, 0.0, 1.0]])
    return np.roll(rgb, k, axis=1), np.roll(depth, k, axis=1), world_from_cam @ R
