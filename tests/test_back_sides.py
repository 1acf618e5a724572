"""A thin divider with a doorway: from the next room its back shows the next room's wall colour, not the source side's;
from the capture point nothing changes; a wall whose back no walk reaches gets no back side."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh

from panoworld.core.conventions import erp_dirs, points_from_depth
from panoworld.gaussians.fusion_params import FusionParams
from panoworld.gaussians.pixel import merge_gaussians, pixel_gaussians
from panoworld.geometry.erp_mesh import erp_mesh_from_depth
from panoworld.geometry.raycast import Raycaster
from panoworld.navmesh.build import build_navmesh
from panoworld.render.erp import render_erp
from panoworld.render.metrics import psnr
from panoworld.room.back_sides import back_side_layer, edge_clear, plane_clear

torch.set_num_threads(1)
H, W = 192, 384
FLOOR, CEILING, DOOR_TOP = 1.5, -1.3, -0.6
WALL_Z = (2.0, 2.15)  # the divider between the rooms, a doorway at |x| < DOOR_X under DOOR_TOP
DOOR_X = 0.5
FRONT, BACK, WALL, FLOOR_RGB, CEIL_RGB = (230, 120, 160), (235, 215, 170), (150, 200, 150), (120, 100, 80), (240,) * 3
NEXT_ROOM = np.array([1.2, 0.0, 3.3])  # a camera in the next room, facing the divider's back
CABINET = [[-0.8, -0.3, -1.6], [0.8, FLOOR, -1.0]]  # free-standing, 1.8 m tall (its top unseen), facing the capture point


def colour(p: np.ndarray) -> np.ndarray:
    """The source room's walls green, the next room's cream, the divider's source side (and jambs) pink."""
    y, z = p[..., 1], p[..., 2]
    out = np.broadcast_to(np.array(WALL, float), p.shape).copy()
    out[z > WALL_Z[1] - 1e-3] = BACK
    out[(z > WALL_Z[0] - 1e-3) & (z < WALL_Z[1] - 1e-3)] = FRONT
    out[np.abs(y - FLOOR) < 1e-3] = FLOOR_RGB
    out[np.abs(y - CEILING) < 1e-3] = CEIL_RGB
    return out.astype(np.uint8)


def scene(doorway: bool, cabinet: bool = False) -> trimesh.Trimesh:
    room = trimesh.creation.box(bounds=[[-3.0, CEILING, -2.5], [3.0, FLOOR, 5.0]])
    x = DOOR_X if doorway else 0.0
    parts = [trimesh.creation.box(bounds=[[-3.0, CEILING, WALL_Z[0]], [-x, FLOOR, WALL_Z[1]]]),
             trimesh.creation.box(bounds=[[x, CEILING, WALL_Z[0]], [3.0, FLOOR, WALL_Z[1]]]),
             trimesh.creation.box(bounds=[[-x, CEILING, WALL_Z[0]], [x, DOOR_TOP, WALL_Z[1]]])]
    if cabinet:
        parts.append(trimesh.creation.box(bounds=CABINET))
    return trimesh.util.concatenate([room] + parts)


def source(doorway: bool, cabinet: bool = False):
    """(source Gaussians, rgb, depth, NavMesh of the source depth's mesh, ground-truth ray caster)."""
    full = scene(doorway, cabinet)
    caster = Raycaster(full.vertices, full.faces)
    d = caster.render_erp(np.eye(4), H, W).distance.astype(np.float64)
    rgb = colour(points_from_depth(d, np.eye(4)))
    em = erp_mesh_from_depth(d.astype(np.float32), rgb)
    nav = build_navmesh(em.vertices, em.faces, em.face_valid)
    g = pixel_gaussians(rgb, d, np.eye(4), replace(FusionParams(), scale_factor=2.1))
    return g, rgb, d, nav, caster


@pytest.fixture(scope="module")
def doorway():
    g, rgb, d, nav, caster = source(True)
    back = back_side_layer(g, rgb, d, np.eye(4), nav=nav, thickness=0.12, reach=4.0)
    return g, rgb, d, nav, caster, back


def test_the_divider_seen_from_the_next_room_shows_its_back(doorway):
    g, rgb, d, nav, caster, back = doorway
    assert back.stats["num"] > 500
    assert np.abs(np.asarray(back.stats["color"]) - BACK).max() <= 3  # the next room's walls the doorway shows
    pose = np.eye(4)
    pose[:3, 3] = NEXT_ROOM
    hits = caster.render_erp(pose, 48, 96)
    p = points_from_depth(hits.distance.astype(np.float64), pose)
    on_back = (np.abs(p[..., 2] - WALL_Z[1]) < 1e-3) & (p[..., 0] > DOOR_X + 0.2) & (p[..., 0] < 2.2) & (
        p[..., 1] > DOOR_TOP) & (p[..., 1] < FLOOR - 0.2)
    assert on_back.sum() > 50
    before = (render_erp(g, pose, 48, 96).rgb.numpy() * 255)[on_back]
    after = (render_erp(merge_gaussians([g, back.gaussians]), pose, 48, 96).rgb.numpy() * 255)[on_back]
    assert np.median(np.abs(before - FRONT).max(1)) < 25  # without: the source side's pink seen from behind
    assert np.percentile(np.abs(after - BACK).max(1), 90) < 12


def test_the_capture_point_sees_no_change(doorway):
    g, rgb, d, nav, caster, back = doorway
    ref = rgb.astype(np.float64)
    before = render_erp(g, np.eye(4), H, W).rgb.numpy() * 255
    after = render_erp(merge_gaussians([g, back.gaussians]), np.eye(4), H, W).rgb.numpy() * 255
    # splats of opacity 0.98: the back layer adds at most ~2 % of its colour where the front lets black through
    assert np.abs(after - before).max() < 8 and psnr(after, ref, data_range=255) > psnr(before, ref, data_range=255) - 0.05
    # the divider's back side lies inside it, none in the doorway; the next room's far wall (seen through the
    # doorway, its back out of sight) gets none; the few others lie behind the room's side walls at their corner with
    # the divider, where the next room's unseen side wall leaves a gap in what the source saw
    m = np.asarray(back.gaussians.means)
    inside = (m[:, 2] > WALL_Z[0]) & (m[:, 2] < WALL_Z[1])
    assert inside.mean() > 0.97 and (m[:, 2] < WALL_Z[1]).all()
    assert (np.abs(m[~inside, 0]) > 3.0).all()
    assert not ((np.abs(m[:, 0]) < DOOR_X) & (m[:, 1] > DOOR_TOP)).any()


def test_nothing_behind_walls_no_walk_reaches():
    g, rgb, d, nav, _ = source(False)  # the divider closed: the next room unseen, its floor unreachable
    back = back_side_layer(g, rgb, d, np.eye(4), nav=nav, thickness=0.12, reach=4.0)
    assert back.stats["num"] == 0 and back.stats["upright"] > 1000 and back.stats["color"] is None


def test_furniture_fronts_get_no_back_only_the_rooms_shell():
    g, rgb, d, nav, _ = source(True, cabinet=True)
    m = np.asarray(g.means)
    front = (np.abs(m[:, 2] - CABINET[1][2]) < 0.03) & (np.abs(m[:, 0]) < CABINET[1][0] - 0.1)
    assert front.sum() > 100

    def backs(shell: bool) -> np.ndarray:
        out = back_side_layer(g, rgb, d, np.eye(4), nav=nav, thickness=0.12, reach=4.0, shell=shell)
        return np.asarray(out.gaussians.means)

    def on_cabinet(b: np.ndarray) -> np.ndarray:
        return (b[:, 2] > CABINET[0][2]) & (b[:, 2] < CABINET[1][2] + 1e-3) & (np.abs(b[:, 0]) < CABINET[1][0])

    # the walk beside the cabinet sees past its unseen sides to the space behind its front: the unrestricted rule
    # copies the front
    assert on_cabinet(backs(False)).sum() > 100
    b = backs(True)
    assert not on_cabinet(b).any()
    divider = (b[:, 2] > WALL_Z[0]) & (b[:, 2] < WALL_Z[1])
    assert divider.sum() > 500
    # the rest lie behind the room's outer walls (the wall the cabinet hides from the capture point blocks no sight)
    assert ((np.abs(b[~divider, 0]) > 3.0) | (b[~divider, 2] < -2.5)).all()


def doorway_wall_depth() -> np.ndarray:
    """The source's depth (640 x 1280 rows, ERP): a wall 2 m ahead (camera frame, z forward), a doorway |x| < 0.5
    under y > -0.6 seeing 5 m through it."""
    dirs = erp_dirs(640, 1280, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dirs[..., 2] > 1e-6, 2.0 / dirs[..., 2], np.inf)
    hit = dirs * t[..., None]
    door = (np.abs(hit[..., 0]) < 0.5) & (hit[..., 1] > -0.6)
    return np.where(door, 2.5 * t, np.minimum(t, 8.0))


def test_copies_stay_clear_of_a_doorways_edge_by_their_thickness():
    # doorway_wall_depth(). Points 0.12 m behind the wall count as clear only where every ray within 0.12 m across
    # (on the wall, 0.12 / 2.12 of their distance) hits the wall: else a view 45 degrees off the wall's normal sees
    # them past the jamb (a 3-pixel window is 3 cm there)
    depth = doorway_wall_depth()
    gap = np.linspace(0.01, 0.3, 30)  # from the right jamb, across
    p = np.stack([0.5 + gap, np.zeros_like(gap), np.full_like(gap, 2.12)], 1)
    clear = edge_clear(p, depth, 0.12)
    # seen past the jamb from 45 degrees off the normal: not clear; the window (a square of 12 pixels, taken
    # along the capture point's rays, which bring a point behind the wall 6 % nearer the doorway) costs < 0.08 m more
    assert not clear[gap < 0.12].any() and clear[gap > 0.2].all()
    far = p + [1.0, 0.0, 0.0]  # away from the doorway: clear; in front of the wall: not
    assert edge_clear(far, depth, 0.12).all() and not edge_clear(far - [0.0, 0.0, 0.3], depth, 0.12).any()
    assert edge_clear(p, depth, 0.12, adaptive=False)[gap < 0.12].any()  # the default 3-pixel window: some pass


def test_copies_along_the_wall_keep_a_grazing_wall_drop_a_jamb():
    # doorway_wall_depth(): a wall 2 m ahead with a doorway |x| < 0.5 under y > -0.6. plane_clear moves each
    # copy up to its thickness along the wall's plane: near the jamb (or under the lintel) the moved copy is seen
    # through the doorway, so it goes; far along the wall, where the capture point sees it at a grazing angle (66-69
    # degrees off its normal), it stays, while edge_clear's window across the ray reaches farther along the wall,
    # whose depth there exceeds the copy's, and drops most (some pass by pixel rounding)
    depth = doorway_wall_depth()
    normal = np.array([[0.0, 0.0, -1.0]])  # towards the capture point

    def copies(x, y):
        return np.stack(np.broadcast_arrays(x, y, np.full_like(x, 2.12)), 1)

    gap = np.linspace(0.01, 0.3, 30)
    jamb = copies(0.5 + gap, np.zeros_like(gap))
    clear = plane_clear(jamb, normal.repeat(len(gap), 0), depth, 0.12)
    assert not clear[gap < 0.11].any() and clear[gap > 0.19].all()  # + 3 pixels, and the rays 6 % nearer
    lintel = copies(np.zeros_like(gap), -0.6 - gap)  # above the doorway (y is down)
    clear = plane_clear(lintel, normal.repeat(len(gap), 0), depth, 0.12)
    assert not clear[gap < 0.11].any() and clear[gap > 0.19].all()  # + 3 pixels, and the rays 6 % nearer
    x = np.linspace(4.5, 5.5, 41)
    grazing = copies(x, np.full_like(x, 0.3))
    assert plane_clear(grazing, normal.repeat(len(x), 0), depth, 0.12).all()
    assert edge_clear(grazing, depth, 0.12).mean() < 0.3
    assert not plane_clear(grazing - [0.0, 0.0, 0.3], normal.repeat(len(x), 0), depth, 0.12).any()  # in front


def test_plane_clear_keeps_the_divider_and_drops_its_jambs(doorway):
    g, rgb, d, nav, _, back = doorway
    clear = back_side_layer(g, rgb, d, np.eye(4), nav=nav, thickness=0.12, reach=4.0, plane=True)
    m = np.asarray(clear.gaussians.means)
    divider = (m[:, 2] > WALL_Z[0]) & (m[:, 2] < WALL_Z[1])
    assert divider.sum() > 0.6 * back.stats["num"]  # 384 columns: the 3-pixel window is 0.1 m on the divider
    near_jamb = (np.abs(np.abs(m[:, 0]) - DOOR_X) < 0.1) & (m[:, 1] > DOOR_TOP - 0.1)
    assert not near_jamb[divider].any()
    assert np.asarray(back.gaussians.means)[:, 0].size > m.shape[0]
