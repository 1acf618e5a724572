"""video.json of a video artifact: the one parser (frames, depth PNGs, poses, fps) every reader goes through."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from panoworld.conventions import DEPTH_PNG_SCALE
from panoworld.errors import InputError
from panoworld.io.jsonio import read_json
from panoworld.shapes import check_shape

VIDEO_FILE = "video.json"


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
