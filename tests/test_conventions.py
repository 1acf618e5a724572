"""Round trips and anchors for every mapping in panoworld/core/conventions.py."""

from __future__ import annotations

import numpy as np
import pytest

from panoworld.core import conventions as cv

RNG = np.random.default_rng(7)


def random_rotations(n: int) -> np.ndarray:
    q = RNG.normal(size=(n, 4))
    return cv.rotmat_from_quat_wxyz(q)


def random_pose() -> np.ndarray:
    return cv.pose_from_rt(random_rotations(1)[0], RNG.normal(size=3))


def test_erp_anchor_directions():
    H, W = 4, 8
    d = lambda u, v: cv.dir_from_lonlat(*cv.erp_lonlat_from_pixel(u, v, H, W))
    np.testing.assert_allclose(d(W / 2, H / 2), [0, 0, 1], atol=1e-12)  # centre looks forward
    np.testing.assert_allclose(d(3 * W / 4, H / 2), [1, 0, 0], atol=1e-12)  # right
    np.testing.assert_allclose(d(W / 4, H / 2), [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(d(0, H / 2), [0, 0, -1], atol=1e-12)  # seam looks back
    np.testing.assert_allclose(d(W / 2, 0), [0, -1, 0], atol=1e-12)  # top is up (-y)


def test_erp_pixel_dir_round_trip():
    H, W = 90, 180
    dirs = cv.erp_dirs(H, W, dtype=np.float64)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-12)
    u, v = cv.erp_pixel_from_dir(dirs * 3.7, H, W)
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    np.testing.assert_allclose(u, jj, atol=1e-9)
    np.testing.assert_allclose(v, ii, atol=1e-9)


@pytest.mark.parametrize("height", [1, 33, 256, 720])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_erp_dirs_is_dir_from_lonlat_on_the_pixel_grid(height, dtype):
    """The separable erp_dirs equals dir_from_lonlat of every pixel centre's (lon, lat), bit for bit."""
    W = 2 * height
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(height) + 0.5)
    ref = cv.dir_from_lonlat(*cv.erp_lonlat_from_pixel(jj, ii, height, W)).astype(dtype)
    got = cv.erp_dirs(height, W, dtype=dtype)
    assert got.dtype == dtype and got.shape == (height, W, 3)
    np.testing.assert_array_equal(got, ref)


def test_seam_wraps():
    H, W = 8, 16
    lon = np.array([np.pi - 1e-9, -np.pi])
    u, _ = cv.erp_pixel_from_lonlat(lon, np.zeros(2), H, W)
    assert np.all((u >= 0) & (u < W))


def test_matches_pycolmap_equirectangular():
    pycolmap = pytest.importorskip("pycolmap")
    H, W = 32, 64
    cam = pycolmap.Camera.create_from_model_name(1, "EQUIRECTANGULAR", 0.0, W, H)
    d = RNG.normal(size=(50, 3))
    ours = np.stack(cv.erp_pixel_from_dir(d, H, W), axis=-1)
    theirs = cam.img_from_cam(d)
    wrapped = np.abs(((ours[:, 0] - theirs[:, 0]) + W / 2) % W - W / 2)
    assert wrapped.max() < 1e-6
    np.testing.assert_allclose(ours[:, 1], theirs[:, 1], atol=1e-6)


def test_points_from_depth_distance_is_ray_length():
    depth = RNG.uniform(0.5, 5.0, size=(6, 12)).astype(np.float32)
    pts = cv.points_from_depth(depth)
    np.testing.assert_allclose(np.linalg.norm(pts, axis=-1), depth, rtol=1e-6)
    T = random_pose()
    world = cv.points_from_depth(depth, T)
    np.testing.assert_allclose(cv.transform_points(cv.invert_pose(T), world), pts, atol=1e-9)
    with pytest.raises(ValueError, match=r"depth.shape=\(6, 12, 1\) but expected \(H, W\)"):
        cv.points_from_depth(depth[..., None])


def test_quaternion_round_trip_and_order():
    R = random_rotations(200)
    q = cv.quat_wxyz_from_rotmat(R)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(cv.rotmat_from_quat_wxyz(q), R, atol=1e-12)
    # 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45)
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(cv.quat_wxyz_from_rotmat(Rz), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)
    half_turns = np.stack([np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])])  # w = 0 cases
    np.testing.assert_allclose(cv.rotmat_from_quat_wxyz(cv.quat_wxyz_from_rotmat(half_turns)), half_turns, atol=1e-12)
    np.testing.assert_allclose(cv.quat_wxyz_from_xyzw(cv.quat_xyzw_from_wxyz(q)), q)
    assert cv.quat_xyzw_from_wxyz(np.array([1.0, 2, 3, 4])).tolist() == [2, 3, 4, 1]


def test_pose_inverse():
    T = random_pose()
    np.testing.assert_allclose(T @ cv.invert_pose(T), np.eye(4), atol=1e-12)
    with pytest.raises(ValueError, match=r"pose.shape=\(3, 4\) but expected \(4, 4\)"):
        cv.invert_pose(T[:3])


def test_colmap_round_trip():
    T = random_pose()
    q, t = cv.colmap_cam_from_world(T)
    np.testing.assert_allclose(cv.world_from_cam_from_colmap(q, t), T, atol=1e-12)
    p_world = RNG.normal(size=3)
    p_cam = cv.rotmat_from_quat_wxyz(q) @ p_world + t
    np.testing.assert_allclose(p_cam, cv.transform_points(cv.invert_pose(T), p_world), atol=1e-12)


def test_opengl_round_trip_and_axes():
    T = random_pose()
    G = cv.gl_world_from_cam(T)
    np.testing.assert_allclose(cv.cv_world_from_cam_from_gl(G), T, atol=1e-12)
    # The OpenGL camera looks along its -z, which must be our camera's +z (forward) in the world.
    np.testing.assert_allclose(-G[:3, 2], T[:3, 2], atol=1e-12)
    np.testing.assert_allclose(G[:3, 3], T[:3, 3])


def test_ros_world_is_z_up_x_forward():
    R = cv.ROS_FROM_WORLD[:3, :3]
    assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R @ cv.WORLD_UP, [0, 0, 1])  # our up -> ROS +z
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0])  # our forward -> ROS +x
    np.testing.assert_allclose(R @ [1, 0, 0], [0, -1, 0])  # our right -> ROS -y (y is left)
    T = random_pose()
    np.testing.assert_allclose(cv.world_from_ros_world() @ cv.ros_world_from_cam(T), T, atol=1e-12)


def test_gltf_is_y_up():
    np.testing.assert_allclose(cv.GLTF_FROM_WORLD[:3, :3] @ cv.WORLD_UP, [0, 1, 0])
    assert np.isclose(np.linalg.det(cv.GLTF_FROM_WORLD[:3, :3]), 1.0)


def test_solid_angles_sum_to_sphere():
    H, W = 45, 90
    assert np.isclose(cv.erp_pixel_solid_angle(H, W).sum() * W, 4 * np.pi)


def test_check_erp_shape_message():
    with pytest.raises(ValueError, match="must be exactly 2:1"):
        cv.check_erp_shape(10, 30)


def test_depth_png_millimetres():
    depth = np.array([[0.0, np.nan, np.inf, -1.0], [0.0004, 1.2345, 65.535, 70.0]])
    mm = cv.depth_to_mm(depth)
    assert mm.dtype == np.uint16
    assert mm.tolist() == [[0, 0, 0, 0], [0, 1234, 65535, 65535]]
    np.testing.assert_allclose(mm[1, 1] * cv.DEPTH_PNG_SCALE, 1.234)


def test_asset_frame_is_z_up_with_the_floor_at_zero():
    T = cv.asset_from_canonical(1.6)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    np.testing.assert_allclose(T[:3, :3] @ cv.WORLD_UP, [0, 0, 1], atol=1e-12)  # up -> +Z
    np.testing.assert_allclose(cv.transform_points(T, np.array([[0.0, 1.6, 0.0]])), [[0, 0, 0]], atol=1e-12)  # floor
    np.testing.assert_allclose(cv.transform_points(T, np.array([[0.0, 0.0, 2.0]])), [[2, 0, 1.6]], atol=1e-12)  # forward


def test_erp_dirs64_is_the_float64_grid_shared_read_only():
    from panoworld.core.conventions import erp_dirs, erp_dirs64

    d = erp_dirs64(16, 32)
    assert d.dtype == np.float64 and np.array_equal(d, erp_dirs(16, 32, np.float64))
    assert erp_dirs64(16, 32) is d  # computed once per size
    with pytest.raises(ValueError):
        d[0, 0, 0] = 1.0  # callers share it: nobody may write into it
