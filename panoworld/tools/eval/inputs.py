"""SceneInputs: what one scene's evaluation reads: its stage artifacts (read lazily) and its reference."""

from __future__ import annotations

import json
import sys
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from panoworld.core.errors import PanoWorldError
from panoworld.core.params import flatten
from panoworld.io.manifest import ARTIFACTS_DIRNAME, MANIFEST, VARIANTS_DIRNAME
from panoworld.tools.eval.common import EvalParams, Lpips
from panoworld.tools.eval.groundtruth import NoReference, open_ground_truth


class SceneInputs:
    """One scene's stage artifacts (the evaluated variant's tail where it has one) and its reference (self.gt)."""

    def __init__(self, scene_dir: Path, params: EvalParams | None = None, *, progress: bool = True,
                 variant: str | None = None, roam_images: Path | None = None):
        self.scene_dir = Path(scene_dir)
        self.roam_images = roam_images
        """Where the roam protocol saves the first view of every bucket (PNGs for the report), or None."""
        self.params = params or EvalParams()
        self.progress = progress
        self.gt = open_ground_truth(self.scene_dir, self.params.pose_tol_m, supersample=self.params.reference_supersample,
                                    max_rows=self.params.reference_max_rows, cache_mb=self.params.reference_cache_mb)
        self.lpips = Lpips(self.params)
        self.variant = variant
        self.tail: set[str] = set()
        if variant:
            from panoworld.tools.batch.variants import read_variant

            self.tail = set(read_variant(self.scene_dir, variant)["tail"])
        self.pose0 = self._home_frame()
        """Canonical world_from_cam of the depth artifact's top-level panorama (a home's first by name)."""

    def _home_frame(self) -> np.ndarray:
        """A home's world frame is its first registered panorama's camera; the ground truth's canonical frame that
        of its first panorama. Where they differ (that panorama left unregistered) the reference takes the home's
        frame, through the anchor's true pose (gt/poses.json) -> the top-level panorama's pose in it (else identity)."""
        from panoworld.core.conventions import invert_pose
        from panoworld.tools.eval.home import registered_and_true

        reg = self.artifact("register")
        if not hasattr(self.gt, "reframe") or reg is None:
            return np.eye(4)
        try:
            truth, est, anchor = registered_and_true(reg, self.scene_dir)
        except (NoReference, PanoWorldError, OSError, ValueError, TypeError, AttributeError):  # the register row says why
            return np.eye(4)
        world_from_home = truth[anchor] @ invert_pose(est[anchor])
        if not np.allclose(world_from_home, self.gt.world_from_canonical, atol=1e-6):
            self.gt.reframe(world_from_home)
        return invert_pose(world_from_home) @ truth[sorted(truth)[0]]

    # -- helpers

    def artifact(self, stage: str) -> Path | None:
        """The artifact directory of a stage that has run (its manifest.json is written last), else None."""
        d = self.artifact_dir(stage)
        return d if (d / MANIFEST).is_file() else None

    def artifact_dir(self, stage: str) -> Path:
        """artifacts/STAGE, or artifacts/variants/NAME/STAGE for a stage in the evaluated variant's tail."""

        root = self.scene_dir / ARTIFACTS_DIRNAME
        return (root / VARIANTS_DIRNAME / self.variant if stage in self.tail else root) / stage

    def manifest(self, stage: str) -> dict:
        return json.loads((self.artifact_dir(stage) / MANIFEST).read_text())

    def _need(self, stage: str) -> Path:
        d = self.artifact(stage)
        if d is None:
            raise NotRun(stage)
        return d

    @cached_property
    def trajectory_poses(self) -> np.ndarray:
        from panoworld.io.trajectory import load_trajectory

        return load_trajectory(self._need("trajectory"))

    @cached_property
    def video(self):
        """The video artifact's description (frame and depth paths, poses); frames are read when evaluated."""
        from panoworld.io.video import read_video_frames

        return read_video_frames(self._need("video"))

    @cached_property
    def conditions(self):
        from panoworld.io.conditions import load_conditions

        return load_conditions(self._need("conditions"))

    def reference_poses(self) -> tuple[np.ndarray, str]:
        """The poses the video was generated along (the ground truth for recovered poses): video.json, else the trajectory."""
        if self.artifact("video") is not None and self.video.poses is not None:
            return self.video.poses, "video.json poses"
        return self.trajectory_poses, "trajectory.json poses"

    def _frames(self, n: int) -> list[int]:
        from panoworld.gaussians.fusion import uniform_subset

        return uniform_subset(range(1, n), self.params.max_frames)

    def _bar(self, items, desc: str):
        return tqdm(items, desc=desc, leave=False, disable=not self.progress, file=sys.stderr)

    @cached_property
    def preset(self) -> str | None:
        """The preset remembered in SCENE/scene.yaml (None when absent)."""
        import yaml

        from panoworld.io.manifest import SCENE_CONFIG

        cfg = self.scene_dir / SCENE_CONFIG
        try:
            return (yaml.safe_load(cfg.read_text()) or {}).get("preset") if cfg.is_file() else None
        except (OSError, yaml.YAMLError, AttributeError):
            return None

    def setting(self) -> dict[str, Any]:
        """What the evaluated artifacts were made with: trajectory kind/stride/frames and the video backend (the
        columns that group a dataset's results into the paper's rows); empty entries for stages not run."""
        out: dict[str, Any] = {}
        for stage, keys in (("trajectory", ("kind", "stride", "frames")), ("video", ("backend", "wan.steps")),
                            ("poses", ("backend",))):
            if self.artifact(stage) is not None:
                params = flatten(self.manifest(stage).get("params") or {})
                out.update({(f"{stage}_{k}" if k == "backend" else k.rpartition(".")[2]): params.get(k) for k in keys})
        return out


class NotRun(Exception):
    def __init__(self, stage: str):
        super().__init__(stage)
        self.stage = stage
