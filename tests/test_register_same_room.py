"""A pose estimated without the dense depths that puts two panoramas of different rooms into one room is refused."""

from __future__ import annotations

import json

import numpy as np

from panoworld.core.conventions import invert_pose
from panoworld.register.pairwise import depth_toward, same_room_refusal


def _gt(home_dir) -> dict[str, np.ndarray]:
    return {k: np.asarray(v, np.float64) for k, v in json.loads((home_dir / "gt" / "poses.json").read_text()).items()}


def test_same_room_refusal_tells_rooms_apart(home_dir):
    gt = _gt(home_dir)
    rooms = json.loads((home_dir / "gt" / "capture_rooms.json").read_text())
    a, b = "pano_00", "pano_01"
    assert rooms[a] != rooms[b]
    depth = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in (a, b)}
    true = invert_pose(gt[a]) @ gt[b]
    # The true pose of two rooms: each camera is behind a wall of the other's depth.
    assert same_room_refusal(true, depth[a], depth[b], min_consistency=0.9) == ""
    # The second room's camera moved 0.25 m from the first: both cameras stand in each other's free space, the two
    # rooms' depths disagree there.
    wrong = true.copy()
    wrong[:3, 3] = [0.25, 0.0, 0.0]
    assert depth_toward(depth[a], wrong[:3, 3]) > 0.5
    reason = same_room_refusal(wrong, depth[a], depth[b], min_consistency=0.9)
    assert reason.startswith("puts the cameras in one room (0.25 m apart") and "consistency" in reason
    # One room seen twice from 0.25 m apart agrees with itself: a same-room pose stays.
    shift = np.eye(4)
    shift[:3, 3] = [0.25, 0.0, 0.0]
    moved = _depth_from(depth[a], shift)
    assert same_room_refusal(shift, depth[a], moved, min_consistency=0.9) == ""


def _depth_from(depth: np.ndarray, a_from_b: np.ndarray) -> np.ndarray:
    """The depth map of panorama a's surfaces seen from camera b (nearest surface per pixel, 0 where none lands)."""
    from panoworld.core.conventions import erp_dirs, erp_pixel_from_dir

    h, w = depth.shape
    pts = erp_dirs(h, w, np.float64).reshape(-1, 3) * depth.reshape(-1, 1)
    b_from_a = invert_pose(a_from_b)
    q = pts @ b_from_a[:3, :3].T + b_from_a[:3, 3]
    r = np.linalg.norm(q, axis=1)
    u, v = erp_pixel_from_dir(q / r[:, None], h, w)
    ui, vi = np.clip(u.astype(int), 0, w - 1), np.clip(v.astype(int), 0, h - 1)
    out = np.full(h * w, np.inf)
    np.minimum.at(out, vi * w + ui, r)
    out[~np.isfinite(out)] = 0
    return out.reshape(h, w).astype(np.float32)
