"""Implausible layout depth: floor and ceiling beyond the walls, surfaces through the camera (panoworld.room.plausible)."""

from __future__ import annotations

import numpy as np
import pytest

from panoworld.core.conventions import erp_dirs
from panoworld.geometry.polygons import ring_area
from panoworld.room.plausible import NEAR_PLANE_M, STAND_RADIUS_M, mask_implausible, wall_bounds
from panoworld.tools.synth.annotation import polygon_layout_depth

CAM_H, CEIL_H = 1.4, 1.0  # floor below, ceiling above the camera (m)


def layout_depth(polygon, cam_xz, H=128, W=256):
    """The layout depth of polygon seen from cam_xz, CAM_H above its floor and CEIL_H under its ceiling."""
    return polygon_layout_depth(polygon, cam_xz, CAM_H, CEIL_H, H, W)


def points(depth, valid):
    H, W = depth.shape
    return (erp_dirs(H, W, np.float64) * depth[..., None])[valid]


def hull_area(xz):
    import cv2

    return float(cv2.contourArea(cv2.convexHull(xz.astype(np.float32))))


ROOM = [(-2.0, -1.5), (2.0, -1.5), (2.0, 1.5), (-2.0, 1.5)]  # 4 x 3 m


def test_a_room_seen_from_inside_is_left_alone():
    depth = layout_depth(ROOM, np.array([0.4, -0.3]))
    valid = depth > 0
    d2, v2, _, rec = mask_implausible(depth, valid, CAM_H, CEIL_H)
    assert d2 is depth and v2 is valid
    assert rec["near_surface_px"] == rec["far_floor_px"] == rec["far_ceiling_px"] == 0 and rec["masked_fraction"] == 0
    assert rec["room_floor_area_m2"] == pytest.approx(abs(ring_area(np.asarray(ROOM, float))), rel=0.03)  # the walls outline the room


def test_a_camera_outside_its_room_keeps_its_floor_in_the_room():
    # The camera stands 0.4 m outside the polygon's edge: rays that miss the walls reach the floor and ceiling up to
    # hundreds of metres away. What is left of them lies within the walls' reach or the tripod's stand.
    cam = np.array([0.0, -1.9])
    depth = layout_depth(ROOM, cam)
    valid = depth > 0
    floor_before = points(depth, valid & (np.abs(depth * erp_dirs(*depth.shape)[..., 1] - CAM_H) < 0.01))
    assert np.hypot(floor_before[:, 0], floor_before[:, 2]).max() > 50
    d2, v2, _, rec = mask_implausible(depth, valid, CAM_H, CEIL_H)
    assert rec["far_floor_px"] > 0 and rec["far_ceiling_px"] > 0 and rec["near_surface_px"] == 0
    pts = points(d2, v2)
    on_floor = np.abs(pts[:, 1] - CAM_H) < 0.01
    r = np.hypot(pts[:, 0], pts[:, 2])
    bound = wall_bounds(depth, valid, CAM_H, CEIL_H)[0]
    assert r.max() <= max(STAND_RADIUS_M, bound.max()) * 1.05 + 0.1  # nothing recedes past the walls
    assert hull_area(pts[on_floor][:, [0, 2]]) <= 1.5 * abs(ring_area(np.asarray(ROOM, float)))
    assert not (d2[~v2]).any() and np.array_equal(d2[v2], depth[v2])  # masked, never moved
    assert 0 < rec["masked_fraction"] < 1 and rec["max_depth_after"] < 10 < rec["max_depth_before"]


def test_a_wall_line_through_the_camera_never_becomes_geometry_at_the_camera():
    # The camera 5 cm from its polygon's edge (a doorway line annotated through the tripod): that plane, seen
    # edge-on, covers half the sphere; none of it survives, the rest of the room does.
    cam = np.array([0.3, -1.45])
    depth = layout_depth(ROOM, cam)
    valid = depth > 0
    pts_all = points(depth, valid)
    on_line = np.abs(pts_all[:, 2] - (-0.05)) < 1e-3
    assert on_line.mean() > 0.2 and np.linalg.norm(pts_all, axis=1).min() < 0.06
    d2, v2, _, rec = mask_implausible(depth, valid, CAM_H, CEIL_H)
    pts = points(d2, v2)
    floor = np.abs(pts[:, 1] - CAM_H) < 1e-3
    assert np.linalg.norm(pts, axis=1).min() >= 0.10
    assert not (np.abs(pts[~floor, 2] + 0.05) < 1e-3).any()  # nothing of the line's plane is left
    # The tripod stands on a doorway line: the floor continues beyond it, completed from the floor plane within the
    # stand's radius and no farther.
    beyond = pts[floor & (pts[:, 2] < -0.05)][:, [0, 2]]
    assert rec["stand_floor_px"] >= len(beyond) > 0
    assert np.hypot(beyond[:, 0], beyond[:, 1]).max() <= STAND_RADIUS_M + 1e-4
    assert hull_area(beyond) > 0.8 * np.pi * STAND_RADIUS_M ** 2 / 2
    assert rec["near_surface_px"] >= on_line.sum() * 0.99
    kept_other = v2[valid].reshape(-1)[~on_line].mean()
    assert kept_other > 0.97, kept_other  # the room's other walls, floor and ceiling stay


def test_nothing_stands_in_the_tripods_column_the_floor_under_it_does():
    # The camera on a doorway line (5 cm from its polygon's edge) and a surface 0.2 m below it, 2-6 cm beside its
    # vertical axis (what is left of that line where the plane test cannot follow it into the stretched nadir): not
    # geometry; the floor is completed beyond it. Surfaces beside the column, and the floor, stay. Without a
    # surface through the camera (a camera set on a table) the column is left alone.
    H, W = 256, 512
    plain = layout_depth(ROOM, np.array([0.4, -0.3]), H, W)
    depth = layout_depth(ROOM, np.array([0.3, -1.45]), H, W)
    d = erp_dirs(H, W, np.float64)
    horiz = np.hypot(d[..., 0], d[..., 2])
    t = 0.2 / np.maximum(d[..., 1], 1e-9)  # rays reaching 0.2 m below the camera ...
    stub = (d[..., 1] > 0) & (t * horiz < 0.06) & (t * horiz > 0.02) & (d[..., 0] > 0)  # ... 2-6 cm aside, one side
    beside = (d[..., 1] > 0) & (np.abs(t * horiz - 0.4) < 0.02) & (d[..., 2] > 0.5 * horiz)  # 0.4 m aside, in the room
    depth[stub | beside] = t[stub | beside]
    plain[stub | beside] = t[stub | beside]
    valid = depth > 0
    assert stub.any() and beside.any()
    d_plain, _, _, rec_plain = mask_implausible(plain, plain > 0, CAM_H, CEIL_H)
    assert rec_plain["tripod_column_px"] == 0 and d_plain is plain
    d2, v2, _, rec = mask_implausible(depth, valid, CAM_H, CEIL_H)
    pts = points(d2, v2)
    r = np.hypot(pts[:, 0], pts[:, 2])
    inside = (r < NEAR_PLANE_M) & (pts[:, 1] > 0) & (pts[:, 1] < CAM_H * 0.98)  # below the camera, above the floor
    assert 0 < rec["tripod_column_px"] <= stub.sum() and not inside.any()  # the plane test takes a few itself
    assert v2[beside].all() and np.array_equal(d2[beside], depth[beside])
    assert v2[stub].all() and np.allclose(d2[stub] * d[..., 1][stub], CAM_H, rtol=1e-4)  # the floor behind it
    floor = v2 & valid & ~stub & ~beside & (np.abs(depth * d[..., 1] - CAM_H) < 1e-3)
    assert np.allclose(d2[floor], depth[floor], rtol=1e-5)  # the floor stays where it is


@pytest.mark.parametrize("cam", [(0.3, -1.45), (0.0, -1.9)])
def test_the_depth_cleaning_leaves_what_was_masked_unknown(cam):
    # Through the depth stage's cleaning (near cut, poles and dropouts completed): the wall through the camera and the
    # floor beyond the walls are neither completed back nor nearer than 10 cm, and the manifest says what was done.
    from pathlib import Path

    from panoworld.depth.clean import clean_depth
    from panoworld.depth.options import Rescale

    depth = layout_depth(ROOM, np.array(cam), 128, 256)
    valid = depth > 0
    c = clean_depth(np.zeros((*depth.shape, 3), np.uint8), depth, valid, relative=False, rescale=Rescale.AUTO,
                    camera_height=1.6, min_depth_m=0.1, detect_rig=None, rig_mask=None, complete_poles=True,
                    complete_dropouts=True, source=Path("depth.npy"))
    pts = points(c.depth, c.valid)
    assert len(pts) and np.linalg.norm(pts, axis=1).min() >= 0.10
    assert np.hypot(pts[:, 0], pts[:, 2]).max() < 6.0  # nothing reaches past the room (its diagonal is 5 m)
    assert not c.depth[~c.valid].any()
    rec = c.info["plausibility"]
    assert rec["masked_fraction"] > 0.05 and any(n.startswith("implausible room geometry masked") for n in c.notes)


@pytest.mark.parametrize("cam_x, stored", [(-0.5, np.float32), (-0.5, np.float16), (1.4, np.float16)])
def test_a_wall_through_another_capture_point_is_no_geometry_of_the_home(cam_x, stored):
    # Camera B stood in a doorway that camera A's layout closes with a wall line: that wall is dropped from A's depth
    # (near_captures_mask) where B stood, at every height (a doorway); the wall beside it, A's other walls, floor and
    # ceiling stay, and without B nothing is dropped. Also with the depth rounded to float16 as ZInD stores it (its
    # rounding bends the wall by more than the plane test's share of a pixel step), and with A 0.6 m from that wall.
    from panoworld.room.plausible import NEAR_REACH_M, near_captures_mask

    cam = np.array([cam_x, 0.2])
    depth = layout_depth(ROOM, cam, 512, 1024).astype(stored).astype(np.float32)
    world_from_a = np.eye(4)
    world_from_a[[0, 2], 3] = cam
    pts = points(depth, depth > 0) + [cam[0], 0.0, cam[1]]
    on_wall = (np.abs(pts[:, 0] - 2.0) < 1e-3).reshape(-1)
    b = np.array([[2.0, 0.0, 0.3]])
    drop = near_captures_mask(depth, world_from_a, b)[depth > 0]
    along = np.abs(pts[:, 2] - 0.3)
    door, beside = on_wall & (along < NEAR_REACH_M - 0.05), on_wall & (along > NEAR_REACH_M + 0.3)  # + its rim
    assert door.sum() > 200 and drop[door].mean() > 0.99
    assert beside.sum() > 200 and drop[beside].mean() < 0.01
    assert drop[~on_wall].mean() < 0.01
    assert not near_captures_mask(depth, world_from_a, np.zeros((0, 3))).any()
    assert not near_captures_mask(depth, world_from_a, np.array([[0.5, 0.0, -0.4]])).any()  # B in the open room


def test_surfaces_through_other_capture_points_dropped_on_threads_as_on_one():
    """drop_near_captures finds each panorama's mask on its own: on two worker threads the depths are zeroed exactly
    where one thread zeroes them, and the counts per panorama are the same."""
    from panoworld.room.plausible import drop_near_captures

    cams = {"a": np.array([-0.5, 0.2]), "b": np.array([2.0, 0.3]), "c": np.array([0.4, -0.6])}
    poses = {}
    for n, cam in cams.items():
        poses[n] = np.eye(4)
        poses[n][[0, 2], 3] = cam
    base = {n: layout_depth(ROOM, cam, 128, 256).astype(np.float32) for n, cam in cams.items()}
    got = {}
    for workers in (1, 2):
        depths = {n: d.copy() for n, d in base.items()}
        got[workers] = (drop_near_captures(depths, poses, workers=workers), depths)
    assert got[1][0] == got[2][0] and got[1][0]["a"] > 0
    assert all(np.array_equal(got[1][1][n], got[2][1][n]) for n in cams)
