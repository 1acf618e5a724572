"""Synthetic scenes that reproduce the failure classes of real captures (layout-only depth, blind bands, a rig or
an object under the camera, sparse LiDAR in unknown units, odd image formats and sizes), built from the generator."""

from __future__ import annotations

import enum
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from panoworld.core.conventions import erp_dirs
from panoworld.tools.synth.generate import generate_scene
from panoworld.tools.synth.params import FurnitureParams, params_for
from panoworld.tools.synth.scene import SynthScene


class FailureCase(enum.StrEnum):
    """Failure classes of real panoramas, each rebuilt on a generated scene (see docs/real_inputs.md)."""

    LAYOUT_ONLY = "layout-only"
    """An empty room: perfectly planar floor, walls and ceiling (room-layout annotations)."""
    ZERO_BANDS = "zero-bands"
    """Depth 0 in bands at the top and bottom and NaN in a column band (Matterport-style sensor blind zones)."""
    RIG_BLIND_SPOT = "rig-blind-spot"
    """No depth below 60 degrees under the horizon: the capture rig hides the floor the camera stands on."""
    OBJECT_UNDER_CAMERA = "object-under-camera"
    """A round table top 0.45 m across just under the camera: the start is off the walkable floor."""
    SPARSE_LIDAR = "sparse-lidar"
    """Every 4th column and 30 % of the rest valid, stored as a 16-bit PNG in unknown units (450 per metre)."""
    ODD_FORMAT = "odd-format"
    """RGBA 16-bit panorama PNG, depth at half the panorama's resolution."""
    GRAYSCALE_EXIF = "grayscale-exif"
    """Grayscale JPEG stored rotated a quarter turn with EXIF orientation 6; depth at twice the resolution."""
    HUGE = "huge"
    """A panorama taller than the depth stage's max_height (its resolution policy; the test lowers max_height)."""
    CLOSET = "closet"
    """The camera stands in a shallow closet (0.8 m wide, 0.65 m deep) looking out through its 0.6 m door: no floor
    fits the agent."""
    FAR_OUTLIERS = "far-outliers"
    """0.2 % isolated depth spikes and one degenerate wall patch at hundreds of metres (a broken layout / sensor)."""
    RIG_HIDES_FLOOR = "rig-hides-floor"
    """A low rig footprint (a 1 m disk, 0.3 m high) seen under the camera: the start is 1 m off the walkable floor."""


LIDAR_UNITS_PER_M = 450.0
"""Unit scale of the sparse LiDAR case (Realsee-like raw values)."""


def failure_scene(seed: int = 0) -> SynthScene:
    """The ci-tiny scene of seed the failure cases are rendered from."""
    return generate_scene(seed, "ci-tiny")


def empty_room(seed: int = 0) -> SynthScene:
    """A ci-tiny room without furniture or pictures (a layout-only scene)."""
    p = params_for("ci-tiny")
    p = replace(p, furniture=FurnitureParams(per_room=(0, 0), pictures_per_room=(0, 0)))
    return generate_scene(seed, params=p)


def write_failure_scene(case: FailureCase | str, out_dir: Path | str, *, seed: int = 0, height: int = 128) -> Path:
    """Write a scene directory (panorama + depth file, gt_scene.json facts) reproducing one failure class.

    The panorama is rendered from the canonical view of the seed's ci-tiny scene at height x 2 height (the huge
    case: 4 x height). gt_scene.json records the case, the camera height and the number of pixels made invalid.
    """
    import cv2

    case = FailureCase(case)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = empty_room(seed) if case == FailureCase.LAYOUT_ONLY else failure_scene(seed)
    h = 4 * height if case == FailureCase.HUGE else height
    rgb, depth = scene.render(scene.world_from_canonical, h, 2 * h)
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    cam_h = float(scene.tracks[0].camera_height)
    dirs = erp_dirs(h, 2 * h, dtype=np.float64)
    lat_deg = np.rad2deg(np.arcsin(-dirs[..., 1]))
    facts: dict = {"case": str(case), "seed": seed, "camera_height_m": cam_h}

    if case == FailureCase.ZERO_BANDS:
        bad = (lat_deg > 60) | (lat_deg < -55)
        depth[bad] = 0.0
        depth[:, h // 2: h // 2 + max(2, h // 32)] = np.nan
        facts["invalid_pixels"] = int(bad.sum())
    elif case == FailureCase.RIG_BLIND_SPOT:
        depth[lat_deg < -60] = 0.0
        facts["invalid_pixels"] = int((lat_deg < -60).sum())
    elif case == FailureCase.OBJECT_UNDER_CAMERA:
        top = 0.8 * cam_h  # table top 0.2 camera heights above the floor (camera at the origin, y down)
        depth = _with_disk(depth, dirs, top=top, radius=0.45)
        facts.update(object_radius_m=0.45, object_top_above_floor_m=cam_h - top)
    elif case == FailureCase.RIG_HIDES_FLOOR:
        depth = _with_disk(depth, dirs, top=cam_h - 0.3, radius=1.0)
        facts.update(object_radius_m=1.0, object_top_above_floor_m=0.3)
    elif case == FailureCase.CLOSET:
        walls = closet_depth(dirs, cam_h)
        rgb = np.where((walls < depth)[..., None], np.uint8([150, 120, 90]), rgb)  # painted closet walls
        depth = np.minimum(depth, walls).astype(np.float32)
        facts.update(closet_half_width_m=CLOSET["half_width"], closet_back_m=CLOSET["back"],
                     closet_front_m=CLOSET["front"], door_half_width_m=CLOSET["door_half_width"])
    elif case == FailureCase.FAR_OUTLIERS:
        rng = np.random.default_rng(seed + 1)
        spikes = rng.random(depth.shape) < 0.002
        depth[spikes] = rng.uniform(200.0, 900.0, int(spikes.sum()))
        lon = np.rad2deg(np.arctan2(dirs[..., 0], dirs[..., 2]))
        wall = (np.abs(lon - 90) < 12) & (lat_deg > -10) & (lat_deg < 35)
        depth[wall] *= 150.0
        facts.update(spike_pixels=int(spikes.sum()), wall_pixels=int(wall.sum()), outlier_pixels=int((spikes | wall).sum()))

    if case == FailureCase.SPARSE_LIDAR:
        rng = np.random.default_rng(seed)
        keep = np.zeros_like(depth, bool)
        keep[:, 1::4] = True
        keep |= rng.random(depth.shape) < 0.3
        keep &= np.abs(lat_deg) < 70  # zenith / nadir blind spots
        raw = np.where(keep, np.rint(depth * LIDAR_UNITS_PER_M), 0).clip(0, 65535).astype(np.uint16)
        cv2.imwrite(str(out / "depth.png"), raw)
        facts.update(units_per_m=LIDAR_UNITS_PER_M, valid_fraction=float(keep.mean()))
    elif case == FailureCase.ODD_FORMAT:
        np.save(out / "depth.npy", cv2.resize(depth, (h, h // 2), interpolation=cv2.INTER_NEAREST))
    elif case == FailureCase.GRAYSCALE_EXIF:
        np.save(out / "depth.npy", cv2.resize(depth, (4 * h, 2 * h), interpolation=cv2.INTER_NEAREST))
    else:
        np.save(out / "depth.npy", depth)

    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    if case == FailureCase.ODD_FORMAT:
        rgba16 = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA).astype(np.uint16) * 257
        cv2.imwrite(str(out / "panorama.png"), rgba16)
    elif case == FailureCase.GRAYSCALE_EXIF:
        _write_exif_rotated_gray_jpeg(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), out / "panorama.jpg")
    else:
        cv2.imwrite(str(out / "panorama.png"), bgr)
    (out / "gt_scene.json").write_text(json.dumps(facts, indent=1))
    return out


CLOSET = {"half_width": 0.4, "back": -0.3, "front": 0.35, "door_half_width": 0.25, "door_height": 2.0}
"""Closet box around the camera (canonical frame, metres): side walls x = +-half_width, back wall z = back, front wall
z = front with a door |x| < door_half_width up to door_height above the floor."""


def closet_depth(dirs: np.ndarray, cam_h: float) -> np.ndarray:
    """Ray distance (H, W) to the closet's walls (inf where a ray leaves through the door)."""
    c = CLOSET
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.full(dirs.shape[:2], np.inf)
        for axis, plane in ((0, c["half_width"]), (0, -c["half_width"]), (2, c["back"]), (2, c["front"])):
            t = plane / dirs[..., axis]
            p = t[..., None] * dirs
            ok = (t > 0) & (p[..., 1] <= cam_h)
            if axis == 0:
                ok &= (p[..., 2] >= c["back"]) & (p[..., 2] <= c["front"])
            else:
                ok &= np.abs(p[..., 0]) <= c["half_width"]
                if plane == c["front"]:
                    ok &= ~((np.abs(p[..., 0]) < c["door_half_width"]) & (p[..., 1] > cam_h - c["door_height"]))
            out = np.where(ok, np.minimum(out, t), out)
    return out


def _with_disk(depth: np.ndarray, dirs: np.ndarray, *, top: float, radius: float) -> np.ndarray:
    """depth with a horizontal disk (radius, `top` metres below the camera) under the camera in front of it."""
    t = top / np.maximum(dirs[..., 1], 1e-9)
    on = (dirs[..., 1] > 0) & (np.hypot(t * dirs[..., 0], t * dirs[..., 2]) <= radius) & (t < depth)
    return np.where(on, t, depth).astype(np.float32)


def _write_exif_rotated_gray_jpeg(gray: np.ndarray, path: Path) -> None:
    """Store gray (H, W) turned a quarter turn counter-clockwise with EXIF orientation 6 (display: rotate 90 degrees
    clockwise), as cameras held sideways do; readers that honour EXIF see the original."""
    from PIL import Image

    stored = np.ascontiguousarray(np.rot90(gray, 1))
    img = Image.fromarray(stored, mode="L")
    exif = Image.Exif()
    exif[0x0112] = 6
    img.save(path, quality=95, exif=exif)
