"""Layout registration of panoramas in adjoining rooms: wall outlines from layout depth, the overlap test, and on two
rendered rooms joined by a doorway (layout depth closes it, the images see through it) the pose against ground truth;
unrelated images give no trusted pose; layout edges rank below the image-based metric edges in the pose graph."""

from __future__ import annotations

import numpy as np
import pytest

from panoworld.core.conventions import erp_dirs, invert_pose
from panoworld.geometry.upright import yaw_matrix, yaw_of
from panoworld.register.graph import BEARING, LAYOUT, Edge, solve_graph
from panoworld.register.layout import LayoutPose, layout_pair, manhattan_frame, overlaps, room, walls_of
from panoworld.register.options import RegisterOptions
from panoworld.register.solve import _off_manhattan, manhattan_yaws, register_panoramas

H = 128
FLOOR_Y, CEIL_Y = 1.4, -1.0  # camera frame y down: floor below, ceiling above every camera
ROOM_A = (-2.0, 1.5, -1.5, 2.0)  # x0, x1, z0, z1 of the world floor plan
WALL = 0.15
ROOM_B = (1.5 + WALL, 5.0, -1.0, 2.5)
DOOR = (0.0, 1.0, -0.6)  # z0, z1 of the opening in the shared wall x = 1.5 .. 1.65, its top (y)


def _trusted(p: LayoutPose) -> bool:
    o = RegisterOptions()
    return p.score >= o.layout_min_score and p.score >= o.layout_min_margin * p.second


def _pose(yaw_deg: float, x: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = yaw_matrix(np.radians(yaw_deg)), [x, 0.0, z]
    return T


def _exit(o: np.ndarray, d: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """Ray length (N,) from points o (N, 3) inside box along d (N, 3) to the box's walls, floor or ceiling."""
    x0, x1, z0, z1 = box
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(d[:, 0] > 0, (x1 - o[:, 0]) / d[:, 0], (x0 - o[:, 0]) / d[:, 0])
        tz = np.where(d[:, 2] > 0, (z1 - o[:, 2]) / d[:, 2], (z0 - o[:, 2]) / d[:, 2])
        ty = np.where(d[:, 1] > 0, (FLOOR_Y - o[:, 1]) / d[:, 1], (CEIL_Y - o[:, 1]) / d[:, 1])
    return np.nanmin(np.where(np.stack([tx, ty, tz]) > 0, np.stack([tx, ty, tz]), np.inf), axis=0)


def _colour(p: np.ndarray, seed: int) -> np.ndarray:
    """A texture fixed to the world: sums of sines of the surface point (N, 3) -> gray (N,) in [0, 1]."""
    rng = np.random.default_rng(seed)
    g = np.zeros(len(p))
    for _ in range(12):
        k = rng.normal(size=3) * 6.0
        g += np.sin(p @ k + rng.uniform(0, 2 * np.pi))
    return 0.5 + 0.5 * np.tanh(g / 4)


def _render(world_from_cam: np.ndarray, inside: tuple, other: tuple, seed: int = 0
            ) -> tuple[np.ndarray, np.ndarray]:
    """ERP (H, 2H, 3) of a camera in room `inside` seeing `other` through the doorway, and its layout depth (the
    doorway closed)."""
    d = (erp_dirs(H, 2 * H, np.float64) @ world_from_cam[:3, :3].T).reshape(-1, 3)
    o = np.broadcast_to(world_from_cam[:3, 3], d.shape)
    t = _exit(o, d, inside)
    p = o + t[:, None] * d
    z0, z1, top = DOOR
    door = (np.abs(np.abs(p[:, 0] - 1.575) - 0.075) < 1e-6) & (p[:, 2] > z0) & (p[:, 2] < z1) & (p[:, 1] > top)
    q = p[door] + d[door] * (WALL / np.abs(d[door, 0]))[:, None]
    p[door] = q + _exit(q, d[door], other)[:, None] * d[door]
    rgb = np.repeat((255 * _colour(p, seed))[:, None], 3, 1).reshape(H, 2 * H, 3).astype(np.uint8)
    return rgb, t.reshape(H, 2 * H)


def test_walls_of_a_rectangle_room():
    cam = _pose(20.0, -0.5, 0.3)
    r = room(*_render(cam, ROOM_A, ROOM_B))
    assert r is not None and len(r.walls) == 4
    # the walls' normals are the room's axes seen from a camera turned by 20 degrees
    assert abs(np.degrees(np.angle(np.exp(4j * (r.theta - np.radians(20.0))))) / 4) < 0.5
    lengths = np.array([np.linalg.norm(w.p1 - w.p0) for w in r.walls])
    assert np.abs(lengths - 3.5).max() < 0.15  # corners fall between the 256 columns
    assert walls_of(np.full(256, np.nan)) == []


def test_manhattan_frames_give_the_relative_yaw_modulo_90_degrees():
    wa, wb = _pose(20.0, -0.5, 0.3), _pose(-113.0, 3.0, 0.5)
    ta, tb = manhattan_frame(_render(wa, ROOM_A, ROOM_B)[1]), manhattan_frame(_render(wb, ROOM_B, ROOM_A)[1])
    assert ta is not None and tb is not None
    yaws = manhattan_yaws(ta, tb)
    truth = yaw_of((invert_pose(wa) @ wb)[:3, :3])
    assert np.degrees(np.abs(np.angle(np.exp(1j * (yaws - truth)))).min()) < 0.5
    o = RegisterOptions()
    assert _off_manhattan(_pose(np.degrees(truth) + 3.0, 1.0, 0.0), yaws, o) == ""
    assert "off the rooms' wall directions" in _off_manhattan(_pose(np.degrees(truth) + 30.0, 1.0, 0.0), yaws, o)
    assert _off_manhattan(_pose(33.0, 1.0, 0.0), None, o) == ""


@pytest.mark.parametrize("yaw_deg", [7.3, -33.1])
def test_manhattan_frame_is_fitted_to_the_walls_to_a_hundredth_of_a_degree(yaw_deg):
    """A floor edge takes its yaw from the two wall directions: their error turns everything beyond it in a chain of
    rooms (0.1 deg is 1.7 cm at 10 m). The normals are fitted to every outline point of a wall, not taken from the two
    polyline ends next to the rounded corners (which tilt them by 0.04-0.14 deg here)."""
    cam = _pose(yaw_deg, -0.4, 0.2)
    d = (erp_dirs(2 * H, 4 * H, np.float64) @ cam[:3, :3].T).reshape(-1, 3)
    depth = _exit(np.broadcast_to(cam[:3, 3], d.shape), d, ROOM_A).reshape(2 * H, 4 * H)
    depth *= 1 + 0.003 * np.random.default_rng(0).normal(size=depth.shape)  # 3 mm per metre of range
    theta = manhattan_frame(depth)
    assert theta is not None
    assert np.degrees(np.abs(np.angle(np.exp(4j * (theta - np.radians(yaw_deg)))))) / 4 < 0.01


def test_no_manhattan_frame_without_a_right_angled_outline():
    depth = _render(_pose(0.0, 0.0, 0.0), ROOM_A, ROOM_B)[1]
    masked = depth.copy()
    masked[:, : depth.shape[1] // 4] = 0  # a quarter of the outline unknown (layout masked as implausible)
    assert manhattan_frame(masked) is None
    d = erp_dirs(H, 2 * H, np.float64)
    circle = 2.0 / np.maximum(np.hypot(d[..., 0], d[..., 2]), 1e-6)  # a round room: no walls at right angles
    circle = np.minimum(circle, np.where(d[..., 1] > 0, FLOOR_Y / np.maximum(d[..., 1], 1e-6), np.inf))
    circle = np.minimum(circle, np.where(d[..., 1] < 0, -CEIL_Y / np.maximum(-d[..., 1], 1e-6), np.inf))
    assert manhattan_frame(circle) is None


def test_overlapping_placement_is_rejected():
    a = room(*_render(_pose(0, -0.5, 0.3), ROOM_A, ROOM_B))
    b = room(*_render(_pose(0, 3.3, 1.0), ROOM_B, ROOM_A))
    assert not overlaps(a, b, 0.0, np.array([3.8, 0.7]))  # the true placement: side by side, a wall between
    assert overlaps(a, b, 0.0, np.array([1.0, 0.7]))  # b's room pushed into a's


def test_adjoining_rooms_register_through_the_doorway():
    wa, wb = _pose(0.0, -0.5, 0.3), _pose(100.0, 3.3, 1.0)
    a = room(*_render(wa, ROOM_A, ROOM_B))
    b = room(*_render(wb, ROOM_B, ROOM_A))
    p = layout_pair(a, b, step_m=0.2)  # a coarser slide than the default keeps the test fast; the refinement does the rest
    gt = invert_pose(wa) @ wb
    assert np.linalg.norm(p.a_from_b[[0, 2], 3] - gt[[0, 2], 3]) < 0.1  # two of the refinement's 5 cm steps
    assert abs(np.degrees(yaw_of(p.a_from_b[:3, :3]) - yaw_of(gt[:3, :3]))) < 1.0
    assert _trusted(p) and p.score > 2.0 * p.second


def test_unrelated_images_give_no_clear_pose():
    wa, wb = _pose(0.0, -0.5, 0.3), _pose(100.0, 3.3, 1.0)
    a = room(*_render(wa, ROOM_A, ROOM_B, seed=0))
    b = room(*_render(wb, ROOM_B, ROOM_A, seed=1))  # another world's texture: nothing agrees
    p = layout_pair(a, b, step_m=0.2)  # a coarser slide than the default keeps the test fast; the refinement does the rest
    assert not _trusted(p)


def test_layout_edges_rank_below_bearing_edges():
    near, far = _pose(0.0, 1.0, 0.0), _pose(0.0, 9.0, 0.0)
    edges = [Edge(a="a", b="b", a_from_b=np.eye(4), kind=BEARING, inliers=30, info={}),
             Edge(a="a", b="c", a_from_b=far, kind=LAYOUT, inliers=900, info={}),
             Edge(a="b", b="c", a_from_b=near, kind=BEARING, inliers=25, info={})]
    poses, info = solve_graph(["a", "b", "c"], edges)
    assert info["c"]["edge"] == BEARING and np.allclose(poses["c"], near)


@pytest.mark.slow
def test_register_panoramas_joins_adjoining_rooms_by_a_layout_edge():
    wa, wb = _pose(0.0, -0.5, 0.3), _pose(100.0, 3.3, 1.0)
    (ra, da), (rb, db) = _render(wa, ROOM_A, ROOM_B), _render(wb, ROOM_B, ROOM_A)
    reg = register_panoramas(["a", "b"], {"a": ra, "b": rb}, {"a": da, "b": db},
                             options=RegisterOptions(height=H, layout=True))
    assert reg.panoramas["b"]["edge"] == LAYOUT  # no depth, floor or bearing edge: the doorway is all they share
    gt = invert_pose(wa) @ wb
    assert np.linalg.norm(reg.world_from_cam["b"][[0, 2], 3] - gt[[0, 2], 3]) < 0.1
    assert abs(np.degrees(yaw_of(reg.world_from_cam["b"][:3, :3]) - yaw_of(gt[:3, :3]))) < 1.0
    off = register_panoramas(["a", "b"], {"a": ra, "b": rb}, {"a": da, "b": db},
                             options=RegisterOptions(height=H))  # layout off by default
    assert "b" not in off.world_from_cam


def _splat_reference(pts, gray, T, stride, depth_t, behind, beyond):
    """numpy oracle of layout._splat: the nearest point per target pixel beyond depth * behind + beyond."""
    from panoworld.core.conventions import erp_pixel_from_lonlat, lonlat_from_dir

    h, w = depth_t.shape
    p = pts[::stride, ::stride].reshape(-1, 3).astype(np.float64)
    g = gray[::stride, ::stride].reshape(-1)
    keep = np.any(p != 0, axis=1)
    q = p[keep] @ T[:3, :3].T + T[:3, 3]
    g = g[keep]
    r = np.linalg.norm(q, axis=1)
    u, v = erp_pixel_from_lonlat(*lonlat_from_dir(q), h, w)
    u, v = np.floor(u).astype(int) % w, np.floor(v).astype(int)
    ok = (r >= 1e-6) & (v >= 0) & (v < h)
    d = np.where(ok, depth_t[np.clip(v, 0, h - 1), u], 0.0)
    ok &= (d > 0) & (r >= d * behind + beyond)
    out, zb = np.zeros((h, w), np.float32), np.full((h, w), np.inf)
    for k in np.flatnonzero(ok):
        if r[k] < zb[v[k], u[k]]:
            zb[v[k], u[k]], out[v[k], u[k]] = r[k], g[k]
    return out, np.isfinite(zb)


def test_splat_kernel_matches_its_numpy_reference():
    from panoworld.register.layout import _splat

    rng = np.random.default_rng(3)
    pts = rng.normal(0.0, 3.0, (40, 80, 3))
    pts[rng.random((40, 80)) < 0.1] = 0.0  # no depth there
    gray = rng.random((40, 80)).astype(np.float32)
    T = _pose(30.0, 0.7, -0.4)
    depth_t = rng.uniform(0.5, 4.0, (24, 48))
    depth_t[rng.random((24, 48)) < 0.1] = 0.0
    for stride in (1, 2):
        got, filled = _splat(pts, gray, T, stride, depth_t, 1.02, 0.4)
        want, want_filled = _splat_reference(pts, gray, T, stride, depth_t, 1.02, 0.4)
        np.testing.assert_array_equal(filled, want_filled)
        np.testing.assert_array_equal(got, want)
        assert 20 < filled.sum() < filled.size
