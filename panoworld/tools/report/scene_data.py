"""What the scene report reads: its params and each stage artifact through that kind's one reader (None when missing)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.asset import read_asset_doc
from panoworld.core.errors import PanoWorldError
from panoworld.geometry.navmesh import load_navmesh
from panoworld.io.conditions import load_conditions
from panoworld.io.home import capture_poses, home_depth_dirs
from panoworld.io.manifest import read_manifest
from panoworld.io.trajectory import load_clips, load_trajectory, read_trajectory_doc
from panoworld.io.video import read_video_doc
from panoworld.poses.estimate import load_poses
from panoworld.register.artifact import read_registration

ARTIFACTS = "artifacts"
ROAM_IMAGES = "report/roam"
"""Where `report --eval` has the roam protocol save its first view per bucket (under artifacts/)."""
EVAL_JSON_CANDIDATES = ("artifacts/report/eval.json", "artifacts/eval.json", "eval.json")


@dataclass(kw_only=True)
class ReportParams:
    """What the scene report embeds and how much it may cost."""

    max_frames: int = 24
    """Frames shown on the frame slider (uniformly subsampled, first and last kept)."""
    image_width: int = 512
    """Width in pixels of every embedded frame (panorama and depth: 2x this)."""
    gs_views: int = 3
    """Gaussian renders (a context pose and novel poses between frames); 0 = only the stage's preview.png."""
    gs_height: int = 192
    """Size in pixels of those renders (square forward views, 90 degree field of view)."""
    gs_budget_s: float = 5.0
    """Stop rendering Gaussians once this many seconds are spent (the page says how many were rendered)."""
    eval_json: Path | None = None
    """A saved `runner.py eval --out FILE` report; default: the first of artifacts/report/eval.json,
    artifacts/eval.json, eval.json in the scene."""
    preset: str | None = None
    """Preset for the stage states (up to date / stale); default: the preset under which most stages are up to date."""


class SceneData:
    """Reads a scene's artifacts through each kind's one reader, defensively: a missing or unreadable artifact gives
    None, never an exception."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.art = self.root / ARTIFACTS
        self._read: dict[str, object] = {}

    def _load(self, stage: str, reader, key: str = ""):
        key = key or stage
        if key not in self._read:
            try:
                self._read[key] = reader(self.dir(stage)) if self.has(stage) else None
            except (PanoWorldError, OSError, ValueError, KeyError, TypeError):
                self._read[key] = None
        return self._read[key]

    def navmesh(self):
        """NavMesh or None."""
        return self._load("navmesh", load_navmesh)

    def trajectory(self) -> np.ndarray | None:
        """Planned world_from_cam (N, 4, 4) or None."""
        return self._load("trajectory", load_trajectory)

    def clips(self) -> list[list[int]] | None:
        """Pose indices of each path of the planned trajectory (io.trajectory.load_clips) or None."""
        traj = self.trajectory()
        return None if traj is None else self._load("trajectory", lambda d: load_clips(d, len(traj)), "clips")

    def conditions(self):
        """LoadedConditions (frames read lazily) or None."""
        return self._load("conditions", load_conditions)

    def video(self):
        """VideoDoc or None."""
        return self._load("video", read_video_doc)

    def poses_artifact(self):
        """PosesArtifact or None."""
        return self._load("poses", load_poses)

    def capture_points(self) -> dict[str, np.ndarray]:
        """{NAME: world_from_cam} of the register artifact (a home's capture points; one for a single panorama)."""
        return self._load("register", capture_poses) or {}

    def registration(self) -> dict | None:
        """registration.json of the register artifact (per-panorama status and every pair tried) or None."""
        doc = self._load("register", lambda d: read_registration(d)[1], "registration")
        return doc if isinstance(doc, dict) else None

    def home_depth_dirs(self) -> dict[str, Path] | None:
        """{NAME: folder of its cleaned panorama.png, depth.npy, valid.png} of a home's depth artifact, else None."""
        return self._load("depth", home_depth_dirs, "home_depth_dirs")

    def dir(self, stage: str) -> Path:
        return self.art / stage

    def has(self, stage: str) -> bool:
        return (self.dir(stage) / "manifest.json").is_file()

    def trajectory_doc(self) -> dict | None:
        """trajectory.json's document (poses and metadata: paths, fps, floor_y, ...) or None."""
        return self._load("trajectory", read_trajectory_doc, "trajectory_doc")

    def asset_doc(self) -> dict | None:
        """asset.json of the asset artifact or None."""
        return self._load("asset", read_asset_doc, "asset_doc")

    def manifest(self, stage: str) -> dict | None:
        return self._load(stage, read_manifest, "manifest:" + stage)

    def info(self, stage: str) -> dict:
        m = self.manifest(stage)
        return (m or {}).get("info") or {}

    def video_poses(self) -> np.ndarray | None:
        """The poses the video was generated along, when video.json records them."""
        v = self.video()
        return None if v is None else v.poses


def subsample(n: int, k: int) -> list[int]:
    """k indices of range(n) spread uniformly, first and last included."""
    if n <= k:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})


def find_eval_json(scene: SceneData, given: Path | None) -> Path | None:
    """The eval JSON the report shows: `given` where it exists, else the first of EVAL_JSON_CANDIDATES in the scene."""
    if given is not None:
        return Path(given) if Path(given).is_file() else None
    return next((scene.root / c for c in EVAL_JSON_CANDIDATES if (scene.root / c).is_file()), None)
