"""The next room seen through a doorway: its hidden floor takes the top-down map of the floor the doorway shows, its
hidden walls and ceiling the colour of the walls and the ceiling the doorway shows."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from panoworld.core.conventions import points_from_depth
from panoworld.geometry.erp_mesh import erp_mesh_from_depth
from panoworld.geometry.raycast import Raycaster
from panoworld.room import plane_colors
from panoworld.video.background_layer import BackgroundLayer, build_background_layer

torch.set_num_threads(1)
H, W = 128, 256
FLOOR, CEILING, DOOR_TOP = 1.2, -1.6, -1.2
WALL_Z = (2.0, 2.15)  # the wall between the rooms, a doorway in it at |x| < DOOR_X under DOOR_TOP
DOOR_X = 0.45
FLOOR_A, FLOOR_B = (200, 180, 120), (60, 90, 200)  # the source room's floor, the next room's
WALL_RGB, FRAME_RGB, CEIL_RGB = (150, 200, 150), (240, 60, 60), (230, 230, 240)
WALL_B, CEIL_B, POSTER = (235, 215, 170), (120, 160, 140), (40, 60, 220)  # the next room's walls, ceiling, and
POSTER_X, POSTER_Y = (0.75, 1.3), (-1.0, 0.6)  # posters on its far wall at the edges of what the doorway shows


def colour(p: np.ndarray) -> np.ndarray:
    y, z = p[..., 1], p[..., 2]
    out = np.broadcast_to(np.array(WALL_RGB, float), p.shape).copy()
    floor = np.abs(y - FLOOR) < 1e-3
    out[floor & (z < WALL_Z[0])] = FLOOR_A
    out[floor & (z >= WALL_Z[0])] = FLOOR_B
    out[(z > WALL_Z[1] + 1e-3) & ~floor] = WALL_B
    ax = np.abs(p[..., 0])
    out[(z > 5.0 - 1e-3) & (ax > POSTER_X[0]) & (ax < POSTER_X[1]) & (y > POSTER_Y[0]) & (y < POSTER_Y[1])] = POSTER
    out[np.abs(y - CEILING) < 1e-3] = CEIL_RGB
    out[(np.abs(y - CEILING) < 1e-3) & (z > WALL_Z[1] + 1e-3)] = CEIL_B
    frame = (z > WALL_Z[0] - 1e-3) & (z < WALL_Z[1] + 1e-3) & ~floor & (np.abs(y - CEILING) > 1e-3)
    out[frame] = FRAME_RGB  # the divider's faces, the doorway's jambs and lintel: a colour found nowhere else
    return out.astype(np.uint8)


def scene():
    room = trimesh.creation.box(bounds=[[-3.0, CEILING, -2.5], [3.0, FLOOR, 5.0]])
    parts = [trimesh.creation.box(bounds=[[-3.0, CEILING, WALL_Z[0]], [-DOOR_X, FLOOR, WALL_Z[1]]]),
             trimesh.creation.box(bounds=[[DOOR_X, CEILING, WALL_Z[0]], [3.0, FLOOR, WALL_Z[1]]]),
             trimesh.creation.box(bounds=[[-DOOR_X, CEILING, WALL_Z[0]], [DOOR_X, DOOR_TOP, WALL_Z[1]]])]
    full = trimesh.util.concatenate([room] + parts)
    d = Raycaster(full.vertices, full.faces).render_erp(np.eye(4), H, W).distance.astype(np.float64)
    room_d = Raycaster(room.vertices, room.faces).render_erp(np.eye(4), H, W).distance.astype(np.float64)
    return d, room_d


@pytest.fixture(scope="module")
def layers():
    d, room_d = scene()
    rgb = colour(points_from_depth(d, np.eye(4)))
    mesh = erp_mesh_from_depth(d.astype(np.float32), rgb)
    layers = {on: build_background_layer(mesh, 1.5, plane_colors=on) for on in (False, True)}
    layers["walls"] = build_background_layer(mesh, 1.5, plane_colors=True, next_room_colors=True)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plane_colors, "NEXT_CEILING", True)
        layers["ceiling"] = build_background_layer(mesh, 1.5, plane_colors=True, next_room_colors=True)
    return mesh, d, room_d, layers


def layer_rgb(mesh, layer: BackgroundLayer) -> np.ndarray:
    out = np.zeros((H, W, 3))
    k = int(layer.synthesized.sum())
    out[layer.synthesized] = layer.colors[len(mesh.vertices):len(mesh.vertices) + k]
    return out


def test_hidden_floor_beyond_the_doorway_takes_the_floor_seen_through_it(layers):
    mesh, d, room_d, layer = layers
    p_true = points_from_depth(room_d, np.eye(4))
    hidden_b = (room_d > d * 1.2) & (np.abs(p_true[..., 1] - FLOOR) < 1e-3) & (p_true[..., 2] > WALL_Z[1] + 0.1)
    near = hidden_b & (np.abs(p_true[..., 0]) < 1.5)  # within about REACH_M of the floor the doorway shows
    errs = {}
    for on in (False, True):
        s = layer[on].synthesized & hidden_b
        assert s.sum() > 0.4 * hidden_b.sum() and (s & near).sum() > 30
        e = np.abs(layer_rgb(mesh, layer[on]) - FLOOR_B).max(axis=-1)
        errs[on] = e[s], e[s & near]
    # the default inpaints across the door frame: a third of these pixels get its red or the near room's floor
    assert np.mean(errs[False][0] > 30) > 0.3 and np.quantile(errs[False][1], 0.9) > 25
    assert np.quantile(errs[True][1], 0.9) < 8 and np.mean(errs[True][0]) < 0.6 * np.mean(errs[False][0])
    # the doorway's lintel is the room's wall there (not the next room's far wall seen under it)
    walls = layer[True].floor_map.walls
    assert np.isfinite(walls.dist).all() and np.abs(walls.dist[W // 2 - 4:W // 2 + 4] - WALL_Z[0]).max() < 0.05


def test_the_map_paints_only_the_floor_beyond_the_room(layers):
    fm = layers[3][True].floor_map
    # on the next room's floor near / far from what the doorway shows, on the source room's floor, on a wall
    pts = np.array([[0.0, FLOOR, 3.5], [0.8, FLOOR, 3.0], [2.9, FLOOR, 4.9], [-1.0, FLOOR, 1.0], [0.0, 0.0, 4.99]])
    before = np.full((5, 3), 7, np.uint8)
    rgb, done = fm.paint(pts, before)
    assert done.tolist() == [True, True, True, False, False]
    assert np.abs(rgb[:2].astype(int) - FLOOR_B).max() < 10
    assert (rgb[3:] == 7).all()
    # far from any floor seen (a corner the doorway does not show), partly the colour it had
    assert np.abs(rgb[2].astype(int) - FLOOR_B).max() > np.abs(rgb[1].astype(int) - FLOOR_B).max()


def test_hidden_next_room_walls_and_ceiling_take_the_colours_seen_through_the_doorway(layers):
    mesh, _, _, layer = layers
    n0 = len(mesh.vertices)
    k = int(layer[True].synthesized.sum())
    assert int(layer["walls"].synthesized.sum()) == k  # the same layer points, recoloured
    pts = layer[True].vertices[n0:n0 + k].astype(np.float64)
    # layer points on the next room's far wall (the plane z = 5 continued behind the divider) and ceiling, hidden
    far_wall = (np.abs(pts[:, 2] - 5.0) < 0.05) & (pts[:, 1] > CEILING + 0.1) & (pts[:, 1] < FLOOR - 0.1)
    hidden = np.abs(pts[:, 0]) > DOOR_X * 5.0 / WALL_Z[0] + 0.2  # beyond what the doorway shows of that wall
    ceiling = (np.abs(pts[:, 1] - CEILING) < 0.02) & (pts[:, 2] > WALL_Z[1] + 0.2)
    assert (far_wall & hidden).sum() > 50 and ceiling.sum() > 20
    fm = layer["ceiling"].floor_map
    assert np.abs(fm.wall_rgb - WALL_B).max() < 6 and np.abs(fm.ceiling_rgb - CEIL_B).max() < 6
    assert layer["walls"].floor_map.ceiling_rgb is None  # NEXT_CEILING off: the ceiling keeps its colour
    assert (layer["walls"].colors[n0:n0 + k][ceiling] == layer[True].colors[n0:n0 + k][ceiling]).all()
    for part, truth, v in ((far_wall & hidden, WALL_B, "walls"), (ceiling, CEIL_B, "ceiling")):
        err = {u: np.abs(layer[u].colors[n0:n0 + k][part].astype(int) - truth).max(axis=1) for u in (True, v)}
        assert np.quantile(err[v], 0.9) < 8 and err[v].mean() < err[True].mean()
        if truth == WALL_B:  # the default inpaints the posters at the doorway's edges over the hidden wall
            assert np.mean(err[True] > 30) > 0.5
    # only points beyond the room's shell change, none on the floor (the floor map's)
    changed = (layer["walls"].colors[n0:n0 + k] != layer[True].colors[n0:n0 + k]).any(axis=1)
    assert changed.sum() > 100 and (pts[changed, 2] > WALL_Z[0]).all()
    assert not (changed & (np.abs(pts[:, 1] - FLOOR) < 0.02)).any()
