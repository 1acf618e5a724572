"""Convert a dataset scene with ground-truth ERP frames + poses (InteriorGS-like, no mesh) to our scene layout.

    python -m panoworld.tools.eval.convert POSES OUT_SCENE --rgb 'frames/{:06d}.png' [--depth 'depth/{:06d}.npy']
                                     [--start 0] [--stride 1] [--frames 81] [--camera-axes opencv|opengl]

POSES: world_from_cam poses, a JSON ({"poses": [4x4...]} or {"world_from_cam": ...}), a TUM file, or a nerfstudio
transforms.json (frames[].transform_matrix, OpenGL camera axes). OUT_SCENE gets panorama.png (frame `start`),
depth.npy (when depth is given), gt/gt.json + gt/tracks/track_00.json + gt/frames/ (the whole track, for eval and
precompute) and trajectory.json (the clip the pipeline follows: `frames` poses from `start` every `stride` track
frames, in the canonical frame of the first one), so `runner.py eval` scores every generated frame against the
ground-truth frame at its pose.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from panoworld.core.limits import load_npy
from panoworld.io.images import read_image

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def read_poses(path: Path, camera_axes: str = "opencv") -> tuple[np.ndarray, list[str] | None]:
    """(world_from_cam (N, 4, 4) with OpenCV camera axes, frame file names from a transforms.json or None)."""
    from panoworld.io.trajectory import read_trajectory_file

    path = Path(path)
    names = None
    text = path.read_text()
    doc = json.loads(text) if text.lstrip().startswith(("{", "[")) else None
    if isinstance(doc, dict) and "frames" in doc and "poses" not in doc:  # nerfstudio transforms.json
        frames = doc["frames"]
        poses = np.asarray([f["transform_matrix"] for f in frames], np.float64)
        names = [f.get("file_path") for f in frames]
        camera_axes = "opengl"
    elif isinstance(doc, dict) and "world_from_cam" in doc:
        poses = np.asarray(doc["world_from_cam"], np.float64)
    else:
        poses = read_trajectory_file(path)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{path}: poses have shape {poses.shape} but expected (N, 4, 4)")
    if camera_axes == "opengl":
        poses = poses @ OPENGL_TO_OPENCV
    return poses, names


def convert_frames_scene(poses_file: Path, out: Path, rgb: str, depth: str | None = None, *, start: int = 0,
                         stride: int = 1, frames: int = 81, camera_axes: str = "opencv") -> Path:
    """Write OUT as a frames + poses scene (module docstring); returns OUT. rgb/depth: str.format patterns of the
    track frame index (relative to the poses file's directory unless absolute)."""
    import cv2

    poses, _ = read_poses(poses_file, camera_axes)
    base = Path(poses_file).parent
    n = len(poses)
    if not 0 <= start < n or stride < 1 or frames < 2:
        raise ValueError(f"--start {start} --stride {stride} --frames {frames}: need 0 <= start < {n}, stride >= 1, frames >= 2")
    out = Path(out)
    gt = out / "gt"
    (gt / "tracks").mkdir(parents=True, exist_ok=True)
    rgb_dir, depth_dir = gt / "frames" / "track_00" / "rgb", gt / "frames" / "track_00" / "depth"
    rgb_dir.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        src = base / rgb.format(i)
        if not src.is_file():
            raise ValueError(f"{src}: missing frame {i} of the track ({n} poses); check --rgb")
        cv2.imwrite(str(rgb_dir / f"{i:06d}.png"), read_image(src, cv2.IMREAD_COLOR, what="frame"))
        if depth:
            depth_dir.mkdir(parents=True, exist_ok=True)
            d = load_npy(base / depth.format(i), "depth frame").astype(np.float32)
            np.save(depth_dir / f"{i:06d}.npy", d)
    world_from_canonical = poses[start]
    (gt / "tracks" / "track_00.json").write_text(json.dumps({"world_from_cam": poses.tolist()}))
    index = {
        "format": "frames",
        "world_from_canonical": world_from_canonical.tolist(),
        "tracks": [{"poses": "tracks/track_00.json", "n_frames": n,
                    "frames": {"rgb": "frames/track_00/rgb/{:06d}.png",
                               "depth": "frames/track_00/depth/{:06d}.npy" if depth else None}}],
    }
    (gt / "gt.json").write_text(json.dumps(index, indent=1))
    shutil.copyfile(rgb_dir / f"{start:06d}.png", out / "panorama.png")
    if depth:
        shutil.copyfile(depth_dir / f"{start:06d}.npy", out / "depth.npy")
    idx = list(range(start, n, stride))[:frames]
    canonical = np.linalg.inv(world_from_canonical)[None] @ poses[idx]
    (out / "trajectory.json").write_text(json.dumps({"poses": canonical.tolist(), "track_frames": idx}))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m panoworld.tools.eval.convert", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("poses", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--rgb", required=True, help="frame pattern, e.g. 'pano_camera0/frame_{:04d}.png'")
    ap.add_argument("--depth", help="ray-distance depth pattern (float32 .npy, metres)")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--stride", type=int, default=1, help="track frames between clip frames (the paper's r)")
    ap.add_argument("--frames", type=int, default=81)
    ap.add_argument("--camera-axes", choices=["opencv", "opengl"], default="opencv")
    a = ap.parse_args(argv)
    try:
        convert_frames_scene(a.poses, a.out, a.rgb, a.depth, start=a.start, stride=a.stride, frames=a.frames,
                             camera_axes=a.camera_axes)
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
