"""The video artifact's video.json (the one parser every reader goes through) and its readers: PNG or JPEG frames,
uint16 depth and poses, loaded into memory or as the paths of the files."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from panoworld.core.conventions import DEPTH_PNG_SCALE
from panoworld.core.errors import InputError
from panoworld.core.shapes import check_shape
from panoworld.io.depth_png import read_depth_png
from panoworld.io.jsonio import read_json
from panoworld.io.rgb_image import decode_rgb

VIDEO_FILE = "video.json"
DEPTH_SCALE = DEPTH_PNG_SCALE  # metres per depth PNG unit (millimetres); 0 = unknown


@dataclass
class VideoDoc:
    """What video.json says (paths resolved against the artifact directory; nothing decoded)."""

    root: Path
    height: int
    width: int
    rgb: list[Path]
    depth: list[Path | None]
    """Per frame the depth PNG, or None (a video without depth)."""
    depth_scale: float
    poses: np.ndarray | None
    """(N, 4, 4) world_from_cam the video was generated along, when recorded."""
    fps: float | None
    """None when video.json records none."""
    meta: dict = field(default_factory=dict)
    """The whole document (backend, upscale, ...)."""

    @property
    def num_frames(self) -> int:
        return len(self.rgb)

    @property
    def has_depth(self) -> bool:
        return bool(self.rgb) and all(d is not None for d in self.depth)


def read_video_doc(video_dir: Path | str) -> VideoDoc:
    """Parse video.json of a video artifact; InputError naming the file (and `rerun the video stage`) on a missing
    file, a missing key, a wrong shape or a size that is not 2:1."""
    root = Path(video_dir)
    path = root / VIDEO_FILE
    try:
        meta = read_json(path)
        h, w = int(meta["height"]), int(meta["width"])
        frames = meta["frames"]
        rgb = [root / f["rgb"] for f in frames]
        depth = [root / f["depth"] if f.get("depth") else None for f in frames]
        scale = float(meta.get("depth_scale") or DEPTH_PNG_SCALE)
        poses = np.asarray(meta["poses"], np.float64) if meta.get("poses") is not None else None
        fps = float(meta["fps"]) if meta.get("fps") else None
    except (OSError, KeyError, TypeError, ValueError) as e:
        raise InputError(f"{path}: cannot read the video description ({e}); rerun the video stage") from None
    if w != 2 * h:
        raise InputError(f"{path}: frames are {w}x{h} (WxH) but ERP frames must be 2:1; rerun the video stage")
    if poses is not None:
        check_shape(f"{path} poses", poses, "N 4 4", dims={"N": len(rgb)})
    return VideoDoc(root, h, w, rgb, depth, scale, poses, fps, meta)


@dataclass
class Video:
    """A loaded video artifact."""

    frames: np.ndarray  # (T, H, W, 3) uint8 RGB
    depth: np.ndarray | None  # (T, H, W) float32 metres along the ray, 0 = unknown; None when the backend has none
    poses: np.ndarray  # (T, 4, 4) float64 world_from_cam (canonical frame, OpenCV camera axes)
    fps: float
    meta: dict = field(default_factory=dict)  # the parsed video.json


def load_video(artifact_dir: Path, *, with_depth: bool = True) -> Video:
    """Read a video artifact directory (video.json, frames/, depth/) into memory."""
    doc = read_video_doc(artifact_dir)
    H, W = doc.height, doc.width
    if doc.poses is None:
        raise InputError(f"{doc.root / VIDEO_FILE}: records no poses; rerun the video stage")
    poses = doc.poses
    frames = np.empty((doc.num_frames, H, W, 3), np.uint8)
    depth = np.zeros((doc.num_frames, H, W), np.float32) if doc.meta.get("has_depth") and with_depth else None
    for t, path in enumerate(doc.rgb):
        img = decode_rgb(path.read_bytes(), what=str(path))
        check_shape(str(path), img, "H W 3", dims={"H": H, "W": W})
        frames[t] = img
        if depth is not None and doc.depth[t] is not None:
            d = read_depth_png(doc.depth[t], doc.depth_scale)
            check_shape(str(doc.depth[t]), d, "H W", dims={"H": H, "W": W})
            depth[t] = d
    return Video(frames, depth, poses, doc.fps or 0.0, doc.meta)


# ---------------------------------------------------------------- frames on disk


VideoFrames = VideoDoc
"""The frames of a video artifact (video.json), with paths resolved against its directory."""


def read_video_frames(video_dir: Path) -> VideoFrames:
    """video.json of a video artifact without loading frames (COLMAP reads them from disk; see
    panoworld.io.video.load_video for the in-memory reader); InputError naming the file on any problem."""
    video = read_video_doc(video_dir)
    if not video.rgb:
        raise InputError(f"{video.root / VIDEO_FILE}: lists no frames; rerun the video stage")
    missing = [str(p) for p in video.rgb if not p.is_file()]
    if missing:
        raise InputError(f"{video.root / VIDEO_FILE}: {len(missing)} frame files are missing (first {missing[0]}); "
                              "rerun the video stage")
    return video


def load_frames(paths: list[Path], height: int | None = None) -> np.ndarray:
    """RGB frames (N, H, W, 3) uint8, resized (INTER_AREA) to height x 2*height when height is given."""
    out = []
    for p in paths:
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(f"{p}: not a readable image; rerun the video stage")
        if height is not None and bgr.shape[0] != height:
            bgr = cv2.resize(bgr, (2 * height, height), interpolation=cv2.INTER_AREA)
        out.append(bgr[..., ::-1])
    return np.stack(out)
