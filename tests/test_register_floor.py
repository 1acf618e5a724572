"""Floor-plane registration of upright panoramas: camera height from depth, the metric top-down floor images and the
1-point oriented rigid fit recover (x, z, yaw) against ground truth; unrelated floors give no supported pose; the pose graph
joins groups by a floor edge, and the registration of a pair uses it."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from panoworld.core.conventions import erp_dirs, invert_pose
from panoworld.geometry.floor_view import camera_height, floor_view, nearest_both_ways, squared_distances
from panoworld.geometry.upright import yaw_matrix, yaw_of
from panoworld.register.floor import (
    fixed_yaw_translation,
    floor_pair,
    floor_support,
    oriented_rigid2d_ransac,
    runner_up,
)
from panoworld.register.graph import FLOOR, Edge, solve_graph
from panoworld.register.options import RegisterOptions
from panoworld.register.solve import register_panoramas

H = 512
FLOOR_Y = 1.4  # the floor, below every camera (y down)


def _texture(seed: int, n: int = 1024) -> np.ndarray:
    """(n, n) uint8 blob texture covering x, z in [-8, 8] m (1.6 cm cells)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((n, n)).astype(np.float32), (0, 0), 3)
    img = (img - img.min()) / (img.max() - img.min())
    return (255 * img).astype(np.uint8)


def _pose(yaw_deg: float, x: float, z: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = yaw_matrix(np.radians(yaw_deg)), [x, y, z]
    return T


def _render(world_from_cam: np.ndarray, tex: np.ndarray, rows: int = H) -> tuple[np.ndarray, np.ndarray]:
    """An upright ERP panorama (rows, 2 rows, 3) of a textured floor plane (world y = FLOOR_Y) under a grey ceiling
    1 m above the camera, and its ray depth."""
    d = erp_dirs(rows, 2 * rows, np.float64) @ world_from_cam[:3, :3].T
    cam_y = world_from_cam[1, 3]
    rng_floor = np.where(d[..., 1] > 1e-3, (FLOOR_Y - cam_y) / np.maximum(d[..., 1], 1e-3), np.inf)
    rng_ceil = np.where(d[..., 1] < -1e-3, 1.0 / np.maximum(-d[..., 1], 1e-3), np.inf)
    depth = np.minimum(np.minimum(rng_floor, rng_ceil), 30.0)
    p = world_from_cam[:3, 3] + d * rng_floor[..., None]
    n = tex.shape[0]
    u, v = (p[..., 0] + 8) / 16 * n, (p[..., 2] + 8) / 16 * n
    ok = np.isfinite(rng_floor) & (rng_floor < 30)
    g = cv2.remap(tex, np.where(ok, u, -1).astype(np.float32), np.where(ok, v, -1).astype(np.float32),
                  cv2.INTER_LINEAR, borderValue=128)
    g = np.where(ok, g, 200).astype(np.uint8)
    return np.repeat(g[..., None], 3, 2), depth.astype(np.float32)


def test_camera_height_in_a_narrow_room_is_the_floor_not_the_walls():
    """A camera in a closet 0.6 m wide: walls fill most of the cone below 40 degrees, floor pixels are a minority of
    it; the height is still the floor's, not a median of every height there."""
    d = erp_dirs(H, 2 * H, np.float64)
    dy = np.maximum(d[..., 1], 1e-9)
    to_floor = np.where(d[..., 1] > 1e-3, FLOOR_Y / dy, np.inf)
    to_wall = np.where(np.abs(d[..., 0]) > 1e-9, 0.3 / np.maximum(np.abs(d[..., 0]), 1e-9), np.inf)
    depth = np.minimum(np.minimum(to_floor, to_wall), 30.0).astype(np.float32)
    down = d[..., 1] > np.sin(np.radians(40.0))
    assert (depth[down] < to_floor[down] - 1e-3).mean() > 0.5  # walls are most of the cone
    assert abs(camera_height(depth) - FLOOR_Y) < 0.005
    flat = np.minimum(to_floor, 30.0).astype(np.float32)  # every height in the cone one value (one histogram bin)
    assert abs(camera_height(flat) - FLOOR_Y) < 1e-4


def test_a_supersampled_floor_image_is_the_floor_averaged_over_each_cell():
    """Within 2 m of the camera a 1.6 cm floor cell spans several pixels of a 2048-wide panorama: one bilinear sample
    per cell aliases a fine floor texture (about 1 cm blobs), 3 x 3 samples averaged give the texture averaged over
    each cell (the reference: the texture itself area-resized to the cells) at half the error; farther out, where the
    panorama's pixels are coarser than a cell, the two agree."""
    from panoworld.geometry.floor_view import floor_image

    n, radius, cell = 4096, 4.0, 0.016  # texels of 3.9 mm over [-8, 8] m; 500 cells over [-4, 4] m
    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.random((n, n)).astype(np.float32), (0, 0), 1.0)
    tex = (255 * (tex - tex.min()) / (tex.max() - tex.min())).astype(np.uint8)
    rgb, _ = _render(_pose(0.0, 0.0, 0.0), tex, rows=1024)
    crop = tex[n // 4:3 * n // 4, n // 4:3 * n // 4].astype(np.float32)
    truth = cv2.resize(crop, (500, 500), interpolation=cv2.INTER_AREA)[::-1]  # row 0 = far +z
    c = (np.arange(500) + 0.5) * cell - radius
    r = np.hypot(*np.meshgrid(c, c))

    def rmse(k: int, lo: float, hi: float) -> float:
        img = floor_image(rgb, FLOOR_Y, radius_m=radius, cell_m=cell, supersample=k)[..., 0].astype(np.float32)
        ring = (r > lo) & (r < hi)
        return float(np.sqrt(np.mean((img[ring] - truth[ring]) ** 2)))

    assert rmse(3, 1.0, 2.0) < 0.65 * rmse(1, 1.0, 2.0)
    assert rmse(3, 1.0, 2.0) < 0.45 * truth.std()
    assert abs(rmse(3, 3.0, 3.9) - rmse(1, 3.0, 3.9)) < 0.1 * rmse(1, 3.0, 3.9)


def test_a_turned_floor_view_returns_its_keypoints_in_the_camera_frame():
    """A floor image laid along other axes (turn) holds the same floor: its keypoints, returned in the camera's frame,
    fit the unturned view's at the identity; and a panorama turned about gravity by whole columns, whose floor image is
    turned back by as much, gives the unturned floor image (the same samples) and a fit at the panorama's own yaw."""
    rgb, depth = _render(_pose(0.0, 0.0, 0.0), _texture(3))
    plain = floor_view(rgb, depth, radius_m=4.0)
    for turn in (np.pi / 2, 0.61):
        turned = floor_view(rgb, depth, radius_m=4.0, turn=turn)
        p = floor_pair(plain, turned)
        assert p.inliers > 0.3 * len(plain.xz)
        assert np.abs(p.a_from_b[[0, 2], 3]).max() < 0.01 and abs(np.degrees(yaw_of(p.a_from_b[:3, :3]))) < 0.2
    k = 2 * H // 8  # a 45 degree turn of the camera
    rolled_rgb, rolled_depth = np.roll(rgb, k, axis=1), np.roll(depth, k, axis=1)
    back = 2 * np.pi * k / (2 * H)
    from panoworld.geometry.floor_view import floor_image

    same = floor_image(rolled_rgb, FLOOR_Y, radius_m=4.0, cell_m=0.015, turn=back)
    assert np.abs(same.astype(int) - floor_image(rgb, FLOOR_Y, radius_m=4.0, cell_m=0.015).astype(int)).max() <= 1
    p = floor_pair(plain, floor_view(rolled_rgb, rolled_depth, radius_m=4.0, turn=back))
    assert p.inliers > 0.5 * len(plain.xz)
    assert np.abs(p.a_from_b[[0, 2], 3]).max() < 0.01
    assert abs(abs(np.degrees(yaw_of(p.a_from_b[:3, :3]))) - 45.0) < 0.2


def test_floor_pair_recovers_upright_pose_on_a_shared_floor():
    tex = _texture(0)
    wa, wb = _pose(20.0, 0.3, -0.2), _pose(-113.0, 2.1, 1.4, y=0.05)
    (ra, da), (rb, db) = _render(wa, tex), _render(wb, tex)
    assert abs(camera_height(da) - FLOOR_Y) < 0.01
    assert abs(camera_height(db) - (FLOOR_Y - 0.05)) < 0.01
    va, vb = floor_view(ra, da, radius_m=4.0), floor_view(rb, db, radius_m=4.0)
    p = floor_pair(va, vb)
    assert p is not None and p.inliers >= 50
    truth = invert_pose(wa) @ wb
    assert np.linalg.norm(p.a_from_b[:3, 3] - truth[:3, 3]) < 0.03
    dyaw = np.degrees(yaw_of(p.a_from_b[:3, :3]) - yaw_of(truth[:3, :3]))
    assert abs((dyaw + 180) % 360 - 180) < 0.5
    # The matches that agree with a pose given beforehand: the truth's are about the fit's inliers, a shifted one's none.
    assert floor_support(va, vb, truth) >= 0.8 * p.inliers
    shifted = truth.copy()
    shifted[0, 3] += 0.5
    assert floor_support(va, vb, shifted) <= 2


def test_a_floor_pair_is_the_same_whichever_panorama_comes_first():
    """Swapping the two panoramas (renaming them) gives the same matches, the same inliers and the inverse pose."""
    tex = _texture(3)
    wa, wb = _pose(35.0, 0.0, 0.0), _pose(-70.0, 3.2, 1.1)  # 3.4 m apart: each floor image holds a part of the other
    va, vb = floor_view(*_render(wa, tex), radius_m=4.0), floor_view(*_render(wb, tex), radius_m=4.0)
    ab, ba = floor_pair(va, vb), floor_pair(vb, va)
    assert ab is not None and ba is not None and ab.inliers >= 20
    assert (ab.matches, ab.inliers, ab.second) == (ba.matches, ba.inliers, ba.second)
    assert sorted(map(tuple, ab.matched)) == sorted(map(tuple, ba.matched[:, ::-1]))
    assert np.abs(ab.a_from_b @ ba.a_from_b - np.eye(4)).max() < 1e-6
    truth = invert_pose(wa) @ wb
    assert np.linalg.norm(ab.a_from_b[:3, 3] - truth[:3, 3]) < 0.03


def test_nearest_both_ways_is_numpys_argmin_along_both_axes_ties_included():
    """The one-pass kernel gives numpy's argmin along the rows and along the columns (the first index on a tie) on
    descriptor distances and on a matrix of ties; squared_distances is the plain formula clipped at 0, to the bit."""
    from panoworld.framework import kernels

    rng = np.random.default_rng(0)
    da, db = (rng.random((300, 128)) * 100).astype(np.float32), (rng.random((257, 128)) * 100).astype(np.float32)
    d2 = squared_distances(da, db)
    ref = np.maximum((da * da).sum(1)[:, None] + (db * db).sum(1)[None] - 2.0 * (da @ db.T), 0.0)
    assert d2.dtype == np.float32 and np.array_equal(d2.view(np.int32), ref.view(np.int32))
    ties = rng.integers(0, 3, (200, 150)).astype(np.float32)
    for m in (d2, ties, ties[:1], ties[:, :1]):
        m = np.ascontiguousarray(m)
        ab, ba = nearest_both_ways(m)
        assert np.array_equal(ab, m.argmin(1)) and np.array_equal(ba, m.argmin(0))
    listed = {tuple(sig) for _, _, fn, sig in kernels.kernel_specs() if fn == "nearest_both_ways"}
    assert {tuple(s) for s in nearest_both_ways.signatures} == listed


def test_a_repeated_floor_pattern_leaves_a_runner_up_a_pattern_period_away():
    """On tiles (a 0.5 m period) other translations a whole number of tiles away agree too (FloorPose.second); on an
    aperiodic floor no other translation comes close."""
    wa, wb = _pose(0.0, 0.0, 0.0), _pose(0.0, 2.0, 0.7)
    tiles = np.tile(_texture(4, 256)[:32, :32], (32, 32))  # 32 x 32 tiles of 0.5 m over the 16 m texture
    truth = invert_pose(wa) @ wb
    second = {}
    for name, tex in (("tiles", tiles), ("blobs", _texture(4))):
        p = floor_pair(floor_view(*_render(wa, tex), radius_m=4.0), floor_view(*_render(wb, tex), radius_m=4.0),
                       yaws=np.array([0.0]))
        assert p is not None and p.inliers >= 20
        off = (p.a_from_b[[0, 2], 3] - truth[[0, 2], 3]) / 0.5
        assert np.allclose(off, np.round(off), atol=0.06)  # the fit is the truth up to whole tiles
        second[name] = p.second / p.inliers
    assert second["tiles"] >= 0.2 and second["blobs"] <= 0.05, second


def test_runner_up_is_the_best_translation_away_from_the_fit():
    rng = np.random.default_rng(5)
    q = rng.uniform(-3, 3, (300, 2))
    t_true, t_decoy = np.array([1.0, 0.5]), np.array([3.5, 0.5])  # a decoy 2.5 m along the baseline
    p = rng.uniform(-3, 3, (300, 2))
    p[:12], p[12:20] = q[:12] + t_true, q[12:20] + t_decoy
    dtheta, dlog2 = np.where(np.arange(300) < 20, 0.0, rng.uniform(-np.pi, np.pi, 300)), np.zeros(300)
    assert runner_up(p, q, dtheta, dlog2, 0.0, t_true, threshold=0.05) == 8
    assert runner_up(p, q, dtheta, dlog2, 0.0, t_decoy, threshold=0.05) == 12
    assert runner_up(p[:12], q[:12], dtheta[:12], dlog2[:12], 0.0, t_true, threshold=0.05) == 0
    # counted as a fit's inliers are, once per keypoint spot: the decoy's 8 matches on 2 spots of each view are 2
    spots = (np.arange(300), np.arange(300))
    spots[0][12:20], spots[1][12:20] = 1000 + np.arange(8) // 4, 2000 + np.arange(8) % 2
    assert runner_up(p, q, dtheta, dlog2, 0.0, t_true, threshold=0.05, spots=spots) == 2
    assert runner_up(p, q, dtheta, dlog2, 0.0, t_decoy, threshold=0.05, spots=spots) == 12


def test_unrelated_floors_give_no_supported_pose():
    wa, wb = _pose(0.0, 0.0, 0.0), _pose(40.0, 1.5, 0.5)
    va = floor_view(*_render(wa, _texture(1)), radius_m=4.0)
    vb = floor_view(*_render(wb, _texture(2)), radius_m=4.0)
    p = floor_pair(va, vb)
    assert p is None or p.inliers < 8  # RegisterOptions.min_floor_inliers


def test_oriented_rigid2d_ransac_needs_position_orientation_and_scale_to_agree():
    rng = np.random.default_rng(3)
    n_true, n = 10, 600
    q = rng.uniform(-3, 3, (n, 2))
    yaw = np.radians(70.0)
    R = yaw_matrix(yaw)[[0, 2]][:, [0, 2]]  # acting on (x, z)
    p = rng.uniform(-3, 3, (n, 2))  # outliers everywhere ...
    p[:n_true] = q[:n_true] @ R.T + [1.0, -0.5] + rng.normal(0, 0.005, (n_true, 2))
    dtheta = rng.uniform(-np.pi, np.pi, n)
    dtheta[:n_true] = yaw + rng.normal(0, 0.02, n_true)
    dlog2 = rng.normal(0, 0.3, n)
    # ... and a decoy: matches that agree in position under another yaw, but not in keypoint orientation
    decoy = slice(n_true, 3 * n_true)
    R2 = yaw_matrix(-1.0)[[0, 2]][:, [0, 2]]
    p[decoy] = q[decoy] @ R2.T + [0.2, 0.3]
    yaw_hat, t, inl = oriented_rigid2d_ransac(p, q, dtheta, dlog2, threshold=0.03)
    assert inl[:n_true].sum() >= n_true - 1 and inl[n_true:].sum() <= 1
    assert abs(yaw_hat - yaw) < np.radians(0.5) and np.allclose(t, [1.0, -0.5], atol=0.01)
    # the same positions without orientation agreement: nothing beyond chance
    _, _, inl = oriented_rigid2d_ransac(p, q, rng.uniform(-np.pi, np.pi, n), dlog2, threshold=0.03)
    assert inl.sum() <= 3


def test_fixed_yaw_translation_takes_the_candidate_yaw_the_matches_agree_with():
    rng = np.random.default_rng(4)
    n_true, n = 8, 800
    q = rng.uniform(-3, 3, (n, 2))
    yaw = np.radians(-37.0)
    R = yaw_matrix(yaw)[[0, 2]][:, [0, 2]]
    p = rng.uniform(-3, 3, (n, 2))
    p[:n_true] = q[:n_true] @ R.T + [0.4, 2.1] + rng.normal(0, 0.005, (n_true, 2))
    dtheta = rng.uniform(-np.pi, np.pi, n)
    dtheta[:n_true] = yaw + rng.normal(0, 0.05, n_true)
    dlog2 = rng.normal(0, 0.3, n)
    cands = yaw + np.arange(4) * np.pi / 2
    yaw_hat, t, inl = fixed_yaw_translation(p, q, dtheta, dlog2, cands, threshold=0.03)
    assert yaw_hat == cands[0] and inl[:n_true].all() and inl[n_true:].sum() <= 1
    assert np.allclose(t, [0.4, 2.1], atol=0.01)
    # candidates 20 degrees off the truth: the true matches no longer agree
    _, _, inl = fixed_yaw_translation(p, q, dtheta, dlog2, cands + np.radians(20.0), threshold=0.03)
    assert inl.sum() <= 3


def test_floor_pair_with_the_yaw_fixed_recovers_the_translation():
    tex = _texture(6)
    wa, wb = _pose(10.0, 0.0, 0.0), _pose(-68.0, 1.9, -0.7)
    va, vb = (floor_view(*_render(w, tex), radius_m=4.0) for w in (wa, wb))
    truth = invert_pose(wa) @ wb
    yaw = yaw_of(truth[:3, :3])
    p = floor_pair(va, vb, yaws=yaw + np.arange(4) * np.pi / 2)
    assert p is not None and p.inliers >= 50
    assert abs(yaw_of(p.a_from_b[:3, :3]) - yaw) < 1e-9
    assert np.linalg.norm(p.a_from_b[:3, 3] - truth[:3, 3]) < 0.03


def _views_of(points: np.ndarray, b_from_a_xz: tuple[float, float, float], height: float = 1.4):
    """Floor views a, b whose keypoints are the floor points (N, 2) (x, z in a's frame, several keypoints per point
    allowed), b at (x, z, yaw) in a's frame, with the orientations and sizes a true match has."""
    from panoworld.geometry.floor_view import FloorView
    from panoworld.geometry.upright import yaw_matrix_xz

    x, z, yaw = b_from_a_xz
    in_b = (points - [x, z]) @ yaw_matrix_xz(yaw)  # p_a = R(yaw) p_b + t
    n = len(points)
    desc = np.eye(n, 128, dtype=np.float32)
    ang = np.linspace(0, 1, n)
    a = FloorView(height_m=height, xz=points.astype(float), descriptors=desc, angles=ang, sizes=np.full(n, 4.0))
    b = FloorView(height_m=height, xz=in_b, descriptors=desc, angles=ang - yaw, sizes=np.full(n, 4.0))
    return a, b


def test_floor_inliers_on_one_spot_count_once():
    from panoworld.register.floor import distinct_inliers, floor_support

    rng = np.random.default_rng(0)
    spread = rng.uniform(-3, 3, (12, 2))
    a, b = _views_of(spread, (1.0, 0.5, 0.3))
    m = np.stack([np.arange(12), np.arange(12)], 1)
    T = np.eye(4)
    T[:3, :3], T[[0, 2], 3] = yaw_matrix(0.3), [1.0, 0.5]
    assert distinct_inliers(a, b, m) == 12 and floor_support(a, b, T, matches=m) == 12
    clustered = np.repeat(spread[:2], 6, axis=0) + rng.normal(0, 0.002, (12, 2))  # 6 keypoints on each of 2 spots
    a, b = _views_of(clustered, (1.0, 0.5, 0.3))
    assert distinct_inliers(a, b, m) == 2 and floor_support(a, b, T, matches=m) == 2


def test_a_floor_fit_whose_inliers_lie_inside_both_rooms_of_two_cameras_is_refused():
    """Two round rooms of 3 m radius, the cameras 4.5 m apart (each beyond the other's wall). Floor matched between
    them where both rooms claim it (the rooms would overlap there): refused; floor of a's room seen by b beyond its
    wall (through a doorway): kept; a's floor alone unknown to b (masked depth): not judged."""
    from panoworld.register.floor import FloorPose, floor_rooms_refusal, room_sides

    depth = np.full((64, 128), 3.0, np.float32)
    T = np.eye(4)
    T[[0, 2], 3] = [4.5, 0.0]
    rng = np.random.default_rng(1)
    both = np.stack([rng.uniform(2.0, 2.5, 10), rng.uniform(-0.5, 0.5, 10)], 1)  # ~2.2 m from each camera
    a_only = np.stack([rng.uniform(-2.0, -1.0, 10), rng.uniform(-1.0, 1.0, 10)], 1)  # 5.5 m from b, in a's room
    m = np.stack([np.arange(10), np.arange(10)], 1)
    for pts, refused in ((both, True), (a_only, False)):
        a, b = _views_of(pts, (4.5, 0.0, 0.0))
        f = FloorPose(a_from_b=T, inliers=10, matches=10, residual_m=0.0, matched=m.astype(np.int32))
        why = floor_rooms_refusal(room_sides(f, a, b, depth, depth, threshold_m=0.05))
        assert bool(why) == refused, why
        if refused:
            assert "10 of its 10 floor inliers lie inside both rooms" in why
    a, b = _views_of(both, (4.5, 0.0, 0.0))
    f = FloorPose(a_from_b=T, inliers=10, matches=10, residual_m=0.0, matched=m.astype(np.int32))
    assert floor_rooms_refusal(room_sides(f, a, b, depth, np.zeros_like(depth), threshold_m=0.05)) == ""
    near = T.copy()
    near[[0, 2], 3] = [1.0, 0.0]  # the cameras in each other's free space: one room, same_room_refusal's to judge
    a, b = _views_of(both, (1.0, 0.0, 0.0))
    f = FloorPose(a_from_b=near, inliers=10, matches=10, residual_m=0.0, matched=m.astype(np.int32))
    assert floor_rooms_refusal(room_sides(f, a, b, depth, depth, threshold_m=0.05)) == ""


def test_floor_inliers_beyond_both_rooms_are_counted():
    """Two round rooms of 1.5 m radius, the cameras 4.5 m apart: floor matched midway lies beyond both walls (a hallway
    both see through their doors); floor of a's room lies beyond b's wall only; cameras in one room count none."""
    from panoworld.register.floor import FloorPose, beyond_both_rooms, room_sides

    depth = np.full((64, 128), 1.5, np.float32)
    T = np.eye(4)
    T[[0, 2], 3] = [4.5, 0.0]
    rng = np.random.default_rng(2)
    hallway = np.stack([rng.uniform(2.1, 2.4, 10), rng.uniform(-0.3, 0.3, 10)], 1)  # 2.1-2.4 m from each camera
    a_room = np.stack([rng.uniform(-1.0, -0.5, 10), rng.uniform(-0.5, 0.5, 10)], 1)
    m = np.stack([np.arange(10), np.arange(10)], 1).astype(np.int32)
    for pts, beyond in ((hallway, 10), (a_room, 0)):
        a, b = _views_of(pts, (4.5, 0.0, 0.0))
        f = FloorPose(a_from_b=T, inliers=10, matches=10, residual_m=0.0, matched=m)
        assert beyond_both_rooms(room_sides(f, a, b, depth, depth, threshold_m=0.05)) == (beyond, 10)
    wide = np.full((64, 128), 6.0, np.float32)  # rooms of 6 m: the cameras stand in each other's free space
    a, b = _views_of(hallway, (4.5, 0.0, 0.0))
    f = FloorPose(a_from_b=T, inliers=10, matches=10, residual_m=0.0, matched=m)
    assert beyond_both_rooms(room_sides(f, a, b, wide, wide, threshold_m=0.05)) == (0, 0)


def test_floor_edge_joins_groups_in_the_pose_graph():
    ab, cd, bc = _pose(30.0, 1.0, 0.0), _pose(-60.0, 0.0, 2.0), _pose(90.0, 3.0, 1.0)
    edges = [Edge(a="a", b="b", a_from_b=ab, kind="depth", inliers=100, info={}),
             Edge(a="c", b="d", a_from_b=cd, kind="depth", inliers=100, info={}),
             Edge(a="b", b="c", a_from_b=bc, kind=FLOOR, inliers=12, info={})]
    poses, info = solve_graph(["a", "b", "c", "d", "e"], edges)
    assert set(poses) == {"a", "b", "c", "d"} and not info["e"]["registered"]
    assert np.allclose(poses["d"], ab @ bc @ cd)
    assert info["c"]["edge"] == FLOOR


def test_register_panoramas_joins_a_pair_by_its_floor():
    tex = _texture(4)
    wa, wb = _pose(0.0, 0.0, 0.0), _pose(75.0, 1.6, 0.9)
    (ra, da), (rb, db) = _render(wa, tex), _render(wb, tex)
    o = RegisterOptions(min_inliers=10**6, floor_radius_m=4.0)  # no depth-backed edge: the floor must join them
    reg = register_panoramas(["a", "b"], {"a": ra, "b": rb}, {"a": da, "b": db}, options=o)
    assert reg.panoramas["b"]["registered"] and reg.panoramas["b"]["edge"] == FLOOR
    truth = invert_pose(wa) @ wb
    assert np.linalg.norm(reg.world_from_cam["b"][:3, 3] - truth[:3, 3]) < 0.03
    row = reg.pairs[0]
    assert row["floor_inliers"] >= 50
    # the row carries the floor fit's own pose (what bench_multi scores the floor fits by)
    assert abs(row["floor_yaw_deg"] - np.degrees(yaw_of(truth[:3, :3]))) < 0.5
    assert np.hypot(row["floor_xz_m"][0] - truth[0, 3], row["floor_xz_m"][1] - truth[2, 3]) < 0.03
    assert row["floor_beyond_rooms"] == 0  # one floor around both cameras: none of it beyond a wall


def test_no_keypoint_on_the_excluded_rig():
    from panoworld.core.conventions import erp_pixel_from_dir
    from panoworld.register.pairwise import erp_features, grow_exclusion

    rgb, depth = _render(_pose(0.0, 0.0, 0.0), _texture(5))
    rig = np.zeros(depth.shape, bool)
    rig[int(0.8 * H):] = True  # everything within 36 deg of the nadir
    grown = grow_exclusion(rig)
    assert grown.sum() > rig.sum() and grow_exclusion(np.zeros_like(rig)) is None
    free = erp_features(rgb, depth, max_features=4000)
    f = erp_features(rgb, depth, max_features=4000, exclude=grown)
    v = erp_pixel_from_dir(f.bearings, H, 2 * H)[1]
    v_free = erp_pixel_from_dir(free.bearings, H, 2 * H)[1]
    assert (v_free >= 0.8 * H).sum() > 50 and (v < 0.8 * H).all()
    # the floor image: nothing left where the mask covers it beyond the nadir disc
    whole = floor_view(rgb, depth, radius_m=4.0, exclude=None)
    masked = floor_view(rgb, depth, radius_m=4.0, exclude=grown)
    r = lambda fv: np.hypot(*fv.xz.T)
    edge = FLOOR_Y * np.tan(np.radians(36.0))
    assert (r(whole) < edge).sum() > 20 and (r(masked) < edge - 0.02).sum() == 0


def test_a_floor_fit_the_images_cannot_check_is_refused_when_another_translation_agrees_nearly_as_well():
    from panoworld.register.floor import FloorPose
    from panoworld.register.solve import _ambiguous_floor
    from panoworld.register.upright import UprightPose

    o = RegisterOptions()
    fit = FloorPose(a_from_b=_pose(0.0, 6.4, 0.0), inliers=12, matches=3500, residual_m=0.02, second=7)
    no_images = (None, float("nan"), 0)
    assert "another translation 7" in _ambiguous_floor(fit, no_images, o)
    assert _ambiguous_floor(FloorPose(a_from_b=fit.a_from_b, inliers=12, matches=3500, residual_m=0.02, second=5),
                            no_images, o) == ""  # 12 >= 2 x 5: clear
    agree = UprightPose(yaw=0.0, t=np.array([1.0, 0.0, 0.0]), inliers=np.ones(o.min_bearing_inliers, bool))
    assert _ambiguous_floor(fit, (agree, float("nan"), 0), o) == ""  # the images check it (_contradiction)
    weak = FloorPose(a_from_b=fit.a_from_b, inliers=9, matches=3500, residual_m=0.02, second=o.min_floor_inliers - 1)
    assert _ambiguous_floor(weak, no_images, o) == ""  # a runner-up too weak to be a floor fit is chance, no rival
    assert "another translation" in _ambiguous_floor(replace(weak, second=o.min_floor_inliers), no_images, o)


def _two_rooms_one_floor():
    """Four panoramas on one floor, a-b and c-d in two rooms: (names, their floor views, rel(x, y): the true x_from_y,
    a floor pose of b-c 3 m too far along its baseline (as two rooms with one flooring give), each pair's floor fit
    across the cut a|b - c|d, RegisterOptions())."""
    from panoworld.register.floor import floor_pair

    tex = _texture(6)
    names = ["a", "b", "c", "d"]
    world = {"a": _pose(0.0, 0.0, 0.0), "b": _pose(40.0, 1.6, 0.0), "c": _pose(-70.0, 1.6, 1.9),
             "d": _pose(150.0, 0.0, 1.9)}
    o = RegisterOptions()
    views = {n: floor_view(*_render(world[n], tex), radius_m=o.floor_radius_m, cell_m=o.floor_cell_m) for n in names}
    rel = lambda x, y: invert_pose(world[x]) @ world[y]
    wrong = rel("b", "c").copy()
    wrong[:3, 3] *= 1 + 3.0 / np.linalg.norm(wrong[:3, 3])
    floors = {(i, j): floor_pair(views[names[i]], views[names[j]]) for i, j in [(0, 2), (0, 3), (1, 2), (1, 3)]}
    return names, views, rel, wrong, floors, o


def test_a_floor_edge_the_floors_across_its_cut_outvote_is_refused():
    """Two rooms of two panoramas each (depth edges), joined by a floor edge of 40 inliers the images do not confirm,
    3 m off along its baseline (as two rooms with one flooring give), and a right one of 10: the tree takes the 40 and
    the loop gate drops the 10. The floor images of the pairs across that cut agree on the truth: the 40 is refused and
    the truth registered. One supporting pair is not enough, and a confirmed edge is never refused."""
    from panoworld.register.cuts import refuse_outvoted_cuts

    names, views, rel, wrong, floors, o = _two_rooms_one_floor()
    depth = [Edge(a="a", b="b", a_from_b=rel("a", "b"), kind="depth", inliers=300, info={}),
             Edge(a="c", b="d", a_from_b=rel("c", "d"), kind="depth", inliers=300, info={})]
    cross = [Edge(a="b", b="c", a_from_b=wrong, kind=FLOOR, inliers=40, info={}, confirmed=False),
             Edge(a="a", b="d", a_from_b=rel("a", "d"), kind=FLOOR, inliers=10, info={}, confirmed=False)]
    assert all(f.inliers >= 50 for f in floors.values())  # one floor: every pair across the cut sees it

    def error_m(edges: list[Edge]) -> float:
        poses, _ = solve_graph(names, edges)
        return max(np.linalg.norm(poses[n][:3, 3] - rel("a", n)[:3, 3]) for n in names)

    edges = depth + cross
    assert error_m(edges) > 2.5  # the tree takes the 40 inliers
    refused = refuse_outvoted_cuts(names, edges, {}, floors, views, o.min_floor_inliers)
    assert list(refused) == [("b", "c")] and "4 pairs" in refused["b", "c"][1] and "c, d 3.0" in refused["b", "c"][1]
    assert error_m(edges) < 0.01

    alone = depth + cross
    assert refuse_outvoted_cuts(names, alone, {}, floors, {"a": views["a"], "d": views["d"]}, 8) == {}
    assert len(alone) == 4  # only the pair a-d supports the truth: not enough to overrule the tree

    confirmed = depth + [Edge(a="b", b="c", a_from_b=wrong, kind=FLOOR, inliers=40, info={}), cross[1]]
    assert refuse_outvoted_cuts(names, confirmed, {}, floors, views, 8) == {}


def test_a_weak_floor_edge_no_other_pair_across_its_cut_supports_is_refused():
    """A floor edge of 10 inliers the images do not confirm whose own pair is the only one across the cut it makes that
    its floor images support (another pair across it, b-c, sees other floors: a chance fit between floors that share
    nothing looks like this): refused below floor_lone_inliers, kept at or above it, kept where b-c agrees, and refused
    where it is the only pair tried across the cut (nothing tells it from a chance fit)."""
    from panoworld.register.cuts import refuse_outvoted_cuts
    from panoworld.register.floor import floor_pair

    tex = _texture(7)
    names = ["a", "b", "c"]
    world = {"a": _pose(0.0, 0.0, 0.0), "b": _pose(60.0, 1.5, 0.2), "c": _pose(-20.0, 0.4, 2.0)}
    views = {n: floor_view(*_render(world[n], tex), radius_m=4.0) for n in names}
    apart = dict(views, b=floor_view(*_render(world["b"], _texture(8)), radius_m=4.0))  # b on another floor
    rel = lambda x, y: invert_pose(world[x]) @ world[y]

    def floors(v: dict, pairs=((0, 1), (0, 2), (1, 2))) -> dict:
        return {(i, j): floor_pair(v[names[i]], v[names[j]]) for i, j in pairs}

    def edges() -> list[Edge]:
        return [Edge(a="a", b="b", a_from_b=rel("a", "b"), kind="depth", inliers=300, info={}),
                Edge(a="a", b="c", a_from_b=rel("a", "c"), kind=FLOOR, inliers=10, info={}, confirmed=False)]

    e = edges()
    refused = refuse_outvoted_cuts(names, e, {}, floors(apart), apart, 8, 12)
    assert list(refused) == [("a", "c")] and "no other of the 2 pairs" in refused["a", "c"][1]
    assert "c" not in solve_graph(names, e)[0]
    assert refuse_outvoted_cuts(names, edges(), {}, floors(apart), apart, 8, 10) == {}  # 10 inliers: not weak there
    assert refuse_outvoted_cuts(names, edges(), {}, floors(views), views, 8, 12) == {}  # b-c's floor agrees
    lone = refuse_outvoted_cuts(names, edges(), {}, floors(apart, ((0, 1), (0, 2))), apart, 8, 12)
    assert list(lone) == [("a", "c")] and "no other pair across it" in lone["a", "c"][1]
    assert refuse_outvoted_cuts(names, edges(), {}, floors(apart, ((0, 1), (0, 2))), apart, 8, 10) == {}


def test_a_panorama_taken_again_at_the_same_spot_lends_a_weak_floor_edge_no_support():
    """A weak floor edge a-c whose only agreeing pair across the cut is b-c, b taken where a stands (a retake or an
    exposure bracket, turned 60 deg): b's floor image repeats a's from the same place, so a chance fit of a-c would
    repeat too. Refused as a lone fit; kept where b stands 1.5 m away."""
    from panoworld.register.cuts import SAME_SPOT_M, refuse_outvoted_cuts
    from panoworld.register.floor import floor_pair

    tex = _texture(7)
    names = ["a", "b", "c"]

    def case(b_x: float) -> dict:
        world = {"a": _pose(0.0, 0.0, 0.0), "b": _pose(60.0, b_x, 0.0), "c": _pose(-20.0, 0.4, 2.0)}
        views = {n: floor_view(*_render(world[n], tex), radius_m=4.0) for n in names}
        rel = lambda x, y: invert_pose(world[x]) @ world[y]
        edges = [Edge(a="a", b="b", a_from_b=rel("a", "b"), kind="depth", inliers=300, info={}),
                 Edge(a="a", b="c", a_from_b=rel("a", "c"), kind=FLOOR, inliers=10, info={}, confirmed=False)]
        floors = {(i, j): floor_pair(views[names[i]], views[names[j]]) for i, j in ((0, 1), (0, 2), (1, 2))}
        return refuse_outvoted_cuts(names, edges, {}, floors, views, 8, 12)

    twin = case(0.6 * SAME_SPOT_M)
    assert list(twin) == [("a", "c")]
    assert "only those from its own capture spots (a-c, b-c)" in twin["a", "c"][1]
    assert case(1.5) == {}  # b-c from another spot agrees: kept


def test_a_weak_floor_edge_whose_inliers_lie_beyond_both_rooms_is_kept_alone():
    """The lone weak floor edge a-c of test_a_weak_floor_edge_no_other_pair_across_its_cut_supports_is_refused, its
    inlier matches beyond both rooms' walls (a hallway both see): kept from floor_beyond_rooms of them on, and where
    BEYOND_SHARE of them are; refused below either, and with the rule off (0)."""
    from panoworld.register.cuts import refuse_outvoted_cuts
    from panoworld.register.floor import floor_pair

    tex = _texture(7)
    names = ["a", "b", "c"]
    world = {"a": _pose(0.0, 0.0, 0.0), "b": _pose(60.0, 1.5, 0.2), "c": _pose(-20.0, 0.4, 2.0)}
    views = {n: floor_view(*_render(world[n], tex), radius_m=4.0) for n in names}
    views["b"] = floor_view(*_render(world["b"], _texture(8)), radius_m=4.0)  # b on another floor
    rel = lambda x, y: invert_pose(world[x]) @ world[y]
    floors = {(i, j): floor_pair(views[names[i]], views[names[j]]) for i, j in ((0, 1), (0, 2), (1, 2))}

    def refused(beyond: int, of: int, beyond_rooms: int = RegisterOptions().floor_beyond_rooms) -> bool:
        edges = [Edge(a="a", b="b", a_from_b=rel("a", "b"), kind="depth", inliers=300, info={}),
                 Edge(a="a", b="c", a_from_b=rel("a", "c"), kind=FLOOR, inliers=10, confirmed=False,
                      info={"beyond_rooms": beyond, "inlier_matches": of})]
        return bool(refuse_outvoted_cuts(names, edges, {}, floors, views, 8, 12, beyond_rooms))

    k = RegisterOptions().floor_beyond_rooms
    assert not refused(k + 1, k + 1) and not refused(k, k + 1)
    assert refused(k - 1, k - 1) and refused(k, k + 2) and refused(k + 1, k + 1, beyond_rooms=0)


def test_a_floor_fit_its_own_pair_refuses_proposes_no_placement_in_the_cut_vote():
    """The wrong 40-inlier floor edge b-c of test_a_floor_edge_the_floors_across_its_cut_outvote_is_refused with no
    right edge beside it: the pairs' floor fits across the cut place the truth and outvote it, unless their own pairs
    refused those fits (refused_fits: their images or rooms), which then propose nothing."""
    from panoworld.register.cuts import refuse_outvoted_cuts

    names, views, rel, wrong, floors, o = _two_rooms_one_floor()

    def edges() -> list[Edge]:
        return [Edge(a="a", b="b", a_from_b=rel("a", "b"), kind="depth", inliers=300, info={}),
                Edge(a="c", b="d", a_from_b=rel("c", "d"), kind="depth", inliers=300, info={}),
                Edge(a="b", b="c", a_from_b=wrong, kind=FLOOR, inliers=40, info={}, confirmed=False)]

    assert list(refuse_outvoted_cuts(names, edges(), {}, floors, views, o.min_floor_inliers)) == [("b", "c")]
    assert refuse_outvoted_cuts(names, edges(), {}, floors, views, o.min_floor_inliers, refused_fits=set(floors)) == {}
