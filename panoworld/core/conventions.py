"""The project's one implementation of axes, ERP pixel mapping, poses and frame conversions (docs/conventions.md)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from panoworld.core.shapes import check_shape

# World frame: right-handed, metres, gravity along +Y (up = -Y). The canonical frame of a scene is the
# frame of its first camera (pose 0 = identity), so world axes equal OpenCV camera axes of view 0.
WORLD_UP = np.array([0.0, -1.0, 0.0])

# Camera frame (OpenCV / COLMAP): x right, y down, z forward.
# OpenGL / nerfstudio / Blender camera: x right, y up, z backward.
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
CV_FROM_GL = GL_FROM_CV
# glTF / Blender-import world (Y up): rotate our world 180 degrees about x.
GLTF_FROM_WORLD = np.diag([1.0, -1.0, -1.0, 1.0])
# ROS / Foxglove world (REP 103): x forward, y left, z up.
ROS_FROM_WORLD = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


DEPTH_PNG_SCALE = 0.001
"""Metres per unit of a 16-bit depth PNG (millimetres); 0 = no depth."""


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """Depth (H, W) metres (0/NaN/inf = unknown) -> uint16 millimetres (0 = unknown, clipped at 65.535 m)."""
    d = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    return np.clip(np.rint(d / DEPTH_PNG_SCALE), 0, 65535).astype(np.uint16)


def check_erp_shape(height: int, width: int, what: str = "panorama") -> None:
    """Raise ValueError unless (height, width) is a 2:1 equirectangular size."""
    if height <= 0 or width != 2 * height:
        raise ValueError(
            f"{what} is {width}x{height} (WxH) but an equirectangular image must be exactly 2:1 (W = 2H)"
        )


def erp_lonlat_from_pixel(u: np.ndarray, v: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coords (centre of pixel (i, j) is (j + 0.5, i + 0.5)) -> (lon, lat) in radians.

    lon in [-pi, pi), 0 at the image centre column, increasing to the right (towards +x).
    lat in [-pi/2, pi/2], +pi/2 at the top row (up, -y).
    """
    lon = (np.asarray(u, dtype=np.float64) / width - 0.5) * 2.0 * np.pi
    lat = (0.5 - np.asarray(v, dtype=np.float64) / height) * np.pi
    return lon, lat


def erp_pixel_from_lonlat(lon: np.ndarray, lat: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of erp_lonlat_from_pixel; u is wrapped into [0, width)."""
    u = (np.asarray(lon, dtype=np.float64) / (2.0 * np.pi) + 0.5) * width
    v = (0.5 - np.asarray(lat, dtype=np.float64) / np.pi) * height
    return np.mod(u, width), v


def dir_from_lonlat(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """(lon, lat) -> unit ray direction in the camera frame, shape (..., 3)."""
    lon, lat = np.broadcast_arrays(lon, lat)
    cl = np.cos(lat)
    return np.stack([cl * np.sin(lon), -np.sin(lat), cl * np.cos(lon)], axis=-1)


def lonlat_from_dir(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray direction(s) (..., 3) in the camera frame (need not be unit) -> (lon, lat)."""
    d = np.asarray(d, dtype=np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    lon = np.arctan2(x, z)
    lat = np.arctan2(-y, np.hypot(x, z))
    return lon, lat


def erp_pixel_from_dir(d: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame direction(s) (..., 3) -> continuous ERP pixel coords (u, v)."""
    return erp_pixel_from_lonlat(*lonlat_from_dir(d), height, width)


def erp_dirs(height: int, width: int, dtype=np.float32) -> np.ndarray:
    """Unit ray directions of every pixel centre, shape (H, W, 3), camera frame."""
    check_erp_shape(height, width, "requested ERP grid")
    u = np.arange(width, dtype=np.float64) + 0.5
    v = np.arange(height, dtype=np.float64) + 0.5
    lon, lat = erp_lonlat_from_pixel(u, v, height, width)
    cl = np.cos(lat)[:, None]  # separable: dir_from_lonlat on the grid, the trigonometry once per row and column
    out = np.empty((height, width, 3), dtype)
    out[..., 0] = cl * np.sin(lon)
    out[..., 1] = -np.sin(lat)[:, None]
    out[..., 2] = cl * np.cos(lon)
    return out


@lru_cache(maxsize=4)
def erp_dirs64(height: int, width: int) -> np.ndarray:
    """erp_dirs(height, width) in float64, computed once per size and read-only (callers that read the grid of every
    depth map of a run)."""
    d = erp_dirs(height, width, np.float64)
    d.flags.writeable = False
    return d


def pinhole_dirs(fx: float, fy: float, cx: float, cy: float, height: int, width: int, dtype=np.float32) -> np.ndarray:
    """Unit ray directions (H, W, 3) of every pixel centre (u + 0.5, v + 0.5) of an OpenCV pinhole camera, camera frame."""
    if height <= 0 or width <= 0:
        raise ValueError(f"pinhole image {width}x{height} (WxH) must be positive")
    x = (np.arange(width, dtype=np.float64) + 0.5 - cx) / fx
    y = (np.arange(height, dtype=np.float64) + 0.5 - cy) / fy
    d = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.ones((1, 1))), -1)
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(dtype)


def erp_pixel_solid_angle(height: int, width: int) -> np.ndarray:
    """Solid angle of each pixel row, shape (H, 1) (for WS-PSNR and area-weighted statistics)."""
    lat_top = (0.5 - np.arange(height) / height) * np.pi
    lat_bot = (0.5 - (np.arange(height) + 1) / height) * np.pi
    return ((np.sin(lat_top) - np.sin(lat_bot)) * (2.0 * np.pi / width))[:, None]


def points_from_depth(depth: np.ndarray, world_from_cam: np.ndarray | None = None) -> np.ndarray:
    """ERP ray-distance depth (H, W) in metres -> 3D points (H, W, 3), in world frame if a pose is given."""
    check_shape("depth", depth, "H W")
    pts = erp_dirs(*depth.shape, dtype=np.float64) * depth[..., None]
    if world_from_cam is not None:
        pts = transform_points(world_from_cam, pts)
    return pts


def transform_points(a_from_b: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid/similarity transform to points (..., 3)."""
    check_pose(a_from_b)
    return pts_b @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def check_pose(T: np.ndarray, what: str = "pose") -> None:
    check_shape(what, T, "4 4")


POSE_RIGID_TOL = 1e-4
"""check_poses' tolerance on every entry of R R^T - I and of the last row - (0, 0, 0, 1): poses stored as float32 or
rounded to 6 decimals pass; a scaled, sheared or similarity (s != 1) matrix does not."""


def check_poses(poses, what: str = "poses") -> np.ndarray:
    """world_from_cam poses (N, 4, 4), N >= 1, finite and rigid (det +1, within POSE_RIGID_TOL), as float64; else
    InputError naming `what` and the first bad pose."""
    from panoworld.core.errors import InputError

    try:
        poses = np.asarray(poses, np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what}: poses are not a numeric array of 4x4 matrices") from None
    check_shape(what, poses, "N 4 4")
    if len(poses) == 0:
        raise InputError(f"{what}: no poses (expected (N, 4, 4) with N >= 1)")
    if not np.isfinite(poses).all():
        bad = int(np.flatnonzero(~np.isfinite(poses).reshape(len(poses), -1).all(1))[0])
        raise InputError(f"{what}: pose {bad} has NaN or inf entries")
    R = poses[:, :3, :3]
    err = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    row = np.abs(poses[:, 3] - [0, 0, 0, 1]).max(axis=1)
    bad = np.flatnonzero((err > POSE_RIGID_TOL) | (det < 0) | (row > POSE_RIGID_TOL))
    if len(bad):
        i = int(bad[0])
        raise InputError(
            f"{what}: pose {i} is not a rigid world_from_cam transform (|R R^T - I| = {err[i]:.2e}, det = {det[i]:.3f}, "
            f"last row {poses[i, 3].tolist()}); {len(bad)} such poses"
        )
    return poses


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (a_from_b -> b_from_a)."""
    check_pose(T)
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def pose_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def quat_wxyz_from_rotmat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4) in (w, x, y, z) order with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    r = {(i, j): m[:, i, j] for i in range(3) for j in range(3)}
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    # Shepperd's method: each row builds q from its largest component (w, x, y or z), all rows at once.
    cands = np.stack(
        [
            [1.0 + tr, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]],
            [r[2, 1] - r[1, 2], 1.0 + r[0, 0] - r[1, 1] - r[2, 2], r[0, 1] + r[1, 0], r[0, 2] + r[2, 0]],
            [r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], 1.0 + r[1, 1] - r[0, 0] - r[2, 2], r[1, 2] + r[2, 1]],
            [r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], 1.0 + r[2, 2] - r[0, 0] - r[1, 1]],
        ]
    )  # (4 choices, 4 components, N)
    k = np.argmax(np.stack([tr, r[0, 0], r[1, 1], r[2, 2]]), axis=0)
    q = cands[k, :, np.arange(len(k))]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def rotmat_from_quat_wxyz(q: np.ndarray) -> np.ndarray:
    """Quaternion(s) (..., 4) in (w, x, y, z) order (normalised here) -> rotation matrices (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def quat_xyzw_from_wxyz(q: np.ndarray) -> np.ndarray:
    """(w, x, y, z) -> (x, y, z, w), the order of TUM files, ROS and Foxglove messages."""
    return np.roll(np.asarray(q), -1, axis=-1)


def quat_wxyz_from_xyzw(q: np.ndarray) -> np.ndarray:
    return np.roll(np.asarray(q), 1, axis=-1)


def colmap_cam_from_world(world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """world_from_cam -> (qvec wxyz, tvec) of COLMAP's cam_from_world (camera axes are already OpenCV)."""
    T = invert_pose(world_from_cam)
    return quat_wxyz_from_rotmat(T[:3, :3]), T[:3, 3].copy()


def world_from_cam_from_colmap(qvec_wxyz: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    return invert_pose(pose_from_rt(rotmat_from_quat_wxyz(qvec_wxyz), tvec))


def gl_world_from_cam(world_from_cam: np.ndarray) -> np.ndarray:
    """Our world_from_cam -> nerfstudio/OpenGL transform_matrix (same world, OpenGL camera axes)."""
    return world_from_cam @ CV_FROM_GL


def cv_world_from_cam_from_gl(gl_world_from_cam_: np.ndarray) -> np.ndarray:
    return gl_world_from_cam_ @ GL_FROM_CV


def ros_world_from_cam(world_from_cam: np.ndarray) -> np.ndarray:
    """Our world_from_cam -> ROS/Foxglove world (z up) from the camera optical frame (OpenCV axes, REP 103)."""
    return ROS_FROM_WORLD @ world_from_cam


def world_from_ros_world() -> np.ndarray:
    return ROS_FROM_WORLD.T.copy()


def asset_from_canonical(floor_y: float) -> np.ndarray:
    """The simulation asset frame (USD, collider.obj): REP 103 axes (x forward = the panorama's centre column, y left,
    z up) with the origin on the floor below the capture point (canonical (0, floor_y, 0))."""
    t = np.eye(4)
    t[2, 3] = float(floor_y)
    return t @ ROS_FROM_WORLD
