"""Panoramas from a camera that was not level: the tilt found from the floor, registration levelled and composed back."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import invert_pose, pose_from_rt
from panoworld.geometry.level import level_from_cam, levelled, levelled_depth, tilt_deg
from panoworld.register import solve
from panoworld.register.solve import register_panoramas
from tests.test_register import TOL_CM, TOL_DEG, _errors, _home_sources


def tilt_from_level(deg: float, azimuth: float) -> np.ndarray:
    """(3, 3) a camera turned by deg about the horizontal axis at azimuth (Rodrigues, written out)."""
    axis = np.array([np.sin(azimuth), 0.0, np.cos(azimuth)])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def test_the_tilt_is_found_from_the_floor_and_levelling_keeps_the_yaw(home_dir):
    _, _, _, depths = _home_sources(home_dir)
    depth = depths["pano_00"]
    assert level_from_cam(depth) is None  # a level capture is left as it is
    for deg, az in ((2.0, 0.3), (1.0, 2.5), (5.0, 4.0)):
        X = tilt_from_level(deg, az)
        R = level_from_cam(levelled_depth(depth, X))
        assert R is not None and abs(tilt_deg(R) - deg) < 0.15, (deg, None if R is None else tilt_deg(R))
        undone = R @ X  # levelled again: at most a turn about the vertical, here none
        assert np.degrees(np.arccos(np.clip((np.trace(undone) - 1) / 2, -1, 1))) < 0.15
    assert level_from_cam(levelled(depth, tilt_from_level(0.1, 1.0), nearest=True)) is None
    assert level_from_cam(levelled(depth, tilt_from_level(15.0, 1.0), nearest=True)) is None  # no floor that steep


def layout_home(height: int = 384) -> tuple[list[str], dict, dict, dict]:
    """(names, true poses in the first panorama's frame, panoramas, layout depths) of the ci-tiny home of seed 7: each
    depth its room's walls, floor and ceiling alone, as real tours give it, so registration rests on the floor and the
    bearings (upright models) rather than on depth that agrees."""
    from dataclasses import replace

    from panoworld.tools.synth.home import floor_plan, generate_home, home_params, layout_depth

    params = home_params("ci-tiny")
    params = replace(params, render=replace(params.render, pano_height=height))
    home = generate_home(7, 3, "ci-tiny", params=params)
    plan = floor_plan(home.scene)
    names = [f"pano_{k:02d}" for k in range(len(home.world_from_cam))]
    rgbs, depths, poses = {}, {}, {}
    for n, pose, room in zip(names, home.world_from_cam, home.rooms):
        rgbs[n] = home.scene.render(pose, height, 2 * height)[0]
        depths[n] = layout_depth(plan, room, pose, height, 2 * height).astype(np.float32)
        poses[n] = invert_pose(home.world_from_cam[0]) @ pose
    return names, poses, rgbs, depths


def test_tilted_panoramas_register_with_their_tilt_in_the_pose(monkeypatch):
    """pano_01 and pano_02 of a home with layout depth as a camera tilted by 2 deg captured them: registered within the
    tolerance of level panoramas, their poses holding the tilt, registration.json saying what was levelled; without
    the levelling the tilt would pass into their poses (2 deg, 5-6 cm)."""
    names, poses, rgbs, depths = layout_home()
    truth = dict(poses)
    for k, n in enumerate(names[1:]):
        X = tilt_from_level(2.0, 1.0 + 2.0 * k)
        rgbs[n], depths[n] = levelled(rgbs[n], X), levelled_depth(depths[n], X)
        truth[n] = poses[n] @ invert_pose(pose_from_rt(X, np.zeros(3)))  # world_from_level @ level_from_tilted
    reg = register_panoramas(names, rgbs, depths)
    assert sorted(reg.world_from_cam) == names
    for n in names:
        t_cm, r_deg = _errors(reg.world_from_cam[n], truth[n])
        assert t_cm <= TOL_CM / 2 and r_deg <= TOL_DEG / 4, (n, t_cm, r_deg)
    assert "levelled_tilt_deg" not in reg.panoramas["pano_00"]
    assert all(abs(reg.panoramas[n]["levelled_tilt_deg"] - 2.0) < 0.2 for n in names[1:])
    monkeypatch.setattr(solve, "level_from_cam", lambda depth: None)
    unlevelled = register_panoramas(names, rgbs, depths).world_from_cam
    assert max(_errors(unlevelled[n], truth[n])[1] for n in names[1:] if n in unlevelled) > 1.5
