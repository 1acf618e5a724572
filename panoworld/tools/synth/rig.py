"""A capture rig under the panorama camera (tripod legs, column, mount, optional soft shadow) for nadir ground truth."""

from __future__ import annotations

import enum
from dataclasses import replace

import numpy as np
import trimesh

from panoworld.core.conventions import erp_dirs
from panoworld.tools.synth.appearance import Material, MaterialKind


class RigKind(enum.StrEnum):
    """What stands under the panorama camera in the rendered panorama.png (gt/ stays rig-free)."""

    NONE = "none"
    """Nothing: the panorama is the clean render."""
    TRIPOD = "tripod"
    """Three thin dark legs reaching the floor about 17 degrees from the nadir, a central column and a mount."""
    TRIPOD_SHADOW = "tripod-shadow"
    """The tripod plus a darker soft disc on the floor around its feet (a photographer's or lamp's shadow)."""


LEG_FOOT_RADIUS_M = 0.5
"""Horizontal distance of each tripod foot from the point under the camera."""
SHADOW_RADIUS_M = 0.4
"""1/e radius of the shadow's Gaussian darkening on the floor."""
SHADOW_STRENGTH = 0.45
"""Fraction of the light removed at the shadow's centre."""


def _segment(a: np.ndarray, b: np.ndarray, radius: float) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=radius, segment=np.stack([a, b]), sections=10)


def rig_meshes(world_from_cam: np.ndarray, camera_height: float, *, yaw: float = 0.0) -> list[trimesh.Trimesh]:
    """Tripod meshes (world frame, up = -Y, floor at y = 0) under a camera at world_from_cam: a mount box 0.22 m
    below the lens, a column down to 0.6 m below it, and three legs from there to feet LEG_FOOT_RADIUS_M out."""
    c = np.asarray(world_from_cam, np.float64)[:3, 3]
    down = np.array([0.0, 1.0, 0.0])
    top = c + 0.22 * down
    hub = c + 0.6 * down
    mount = trimesh.creation.box(extents=(0.045, 0.04, 0.045))
    mount.apply_translation(top + 0.02 * down)
    parts = [mount, _segment(top + 0.04 * down, hub, 0.015)]
    floor_y = c[1] + camera_height
    for k in range(3):
        a = yaw + 2.0 * np.pi * k / 3.0
        out = np.array([np.sin(a), 0.0, np.cos(a)])
        foot = c + LEG_FOOT_RADIUS_M * out
        foot[1] = floor_y
        parts.append(_segment(hub + 0.02 * out, foot, 0.018))
    return parts


def free_yaw(scene, n: int = 24) -> float:
    """The tripod yaw (radians) whose three legs stay farthest from the scene geometry (legs never cut walls)."""
    T = scene.world_from_canonical
    h = scene.tracks[0].camera_height
    hub = T[:3, 3] + np.array([0.0, 0.6, 0.0])
    best, best_margin = 0.0, -np.inf
    for yaw in np.arange(n) * 2.0 * np.pi / (3 * n):
        feet = [T[:3, 3] + np.array([LEG_FOOT_RADIUS_M * np.sin(yaw + 2 * np.pi * k / 3), h - 0.01,
                                     LEG_FOOT_RADIUS_M * np.cos(yaw + 2 * np.pi * k / 3)]) for k in range(3)]
        d = np.array([f - hub for f in feet])
        length = np.linalg.norm(d, axis=1)
        hit = scene.raycaster.cast(np.repeat(hub[None], 3, 0), d / length[:, None])
        margin = float(np.min(np.where(np.isfinite(hit.distance), hit.distance, 1e9) - length))
        if margin > best_margin:
            best, best_margin = float(yaw), margin
    return best


def with_rig(scene):
    """A copy of a SynthScene with the tripod under its canonical camera (node 'rig.metal', material 'rig_0')."""
    meshes = rig_meshes(scene.world_from_canonical, scene.tracks[0].camera_height, yaw=free_yaw(scene))
    mesh = trimesh.util.concatenate(meshes)
    materials = dict(scene.materials)
    materials["rig_0"] = Material(kind=MaterialKind.PAINT, color=(0.035, 0.035, 0.04), color2=(0.035, 0.035, 0.04),
                                  scale=0.05, seed=7)
    node = replace(scene.nodes[0], name="rig.metal", object="rig", kind="rig", room=0, material="rig_0",
                     vertices=np.asarray(mesh.vertices, np.float32), faces=np.asarray(mesh.faces, np.int64))
    return replace(scene, nodes=[*scene.nodes, node], materials=materials)


def shadow_gain(world_from_cam: np.ndarray, camera_height: float, depth: np.ndarray) -> np.ndarray:
    """Per-pixel light factor (H, W) of the soft shadow disc for an ERP render's depth (H, W) from world_from_cam:
    1 - SHADOW_STRENGTH * exp(-(r / SHADOW_RADIUS_M)^2) on floor pixels, r the floor distance from under the camera."""
    H, W = depth.shape
    T = np.asarray(world_from_cam, np.float64)
    d = erp_dirs(H, W, np.float64) @ T[:3, :3].T
    p = T[:3, 3] + d * np.where(np.isfinite(depth), depth, 0.0)[..., None]
    floor_y = T[1, 3] + camera_height
    on_floor = np.isfinite(depth) & (np.abs(p[..., 1] - floor_y) < 2e-3)
    r2 = (p[..., 0] - T[0, 3]) ** 2 + (p[..., 2] - T[2, 3]) ** 2
    return np.where(on_floor, 1.0 - SHADOW_STRENGTH * np.exp(-r2 / SHADOW_RADIUS_M**2), 1.0)


def render_with_rig(scene, kind: RigKind | str, height: int, *, supersample: int = 1):
    """Render the canonical panorama with the rig -> (rgb (H, W, 3) uint8, depth (H, W) float32, rig mask (H, W)
    bool: pixels whose colour differs from the clean render by more than 8 levels or whose ray hits the rig)."""
    kind = RigKind(kind)
    T = scene.world_from_canonical
    clean_rgb, clean_depth = scene.render(T, height, 2 * height, supersample=supersample)
    if kind == RigKind.NONE:
        return clean_rgb, clean_depth, np.zeros(clean_depth.shape, bool)
    rigged = with_rig(scene)
    rgb, depth = rigged.render(T, height, 2 * height, supersample=supersample)
    if kind == RigKind.TRIPOD_SHADOW:
        g = shadow_gain(T, scene.tracks[0].camera_height, depth)
        lin = (rgb.astype(np.float64) / 255.0) ** 2.2 * g[..., None]
        rgb = np.clip(np.rint(255.0 * lin ** (1 / 2.2)), 0, 255).astype(np.uint8)
    mask = (np.abs(rgb.astype(np.int16) - clean_rgb).max(-1) > 8) | (depth < clean_depth - 1e-3)
    return rgb, depth, mask


class FloorObject(enum.StrEnum):
    """A seen object under the camera that rig removal must keep (tests and bench/bench_rig.py)."""

    RUG = "rug"
    """A dark 1.6 x 1.1 m rug, 8 mm thick, lying on the floor under the camera, off-centre."""
    STOOL = "stool"
    """A dark round stool top 0.5 m across, 0.45 m above the floor, right under the camera."""


def with_floor_object(scene, kind: FloorObject | str):
    """A copy of a SynthScene with a rug or a stool top under its canonical camera (node 'seen.<kind>')."""
    kind = FloorObject(kind)
    c = scene.world_from_canonical[:3, 3]
    floor_y = c[1] + scene.tracks[0].camera_height
    if kind == FloorObject.RUG:
        mesh = trimesh.creation.box(extents=(1.6, 0.008, 1.1))
        mesh.apply_translation([c[0] + 0.25, floor_y - 0.004, c[2] - 0.15])
        mat = Material(kind=MaterialKind.FABRIC, color=(0.05, 0.03, 0.06), color2=(0.12, 0.05, 0.04), scale=0.08, seed=5)
    else:
        mesh = trimesh.creation.cylinder(radius=0.25, height=0.03, sections=32)
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        mesh.apply_translation([c[0], floor_y - 0.45, c[2]])
        mat = Material(kind=MaterialKind.PAINT, color=(0.04, 0.04, 0.05), color2=(0.04, 0.04, 0.05), scale=0.05, seed=6)
    materials = dict(scene.materials)
    materials[f"seen_{kind}"] = mat
    node = replace(scene.nodes[0], name=f"seen.{kind}", object="seen", kind=str(kind), room=0, material=f"seen_{kind}",
                   vertices=np.asarray(mesh.vertices, np.float32), faces=np.asarray(mesh.faces, np.int64))
    return replace(scene, nodes=[*scene.nodes, node], materials=materials)
