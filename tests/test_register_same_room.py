"""A pose estimated without the dense depths that puts two panoramas of different rooms into one room is refused."""

from __future__ import annotations

import json

import numpy as np

from panoworld.core.conventions import invert_pose
from panoworld.gaussians.home import depth_from_others
from panoworld.register.pairwise import depth_toward, free_space_violation, rooms_overlap_refusal, same_room_refusal


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
    # Panorama a's surfaces seen from the shifted camera: the z-buffer of its points there.
    moved = depth_from_others(0, ["b", "a"], {"b": depth[a], "a": depth[a]}, {"a": np.eye(4), "b": shift},
                              height=depth[a].shape[0]).astype(np.float32)
    assert same_room_refusal(shift, depth[a], moved, min_consistency=0.9) == ""



def test_rooms_overlap_refusal_tells_adjoining_rooms_from_overlapping_ones(home_dir):
    gt = _gt(home_dir)
    a, b = "pano_00", "pano_01"
    depth = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in (a, b)}
    true = invert_pose(gt[a]) @ gt[b]
    # The true pose: the second room's surfaces lie behind the first room's walls or on what it sees through a doorway.
    assert max(free_space_violation(true, depth[a], depth[b])) < 0.01  # furniture silhouettes are no evidence
    # Counting them: the downsampled depth there mixes near and far, points in mid-air in the other room.
    assert max(free_space_violation(true, depth[a], depth[b], edge=np.inf)) > max(
        free_space_violation(true, depth[a], depth[b]))
    assert rooms_overlap_refusal(true, depth[a], depth[b]) == ""
    # The second room turned a quarter about its own camera: its walls cut through the first room.
    turned = true @ np.array([[0.0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]])
    assert max(free_space_violation(turned, depth[a], depth[b])) > 0.05
    assert "the rooms overlap" in rooms_overlap_refusal(turned, depth[a], depth[b])
    # A depth that does not hold its whole room (masked layout) is not judged.
    masked = depth[b].copy()
    masked[: masked.shape[0] // 4] = 0
    assert rooms_overlap_refusal(turned, depth[a], masked) == ""


def test_refuse_overlapping_rooms_judges_a_chance_fit_by_every_room_it_joins(home_dir):
    from panoworld.register.graph import DEPTH, FLOOR, Edge, solve_graph
    from panoworld.register.options import RegisterOptions
    from panoworld.register.solve import refuse_overlapping_rooms

    gt = _gt(home_dir)
    names = ["pano_00", "pano_01", "pano_02"]
    depth = {n: np.load(home_dir / "depths" / f"{n}.npy") for n in names}
    # pano_02's depth does not hold its whole room: no pair with it is judged.
    depth["pano_02"][: depth["pano_02"].shape[0] // 4] = 0
    rel = {(a, b): invert_pose(gt[a]) @ gt[b] for a in names for b in names}
    turned = rel["pano_00", "pano_01"] @ np.array([[0.0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]])
    # A strong chance floor fit joins pano_01 through pano_02 with its room turned into pano_00's; a weaker floor fit
    # gives pano_01's true pose.
    chance = Edge(a="pano_02", b="pano_01", a_from_b=rel["pano_02", "pano_00"] @ turned, kind=FLOOR, inliers=15, info={})
    edges = [Edge(a="pano_00", b="pano_02", a_from_b=rel["pano_00", "pano_02"], kind=DEPTH, inliers=40, info={}),
             chance,
             Edge(a="pano_00", b="pano_01", a_from_b=rel["pano_00", "pano_01"], kind=FLOOR, inliers=9, info={})]
    poses, _ = solve_graph(names, list(edges), {})
    assert not np.allclose(invert_pose(poses["pano_00"]) @ poses["pano_01"], rel["pano_00", "pano_01"], atol=1e-3)
    refused = refuse_overlapping_rooms(names, edges, {}, depth, RegisterOptions())
    assert list(refused) == [("pano_02", "pano_01")]
    kind, why = refused["pano_02", "pano_01"]
    assert kind == FLOOR and "pano_01's room into pano_00's" in why and "the rooms overlap" in why
    assert all(e is not chance for e in edges)
    poses, info = solve_graph(names, edges, {})
    assert np.allclose(invert_pose(poses["pano_00"]) @ poses["pano_01"], rel["pano_00", "pano_01"], atol=1e-6)
    # The true registration is left as it is.
    assert refuse_overlapping_rooms(names, edges, {}, depth, RegisterOptions()) == {}
