"""A home whose floors do not connect (a closed doorway, as layout-only depth gives): the NavMesh holds every capture
point's floor as its own component, and the trajectory walks within a component and cuts between them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from panoworld.core.conventions import pose_from_rt
from panoworld.geometry.navmesh import HOME_SNAP_M
from panoworld.geometry.raycast import Raycaster
from panoworld.io.trajectory import load_clips, path_indices, write_trajectory
from panoworld.mesh.fuse import fuse_meshes
from panoworld.navmesh.home import home_navmesh
from panoworld.trajectory import TrajectoryParams, poses_from_positions, validate_poses
from panoworld.trajectory.home import plan_home

CAM_H = 1.5
HEIGHT = 96
CAPTURES = {"a": (-2.0, 0.3), "b": (2.0, -0.2), "c": (3.8, 1.0)}
"""Capture points (x, z): a in the west room, b and c in the east room (c 0.2 m from its wall: off the eroded floor)."""


def two_rooms(door: bool) -> trimesh.Trimesh:
    """Two 4 x 4 m rooms (x < 0 and x > 0, floor at y = CAM_H, 2.6 m high) sharing the wall x = 0, with a 1 m wide
    doorway in it (door) or without."""
    t, h = 0.1, 2.6

    def box(ext, c):
        b = trimesh.creation.box(extents=ext)
        b.apply_translation(c)
        return b

    mid = CAM_H - h / 2
    parts = [box((8 + 2 * t, t, 4 + 2 * t), (0, CAM_H + t / 2, 0)), box((8 + 2 * t, t, 4 + 2 * t), (0, CAM_H - h - t / 2, 0)),
             box((t, h, 4), (-4 - t / 2, mid, 0)), box((t, h, 4), (4 + t / 2, mid, 0)),
             box((8, h, t), (0, mid, -2 - t / 2)), box((8, h, t), (0, mid, 2 + t / 2))]
    if door:  # the wall x = 0 on either side of the doorway z in (-0.5, 0.5), and above it
        parts += [box((t, h, 1.5), (0, mid, -1.25)), box((t, h, 1.5), (0, mid, 1.25)),
                  box((t, 0.6, 1.0), (0, CAM_H - h + 0.3, 0))]
    else:
        parts.append(box((t, h, 4), (0, mid, 0)))
    return trimesh.util.concatenate(parts)


def _home(door: bool, rig_deg: float = 0.0):
    """The fused mesh of the two rooms seen from CAPTURES, and the capture poses; rig_deg > 0: no depth within that
    angle of each panorama's nadir (the capture rig)."""
    gt = two_rooms(door)
    rc = Raycaster(gt.vertices, gt.faces)
    poses = {n: pose_from_rt(np.eye(3), np.array([x, 0.0, z])) for n, (x, z) in CAPTURES.items()}
    depths = {n: rc.render_erp(T, HEIGHT, 2 * HEIGHT).distance.astype(np.float32) for n, T in poses.items()}
    for d in depths.values():
        d[HEIGHT - int(np.ceil(rig_deg / 180 * HEIGHT)):] = 0.0
    rgbs = {n: np.full((HEIGHT, 2 * HEIGHT, 3), 128, np.uint8) for n in poses}
    mesh, _ = fuse_meshes(list(poses), rgbs, depths, poses, stride=1)
    return mesh, poses


@pytest.fixture(scope="module")
def closed_home():
    mesh, poses = _home(door=False)
    return mesh, poses, *home_navmesh(mesh, poses)


def test_navmesh_holds_every_capture_point_in_one_component_per_floor(closed_home):
    _, _, nav, on = closed_home
    assert on == {"a": True, "b": True, "c": False}
    home = nav.info["home"]
    comp = home["capture_components"]
    assert comp["b"] == comp["c"] != comp["a"]
    assert [sorted(c["capture_points"]) for c in home["components"]] == [["a"], ["b", "c"]]
    # each room's floor eroded (4 m minus the erosion on each side), nothing between them
    side = 4 - 2 * nav.info["erosion_m"]
    for c in home["components"]:
        assert abs(c["area_m2"] - side**2) < 0.1 * side**2, home
    assert not nav.contains(np.array([[0.0, 0.0]]))[0]
    with pytest.raises(ValueError, match="no path"):
        nav.path(np.array(CAPTURES["a"]), np.array(CAPTURES["b"]))


def test_the_rig_blind_spot_under_every_capture_point_is_floor():
    """a stands alone in its room: nobody else sees the floor under its rig; it is assumed floor as for one panorama."""
    mesh, poses = _home(door=False, rig_deg=25.0)
    nav, on = home_navmesh(mesh, poses)
    assert on["a"] and on["b"], on
    assumed = nav.info["assumed_walkable"]
    assert 1.0 < assumed["blind_spot_m2"] < 2.5 and assumed["blind_spot_radius_m"] < 1.0, assumed
    assert nav.clearance(np.array([CAPTURES["a"]]))[0] > 0.5


def test_connected_home_stays_one_component():
    mesh, poses = _home(door=True)
    nav, on = home_navmesh(mesh, poses)
    assert on["a"] and on["b"] and len(nav.info["home"]["components"]) == 1
    assert set(nav.info["home"]["capture_components"].values()) == {0}
    plan = plan_home(nav, poses, TrajectoryParams(sectors=4), 30)
    assert plan.info["cuts"] == [] and len([p for p in plan.info["paths"] if "walk" in p]) == 2


def test_home_trajectory_walks_within_a_component_and_cuts_between(closed_home, tmp_path):
    mesh, poses, nav, _ = closed_home
    plan = plan_home(nav, poses, TrajectoryParams(sectors=4), 60)
    info, xz = plan.info, plan.positions
    # every pose but the capture frames and the straight way from c onto the NavMesh stands on it (no walk through
    # the wall between the rooms) ...
    caps = sorted(info["capture_frames"].values())
    approach = sorted(set(plan.exempt) - set(caps))
    assert set(caps) <= set(plan.exempt) and approach
    assert np.all(np.linalg.norm(xz[approach] - CAPTURES["c"], axis=1) < 0.25)
    inside = nav.contains(xz)
    assert inside[[i for i in range(len(xz)) if i not in plan.exempt]].all(), f"{(~inside).sum()} poses off the NavMesh"
    # ... and no path (its predecessor included) goes from one component to the other: every clip is one walk
    comp = nav.component_of(xz, HOME_SNAP_M)
    for p in info["paths"]:
        idx = path_indices(p)
        assert len(set(comp[idx])) == 1, p
        assert np.all(np.linalg.norm(np.diff(xz[idx], axis=0), axis=1) < 0.5), p  # steps of ~0.3 m, never 4 m
    assert info["unreached_captures"] == [] and sorted(info["visit_order"]) == ["a", "b", "c"]
    assert len(info["cuts"]) == 1 and "a" in info["cuts"][0] and info["components"]["b"] == info["components"]["c"]
    walks = [p["walk"] for p in info["paths"] if "walk" in p]
    assert walks in ([["b", "c"]], [["c", "b"]]), walks  # the only walk: within the east room
    poses_ = poses_from_positions(xz)
    clearance = np.full(len(xz), 1.0)
    assert validate_poses(poses_, nav, clearance, agent_radius=0.25, skip=tuple(plan.exempt)) == []
    write_trajectory(tmp_path, poses_, clearance, fps=16.0, paths=info["paths"])
    assert sorted({i for c in load_clips(tmp_path, len(xz)) for i in c}) == list(range(len(xz)))


def test_the_run_says_why_the_floors_do_not_connect_and_what_joins_them(closed_home, tmp_path):
    """Under the run table (framework.pipeline.scene_notes): a home whose NavMesh holds its capture points on two
    pieces is named with its pieces and, for each registration edge across them, what joined the two panoramas: floor
    both see beyond their own rooms' walls (a hallway no depth holds) or a pose without an open doorway; one piece
    says nothing."""
    from panoworld.framework.pipeline import scene_notes
    from panoworld.io.jsonio import write_json

    _, _, nav, _ = closed_home
    arts = {"navmesh": tmp_path / "navmesh", "register": tmp_path / "register"}
    for d in arts.values():
        d.mkdir()
    write_json(arts["register"] / "panoramas.json", {n: T.tolist() for n, T in closed_home[1].items()})
    write_json(arts["navmesh"] / "manifest.json", {"info": {"components": nav.info["home"]["components"]}})
    write_json(arts["register"] / "registration.json", {"panoramas": {
        "a": {"registered": True, "parent": None},
        "b": {"registered": True, "parent": "a", "edge": "floor", "beyond_rooms": 10, "inlier_matches": 11},
        "c": {"registered": True, "parent": "b", "edge": "depth"}}})
    (note,) = [n for n in scene_notes(arts, tmp_path) if "NavMesh pieces" in n]
    assert note.startswith("home: the floor is 2 NavMesh pieces that do not connect (a | b, c), so the trajectory "
                           "cuts between them: a and b see one floor beyond both rooms' walls (10 of 11 floor matches)")
    assert "b and c" not in note and note.endswith("a panorama taken where their floors meet joins them (docs/multi.md)")
    doc = {"panoramas": {"a": {"parent": None}, "b": {"parent": "a", "edge": "floor", "beyond_rooms": 2,
                                                     "inlier_matches": 30}, "c": {"parent": "b", "edge": "depth"}}}
    write_json(arts["register"] / "registration.json", doc)
    (note,) = scene_notes(arts, tmp_path)
    assert "a and b are joined by a floor pose, but no doorway between their floors was seen open" in note
    write_json(arts["navmesh"] / "manifest.json", {"info": {"components": nav.info["home"]["components"][:1]}})
    assert scene_notes(arts, tmp_path) == []
