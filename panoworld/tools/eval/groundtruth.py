"""Ground-truth references of `runner.py eval`: a synthetic mesh, ground-truth frames + poses, or none (plan only)."""

from __future__ import annotations

import json
from collections import OrderedDict
from functools import cached_property
from pathlib import Path

import numpy as np

from panoworld.core.conventions import invert_pose, transform_points
from panoworld.tools.eval.common import GT_DIRNAME


class NoReference(Exception):
    """The scene's ground truth cannot give what a metric needs (a mesh, a frame at some pose); the message says why."""


NO_MESH = "needs a ground-truth mesh; this scene has {what}"


class RenderCache:
    """Least-recently-used renders keyed by (pose bytes, size, ...), bounded by their total bytes."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._items: OrderedDict[tuple, tuple] = OrderedDict()
        self._bytes = 0

    def get(self, key: tuple, make):
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        value = make()
        size = sum(a.nbytes for a in value)
        if size <= self.max_bytes:
            self._items[key] = value
            self._bytes += size
            while self._bytes > self.max_bytes:
                self._bytes -= sum(a.nbytes for a in self._items.popitem(last=False)[1])
        return value


def aa_factor(height: int, supersample: int, max_rows: int) -> int:
    """Supersampling factor of an anti-aliased reference `height` rows tall: `supersample`, lowered so that the
    supersampled image has at most max_rows rows (never below 1)."""
    return max(1, min(int(supersample), int(max_rows) // max(int(height), 1)))


class GroundTruth:
    """The synthetic scene of SCENE/gt/ seen in the pipeline's canonical frame (camera 0 of track 0 = identity).

    Every pose argument is canonical world_from_cam. Renders are anti-aliased references: ray cast exactly at
    s x the asked size and area-downsampled in linear RGB (s = aa_factor(H, supersample, max_rows), at least the
    scene panorama's own supersampling); they are cached per pose and size (cache_mb bounds the cache).
    """

    kind = "synthetic"

    def __init__(self, gt_dir: Path, *, supersample: int = 4, max_rows: int = 1536, cache_mb: float = 512.0):
        self.dir = Path(gt_dir)
        self.index = json.loads((self.dir / "gt.json").read_text())
        self.world_from_canonical = np.asarray(self.index["world_from_canonical"], np.float64)
        self.pano_supersample = int((self.index.get("panorama") or {}).get("supersample", 1))
        self.aa_supersample, self.aa_max_rows = int(supersample), int(max_rows)
        self._renders = RenderCache(int(cache_mb * 2**20))

    def reframe(self, world_from_canonical: np.ndarray) -> None:
        """Take another canonical frame (world_from_canonical (4, 4) rigid, upright like the first): a home whose
        first registered panorama is not camera 0 of track 0. The floor height and the cached vertices and renders
        follow."""
        old_from_new = invert_pose(self.world_from_canonical) @ np.asarray(world_from_canonical, np.float64)
        floor = np.array([0.0, float(self.index["floor_y_canonical"]), 0.0])
        self.index = {**self.index, "floor_y_canonical": float(transform_points(invert_pose(old_from_new), floor[None])[0, 1])}
        self.world_from_canonical = np.asarray(world_from_canonical, np.float64)
        self.__dict__.pop("vertices", None)
        self._renders = RenderCache(self._renders.max_bytes)

    def factor(self, height: int) -> int:
        """The supersampling factor of the reference at this height."""
        return max(self.pano_supersample, aa_factor(height, self.aa_supersample, self.aa_max_rows))

    def describe(self, height: int) -> str:
        s = self.factor(height)
        return (f"exact ray cast at {s}x the rows and columns ({s * height} rows), area-downsampled in linear RGB"
                if s > 1 else "exact ray cast at the scored size, not anti-aliased (one ray per pixel)")

    @cached_property
    def scene(self):
        from panoworld.tools.synth import SynthScene

        return SynthScene.load(self.dir)

    @cached_property
    def vertices(self) -> np.ndarray:
        """(V, 3) float64 ground-truth vertices in the canonical frame (gt/scene.glb via world_from_canonical)."""
        return transform_points(invert_pose(self.world_from_canonical), self.scene.vertices.astype(np.float64))

    @property
    def faces(self) -> np.ndarray:
        return self.scene.faces

    def _world(self, pose: np.ndarray) -> np.ndarray:
        return self.world_from_canonical @ np.asarray(pose, np.float64)

    def render(self, pose: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """(rgb (H, W, 3) uint8, depth (H, W) float32 metres, inf = no surface) at a canonical pose (4, 4)."""
        key = ("erp", np.asarray(pose, np.float64).tobytes(), height, width)
        return self._renders.get(key, lambda: self.scene.render(self._world(pose), height, width,
                                                                 supersample=self.factor(height)))

    def render_pinhole(self, pose: np.ndarray, fx: float, fy: float, cx: float, cy: float, height: int,
                       width: int) -> tuple[np.ndarray, np.ndarray]:
        """A pinhole (OpenCV) view at a canonical pose: (rgb (H, W, 3) uint8, ray depth (H, W) float32), anti-aliased."""
        key = ("pinhole", np.asarray(pose, np.float64).tobytes(), fx, fy, cx, cy, height, width)
        return self._renders.get(key, lambda: self.scene.render_pinhole(
            self._world(pose), fx, fy, cx, cy, height, width, supersample=self.factor(height)))

    def depth(self, pose: np.ndarray, height: int, width: int) -> np.ndarray:
        """Exact ray distance (H, W) float32 at a canonical pose, without shading."""
        return self.scene.raycaster.render_erp(self._world(pose), height, width).distance

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance (N,) along canonical unit rays origins (N | 1, 3) + t dirs (N, 3) to the first surface (inf = none)."""
        R, t = self.world_from_canonical[:3, :3], self.world_from_canonical[:3, 3]
        return self.scene.raycaster.cast(np.asarray(origins, np.float64) @ R.T + t, np.asarray(dirs, np.float64) @ R.T).distance

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Exact distance (N,) from canonical points (N, 3) to the ground-truth surface."""
        from panoworld.trajectory import mesh_clearance

        return mesh_clearance(self.vertices, self.faces, points)


class FramesGroundTruth:
    """Ground-truth frames and poses without a mesh (InteriorGS-like scenes converted to the gt/ layout).

    gt/gt.json lists tracks, each with `poses` (a JSON {"world_from_cam": N x 4 x 4}) and `frames` patterns {"rgb",
    "depth" (optional)}; `world_from_canonical` defaults to pose 0 of track 0. render(pose) returns the track frame
    whose pose matches (centre within pose_tol_m, orientation within 0.1 degree), resized to the asked height.
    """

    kind = "frames"

    def __init__(self, gt_dir: Path, pose_tol_m: float = 1e-3):
        from panoworld.tools.dataset import DatasetScene

        self.dir = Path(gt_dir)
        self.dataset = DatasetScene(self.dir.parent)
        self.index = self.dataset.index
        first = self.dataset.poses(0)[0]
        self.world_from_canonical = np.asarray(self.index.get("world_from_canonical", first), np.float64)
        self.pose_tol_m = pose_tol_m
        self._cache: dict[tuple, tuple[np.ndarray, np.ndarray | None]] = {}

    @cached_property
    def tracks(self) -> list[np.ndarray]:
        """Canonical world_from_cam (N, 4, 4) of every track."""
        to_canonical = invert_pose(self.world_from_canonical)
        return [to_canonical[None] @ self.dataset.poses(t) for t in range(self.dataset.n_tracks)]

    def match(self, pose: np.ndarray) -> tuple[int, int]:
        """(track, frame) whose canonical pose equals `pose` within the tolerances, else NoReference."""
        from panoworld.geometry.align import rotation_angle_deg

        pose = np.asarray(pose, np.float64)
        best = (np.inf, -1, -1)
        for t, poses in enumerate(self.tracks):
            d = np.linalg.norm(poses[:, :3, 3] - pose[:3, 3], axis=1)
            i = int(np.argmin(d))
            if d[i] < best[0]:
                best = (float(d[i]), t, i)
        dist, t, i = best
        if t < 0 or dist > self.pose_tol_m or rotation_angle_deg(self.tracks[t][i][:3, :3].T @ pose[:3, :3]) > 0.1:
            raise NoReference(f"no ground-truth frame at the pose with centre {np.round(pose[:3, 3], 4).tolist()} "
                              f"(nearest track frame {dist:.4f} m away; tolerance {self.pose_tol_m} m, 0.1 deg): "
                              "this scene has frames + poses only, so only poses on its tracks can be scored")
        return t, i

    def _frame(self, pose: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray | None]:
        import cv2

        t, i = self.match(pose)
        key = (t, i, height)
        if key not in self._cache:
            frames = self.index["tracks"][t].get("frames") or {}
            rgb_path = self.dir / frames["rgb"].format(i)
            bgr = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"{rgb_path}: missing or unreadable ground-truth frame")
            rgb = np.ascontiguousarray(bgr[..., ::-1])
            if rgb.shape[0] != height:
                rgb = cv2.resize(rgb, (2 * height, height), interpolation=cv2.INTER_AREA)
            depth = None
            if frames.get("depth"):
                depth = np.load(self.dir / frames["depth"].format(i)).astype(np.float32)
                if depth.shape[0] != height:
                    depth = cv2.resize(depth, (2 * height, height), interpolation=cv2.INTER_NEAREST)
            self._cache[key] = (rgb, depth)
        return self._cache[key]

    def render(self, pose: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        rgb, depth = self._frame(pose, height)
        return rgb, depth if depth is not None else np.full((height, width), np.inf, np.float32)

    def depth(self, pose: np.ndarray, height: int, width: int) -> np.ndarray:
        depth = self._frame(pose, height)[1]
        if depth is None:
            raise NoReference("the ground-truth track lists no depth frames")
        return depth

    def _no_mesh(self, *_, **__):
        raise NoReference(NO_MESH.format(what="ground-truth frames + poses only"))

    cast = clearance = render_pinhole = _no_mesh

    def describe(self, height: int) -> str:
        return "the ground-truth track frame at the pose, area-downsampled to the scored size"

    @property
    def vertices(self):
        self._no_mesh()


class PlanOnly:
    """No ground truth at all (RealSee3D-like scenes): poses are scored against the plan, loops by their ends."""

    kind = "plan-only"
    world_from_canonical = np.eye(4)
    index: dict = {}

    def _none(self, *_, **__):
        raise NoReference("no ground truth in this scene (plan-only: no gt/ frames or mesh); pose metrics use the "
                          "planned trajectory and ring paths get loop metrics")

    render = depth = cast = clearance = render_pinhole = _none

    def describe(self, height: int) -> str:
        return "none (no ground truth)"

    @property
    def vertices(self):
        self._none()


def open_ground_truth(scene_dir: Path, pose_tol_m: float = 1e-3, *, supersample: int = 4, max_rows: int = 1536,
                      cache_mb: float = 512.0):
    """The scene's reference: GroundTruth (synthetic gt/ with a mesh; supersample, max_rows, cache_mb: its
    anti-aliased renders), FramesGroundTruth (gt/ tracks with frame files, no mesh) or PlanOnly (no gt/gt.json)."""
    gt_dir = Path(scene_dir) / GT_DIRNAME
    index_path = gt_dir / "gt.json"
    if not index_path.is_file():
        return PlanOnly()
    index = json.loads(index_path.read_text())
    mesh = gt_dir / index.get("glb", "scene.glb")
    if str(index.get("format", "")).startswith("panoworld-synth") and mesh.is_file():
        return GroundTruth(gt_dir, supersample=supersample, max_rows=max_rows, cache_mb=cache_mb)
    tracks = index.get("tracks") or []
    if tracks and all((t.get("frames") or {}).get("rgb") for t in tracks):
        return FramesGroundTruth(gt_dir, pose_tol_m)
    return PlanOnly()
