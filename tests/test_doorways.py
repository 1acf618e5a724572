"""Doorways a layout depth closes are opened where two panoramas see one floor through them, and nowhere else."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from panoworld.core.conventions import erp_dirs
from panoworld.room.doorways import is_layout, open_doorways

H, W = 512, 1024
CAM_H, CEIL = 1.4, 1.0
"""Camera height above the floor and ceiling above the camera (metres)."""
# Two 4 x 4 m rooms side by side (x in [0, 4] and [4, 8], z in [0, 4]); the wall between them at x = 4 has a
# doorway at z in [1.5, 2.5] (floor to ceiling).
ROOMS = {"a": (0.0, 4.0), "b": (4.0, 8.0)}
CAMS = {"a": np.array([2.6, 0.0, 2.2]), "b": np.array([5.4, 0.0, 1.8])}
DOOR = (1.5, 2.5)


def _floor_texture(seed: int = 0) -> np.ndarray:
    """Grey floor texture over x, z in [0, 8] x [0, 4] at 1 cm: blobs of light and wear with fine grain."""
    rng = np.random.default_rng(seed)
    low = cv2.resize(rng.uniform(60, 200, (8, 16)).astype(np.float32), (800, 400), interpolation=cv2.INTER_CUBIC)
    mid = cv2.resize(rng.uniform(-40, 40, (80, 160)).astype(np.float32), (800, 400), interpolation=cv2.INTER_CUBIC)
    return np.clip(low + mid + rng.normal(0, 6, (400, 800)), 0, 255).astype(np.float32)


def _render(cam: np.ndarray, walls: list[tuple[np.ndarray, np.ndarray]], tex: np.ndarray, wall_tex: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """(RGB (H, W, 3) uint8, ray depth (H, W)) from cam (world: x, y down, z) of floor, ceiling and the vertical wall
    segments ((2,) plan start, (2,) plan end), with camera axes = world axes."""
    d = erp_dirs(H, W, np.float64)
    flat = np.hypot(d[..., 0], d[..., 2])
    ux, uz = d[..., 0] / np.maximum(flat, 1e-12), d[..., 2] / np.maximum(flat, 1e-12)
    r_wall = np.full((H, W), np.inf)
    o = cam[[0, 2]]
    for p0, p1 in walls:
        e = p1 - p0
        den = ux * (-e[1]) - uz * (-e[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((p0[0] - o[0]) * (-e[1]) - (p0[1] - o[1]) * (-e[0])) / den
            s = (ux * (p0[1] - o[1]) - uz * (p0[0] - o[0])) / den
        hit = np.isfinite(t) & (t > 1e-6) & (s >= 0) & (s <= 1)
        r_wall = np.where(hit & (t < r_wall), t, r_wall)
    t_wall = r_wall / np.maximum(flat, 1e-12)
    t_floor = np.where(d[..., 1] > 0, CAM_H / np.maximum(d[..., 1], 1e-12), np.inf)
    t_ceil = np.where(d[..., 1] < 0, CEIL / np.maximum(-d[..., 1], 1e-12), np.inf)
    depth = np.minimum(np.minimum(t_wall, t_floor), t_ceil)
    p = cam + d * depth[..., None]
    # Walls papered with a texture like the floor's (its own pattern): texture alone could agree by chance.
    along = np.clip(((p[..., 0] + p[..., 2]) * 100).astype(int), 0, wall_tex.shape[1] - 1)
    up = np.clip(((CAM_H - p[..., 1]) * 100).astype(int), 0, wall_tex.shape[0] - 1)
    grey = np.where(d[..., 1] < 0, 130.0, wall_tex[up, along])
    on_floor = t_floor <= depth + 1e-9
    ix = np.clip((p[..., 0] * 100).astype(int), 0, tex.shape[1] - 1)
    iz = np.clip((p[..., 2] * 100).astype(int), 0, tex.shape[0] - 1)
    grey = np.where(on_floor, tex[iz, ix], grey)
    rgb = np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, -1)
    return rgb, depth.astype(np.float32)


def _box(x0: float, x1: float, door: bool) -> list[tuple[np.ndarray, np.ndarray]]:
    """A room's walls; with door, the wall at x1 (a's) or x0 (b's) keeps a gap at DOOR."""
    P = lambda x, z: np.array([x, z])
    walls = [(P(x0, 0), P(x1, 0)), (P(x0, 4), P(x1, 4))]
    for x in (x0, x1):
        if door and x == 4.0:
            walls += [(P(x, 0), P(x, DOOR[0])), (P(x, DOOR[1]), P(x, 4))]
        else:
            walls.append((P(x, 0), P(x, 4)))
    return walls


def _home(door: bool):
    tex, wall_tex = _floor_texture(0), _floor_texture(1)
    home = _box(0, 4, door) + _box(4, 8, door)
    rgbs, depths, poses = {}, {}, {}
    for n, cam in CAMS.items():
        rgbs[n], _ = _render(cam, home, tex, wall_tex)  # what the camera sees: through the doorway where there is one
        _, depths[n] = _render(cam, _box(*ROOMS[n], door=False), tex, wall_tex)  # its layout: its own room, doorway closed
        poses[n] = np.eye(4)
        poses[n][:3, 3] = cam
    return rgbs, depths, poses


@pytest.fixture(scope="module")
def doorway_home():
    return _home(door=True)


def test_layout_depth_is_told_from_a_furnished_one(doorway_home):
    _, depths, _ = doorway_home
    assert is_layout(depths["a"], CAM_H)
    furnished = depths["a"].copy()
    furnished[H // 2 + 40:H // 2 + 120, 100:400] *= 0.7  # a sofa in front of the wall
    assert not is_layout(furnished, CAM_H)
    # A closet 0.6 m square: its walls fill most of the view above 40 degrees, and it is still a layout.
    tex = _floor_texture(0)
    corners = [np.array(c) for c in ((0.7, 1.7), (1.3, 1.7), (1.3, 2.3), (0.7, 2.3))]
    _, closet = _render(np.array([1.0, 0.0, 2.0]), list(zip(corners, corners[1:] + corners[:1])), tex, tex)
    up = erp_dirs(H, W, np.float64)[..., 1] < -np.sin(np.radians(40.0))
    assert (closet[up] * -erp_dirs(H, W, np.float64)[..., 1][up] < CEIL - 0.01).mean() > 0.5
    assert is_layout(closet, CAM_H)


def _opened(home):
    """open_doorways on a copy of the home's depths -> (pixels opened per panorama, {NAME: (changed (H, W) bool,
    world points of the depth before (H, W, 3), depth after (H, W))})."""
    rgbs, depths, poses = home
    depths = {n: d.copy() for n, d in depths.items()}
    before = {n: d.copy() for n, d in depths.items()}
    opened = open_doorways(["a", "b"], rgbs, depths, poses)
    d = erp_dirs(H, W, np.float64)
    return opened, {n: (depths[n] != before[n], CAMS[n] + d * before[n][..., None], depths[n]) for n in depths}


def test_open_doorways_opens_the_doorway_from_both_sides(doorway_home):
    opened, result = _opened(doorway_home)
    assert opened["a"] > 0 and opened["b"] > 0
    d = erp_dirs(H, W, np.float64)
    for changed, p, after in result.values():
        # What opened lies on the shared wall at x = 4, in or beside the doorway (the opening widened by its margin).
        assert np.all(np.abs(p[changed][:, 0] - 4.0) < 1e-3)
        z = p[changed][:, 2]
        assert z.min() > DOOR[0] - 0.25 and z.max() < DOOR[1] + 0.25
        in_door = (np.abs(p[..., 0] - 4.0) < 1e-3) & (p[..., 2] > DOOR[0] + 0.1) & (p[..., 2] < DOOR[1] - 0.1)
        in_door &= (CAM_H - p[..., 1] > 0.1) & (CAM_H - p[..., 1] < 1.9)
        assert changed[in_door].mean() > 0.95
        # Below the horizon the floor continues through the doorway; the rest of the opening is unknown.
        through = changed & (after > 0)
        assert through.any() and np.allclose(after[through] * d[..., 1][through], CAM_H, atol=1e-3)


def test_matched_keypoints_alone_open_a_doorway_and_never_a_wall(doorway_home, monkeypatch):
    """Where the floor textures do not correlate (a narrow view through a doorway), at least MATCHED_OPENING floor
    keypoints seen through the wall that match the other panorama's in place open it, within the doorway; a solid
    wall gets none."""
    from panoworld.room import doorways

    monkeypatch.setattr(doorways, "_agreeing_columns", lambda a, b, seen_b, gb, grey, depths, heights, world_from_cam:
                        np.zeros(depths[a].shape[1], bool))
    opened, result = _opened(doorway_home)
    assert opened["a"] > 0 and opened["b"] > 0
    for changed, p, _ in result.values():
        assert DOOR[0] - 0.25 < p[changed][:, 2].min() and p[changed][:, 2].max() < DOOR[1] + 0.25
    assert _opened(_home(door=False))[0] == {"a": 0, "b": 0}


def test_open_doorways_keeps_a_solid_wall():
    opened, result = _opened(_home(door=False))
    assert opened == {"a": 0, "b": 0} and not any(changed.any() for changed, _, _ in result.values())


def test_synth_layout_depth_is_the_capture_room_alone(tmp_path):
    """`synth --panoramas K --depth layout`: each depth is its room's walls, floor and flat ceiling, every doorway
    closed: finite everywhere, a layout (is_layout), the furniture in front of it, and the scene seen beyond it only
    through the room's doorways."""
    from dataclasses import replace

    from scipy import ndimage

    from panoworld.core.conventions import transform_points
    from panoworld.tools.synth.cli import main
    from panoworld.tools.synth.home import floor_plan, generate_home, home_params, layout_depth

    params = home_params("ci-tiny")
    params = replace(params, render=replace(params.render, pano_height=96))
    home = generate_home(7, 3, "ci-tiny", params=params)
    plan = floor_plan(home.scene)
    near_door = ndimage.distance_transform_edt(~plan.door) * plan.cell <= plan.cell
    for pose, room in zip(home.world_from_cam, home.rooms):
        _, scene = home.scene.render(pose, 96, 192)
        layout = layout_depth(plan, room, pose, 96, 192)
        assert np.isfinite(layout).all() and is_layout(layout, -pose[1, 3])
        assert (np.abs(scene - layout) < 1e-3).mean() > 0.4  # walls, floor and ceiling where nothing stands
        beyond = scene > layout + 0.02
        assert beyond.any()  # every capture room has a doorway
        wall = transform_points(pose, erp_dirs(96, 192, np.float64)[beyond] * layout[beyond][:, None])
        ij = np.clip(np.round(plan.to_grid(wall[:, [0, 2]])).astype(int), 0, np.array(plan.door.shape) - 1)
        assert near_door[ij[:, 0], ij[:, 1]].all()
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "x"), "--seed", "1", "--depth", "layout"])
    assert e.value.code == 2 and not (tmp_path / "x").exists()


def test_open_doorways_opens_the_true_doorways_of_a_synthetic_home():
    """A furnished synthetic home of 4 rooms, 4 panoramas at their true poses, each with its room's layout depth: the
    walls opened lie at the floor plan's doorways (within 0.2 m: the opening's margin), all but a strip of the plain
    wall beside one doorway, whose shading correlates with the floor behind it (91 % of the pixels); on two worker
    threads the same."""
    from dataclasses import replace

    from scipy import ndimage

    from panoworld.core.conventions import invert_pose, transform_points
    from panoworld.tools.synth.home import floor_plan, generate_home, home_params, layout_depth

    params = home_params("ci-tiny")
    params = replace(params, render=replace(params.render, pano_height=384))
    home = generate_home(2, 4, "ci-tiny", params=params)
    plan = floor_plan(home.scene)
    rgbs, depths = {}, {}
    for n, pose, room in zip(home.names, home.world_from_cam, home.rooms):
        rgbs[n], _ = home.scene.render(pose, 384, 768)
        depths[n] = layout_depth(plan, room, pose, 384, 768)
    before = {n: d.copy() for n, d in depths.items()}
    first = invert_pose(home.world_from_cam[0])
    poses = {n: first @ T for n, T in zip(home.names, home.world_from_cam)}
    opened = open_doorways(home.names, rgbs, depths, poses)
    assert sum(opened.values()) > 20000
    # the panoramas' looks through their walls on two threads open the same pixels to the same depth
    threaded = {n: d.copy() for n, d in before.items()}
    assert open_doorways(home.names, rgbs, threaded, poses, workers=2) == opened
    assert all(np.array_equal(threaded[n], depths[n]) for n in home.names)
    near_door = ndimage.distance_transform_edt(~plan.door) * plan.cell <= 0.2 + plan.cell / 2
    at_door = 0
    for n, pose in zip(home.names, home.world_from_cam):
        changed = depths[n] != before[n]
        wall = transform_points(pose, erp_dirs(384, 768, np.float64)[changed] * before[n][changed][:, None])
        ij = np.clip(np.round(plan.to_grid(wall[:, [0, 2]])).astype(int), 0, np.array(plan.door.shape) - 1)
        at_door += int(near_door[ij[:, 0], ij[:, 1]].sum())
    assert at_door >= 0.85 * sum(opened.values())
