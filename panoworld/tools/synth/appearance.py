"""Procedural materials as deterministic functions of (material spec, 3D point, normal), and baked point-light shading."""

from __future__ import annotations

import enum
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from panoworld.core.shapes import check_shape

_U64 = np.uint64


class MaterialKind(enum.StrEnum):
    """Procedural albedo patterns."""

    PLASTER = "plaster"
    WOOD = "wood"
    PLANKS = "planks"
    TILES = "tiles"
    FABRIC = "fabric"
    PAINT = "paint"
    PICTURE = "picture"
    BOOKS = "books"
    LIGHT = "light"


@dataclass(kw_only=True)
class Material:
    """Parameters of one procedural material; the pattern is a pure function of these and the surface point."""

    kind: MaterialKind
    """Pattern family."""
    color: tuple[float, float, float]
    """Main linear RGB albedo in [0, 1] (the emitted colour for LIGHT)."""
    color2: tuple[float, float, float]
    """Secondary linear RGB albedo in [0, 1] (grain, grout, pattern accents)."""
    scale: float
    """Characteristic size in metres (tile size, plank width, ring spacing, pattern cell)."""
    seed: int
    """Seed of the material's hashed noise and palettes."""
    axis: int = 0
    """World axis (0 = x, 2 = z) along which wood grain, planks and book rows run."""

    def to_json(self) -> dict:
        d = asdict(self)
        d["kind"] = str(self.kind)
        d["color"], d["color2"] = list(self.color), list(self.color2)
        return d

    @classmethod
    def from_json(cls, d: dict) -> Material:
        return cls(
            kind=MaterialKind(d["kind"]), color=tuple(d["color"]), color2=tuple(d["color2"]),
            scale=float(d["scale"]), seed=int(d["seed"]), axis=int(d["axis"]),
        )


def _hash01(seed: int, *ints: np.ndarray) -> np.ndarray:
    """Integer lattice coordinates (same shape) -> uniform [0, 1) floats, a fixed integer hash (splitmix64)."""
    h = np.full(np.shape(ints[0]), _U64((seed * 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF), _U64)
    for k, a in zip((0xBF58476D1CE4E5B9, 0x94D049BB133111EB, 0xD6E8FEB86659FD93), ints):
        h = (h ^ np.asarray(a, np.int64).astype(_U64)) * _U64(k)
        h ^= h >> _U64(31)
    h = (h ^ (h >> _U64(30))) * _U64(0xBF58476D1CE4E5B9)
    h ^= h >> _U64(27)
    return (h >> _U64(40)).astype(np.float64) / float(1 << 24)


def value_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 2D value noise in [0, 1] with unit lattice spacing."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    iu, iv = iu.astype(np.int64), iv.astype(np.int64)
    su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    a, b = _hash01(seed, iu, iv), _hash01(seed, iu + 1, iv)
    c, d = _hash01(seed, iu, iv + 1), _hash01(seed, iu + 1, iv + 1)
    return (a + (b - a) * su) * (1 - sv) + (c + (d - c) * su) * sv


def fbm(u: np.ndarray, v: np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of value noise in [0, 1]; octave k has frequency 2^k and amplitude 2^-k."""
    total, norm, amp, f = 0.0, 0.0, 1.0, 1.0
    for k in range(octaves):
        total = total + amp * value_noise(u * f, v * f, seed + 7919 * k)
        norm += amp
        amp *= 0.5
        f *= 2.0
    return total / norm


def planar_coords(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project points (N, 3) onto the plane of the dominant normal axis -> (u, v) in metres, u horizontal."""
    ax = np.argmax(np.abs(normals), axis=1)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    u = np.where(ax == 0, z, x)
    v = np.where(ax == 1, z, y)
    # Offset by the plane coordinate so parallel planes do not repeat the same pattern.
    w = np.choose(ax, [x, y, z])
    return u + 0.37 * w, v + 0.61 * w


def _mix(c1, c2, t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)[:, None]
    return np.asarray(c1)[None, :] * (1 - t) + np.asarray(c2)[None, :] * t


def _palette(seed: int, n: int) -> np.ndarray:
    """n saturated colours (n, 3) derived from seed."""
    rng = np.random.default_rng(seed)
    hsv = np.stack([rng.uniform(0, 360, n), rng.uniform(0.4, 0.9, n), rng.uniform(0.35, 0.95, n)], 1)
    return cv2.cvtColor(hsv.astype(np.float32)[None], cv2.COLOR_HSV2RGB)[0].astype(np.float64)


def albedo(mat: Material, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Linear RGB albedo (N, 3) of material at world points (N, 3) with unit normals (N, 3)."""
    check_shape("normals", normals, "N 3", dims=check_shape("points", points, "N 3"))
    s, seed = mat.scale, mat.seed
    u, v = planar_coords(points, normals)
    kind = mat.kind
    if kind == MaterialKind.LIGHT:
        return np.broadcast_to(np.asarray(mat.color), points.shape).copy()
    if kind == MaterialKind.PLASTER:
        n = fbm(u / s, v / s, seed, 4)
        speck = value_noise(u / 0.015, v / 0.015, seed + 1)
        return _mix(mat.color, mat.color2, 1.6 * (n - 0.3)) * (0.93 + 0.14 * speck)[:, None]
    if kind == MaterialKind.PAINT:
        n = fbm(u / s, v / s, seed, 3)
        return np.asarray(mat.color)[None, :] * (0.85 + 0.3 * n)[:, None]
    if kind in (MaterialKind.WOOD, MaterialKind.PLANKS):
        along = points[:, mat.axis]
        across = points[:, 2 - mat.axis]
        height = points[:, 1]
        tint = np.ones_like(along)
        if kind == MaterialKind.PLANKS:
            row = np.floor(across / s)
            offset = _hash01(seed + 3, row.astype(np.int64)) * 4.0
            plank = np.floor((along + offset) / (8 * s))
            tint = 0.75 + 0.5 * _hash01(seed + 4, row.astype(np.int64), plank.astype(np.int64))
            f_across = across / s - row
            f_along = (along + offset) / (8 * s) - plank
            gap = np.minimum(np.minimum(f_across, 1 - f_across) * s, np.minimum(f_along, 1 - f_along) * 8 * s)
            tint = tint * np.where(gap < 0.004, 0.45, 1.0)
            across = across + 13.7 * row
            along = along + 5.3 * plank
        warp = fbm(along / 0.7, across / 0.05, seed + 5, 3)
        rings = np.sqrt((across - 0.3) ** 2 + (height * 0.35) ** 2) / (s * 0.2) + 3.0 * warp
        grain = np.abs(np.mod(rings, 1.0) - 0.5) * 2
        streak = value_noise(along / 0.4, across / 0.012, seed + 6)
        t = 0.65 * grain**3 + 0.35 * streak
        return _mix(mat.color, mat.color2, t) * tint[:, None]
    if kind == MaterialKind.TILES:
        iu, iv = np.floor(u / s), np.floor(v / s)
        fu, fv = u / s - iu, v / s - iv
        edge = np.minimum(np.minimum(fu, 1 - fu), np.minimum(fv, 1 - fv)) * s
        h = _hash01(seed, iu.astype(np.int64), iv.astype(np.int64))
        marble = fbm(u / (0.5 * s), v / (0.5 * s), seed + 1, 4)
        veins = np.abs(np.sin(8.0 * marble + 20.0 * h))
        base = _mix(mat.color, mat.color2, 0.6 * h + 0.4 * (1 - veins) ** 4)
        grout = np.asarray(mat.color2)[None, :] * 0.35
        return np.where((edge < 0.005)[:, None], grout, base)
    if kind == MaterialKind.FABRIC:
        n = fbm(u / 0.04, v / 0.04, seed, 3)
        plaid = 0.5 * (np.sin(2 * np.pi * u / s) > 0.6) + 0.5 * (np.sin(2 * np.pi * v / s) > 0.6)
        weave = value_noise(u / 0.01, v / 0.01, seed + 1)
        return _mix(mat.color, mat.color2, 0.6 * plaid + 0.5 * n - 0.2) * (0.85 + 0.2 * weave)[:, None]
    if kind == MaterialKind.PICTURE:
        pal = _palette(seed, 8)
        big = (u / (3 * s), v / (3 * s))
        small = (u / s, v / s)
        ib = _hash01(seed, np.floor(big[0]).astype(np.int64), np.floor(big[1]).astype(np.int64))
        ism = _hash01(seed + 1, np.floor(small[0]).astype(np.int64), np.floor(small[1]).astype(np.int64))
        fx, fy = np.mod(small[0], 1.0) - 0.5, np.mod(small[1], 1.0) - 0.5
        circle = (fx**2 + fy**2) < (0.15 + 0.2 * ism) ** 2
        idx = np.where(circle, (ism * 8).astype(int), (ib * 8).astype(int)) % 8
        col = pal[idx]
        n = fbm(u / (0.5 * s), v / (0.5 * s), seed + 2, 3)
        return col * (0.6 + 0.6 * n)[:, None]
    if kind == MaterialKind.BOOKS:
        pal = _palette(seed, 10)
        t = (points[:, 0] + points[:, 2]) / s
        it = np.floor(t + 0.6 * value_noise(t, np.zeros_like(t), seed + 2)).astype(np.int64)
        h = _hash01(seed, it)
        col = pal[(h * 10).astype(int) % 10]
        band = np.mod(points[:, 1] * 30.0 + h * 7, 1.0) < 0.12
        return col * np.where(band, 0.5, 1.0)[:, None] * (0.85 + 0.3 * _hash01(seed + 1, it))[:, None]
    raise ValueError(f"unknown material kind {kind!r}")


@dataclass(kw_only=True)
class Light:
    """Isotropic point light."""

    position: tuple[float, float, float]
    """World position in metres."""
    intensity: tuple[float, float, float]
    """Linear RGB irradiance scale at 0 m (falls off as 1 / (1 + (d / falloff)^2))."""
    falloff: float
    """Distance in metres at which the light's irradiance has halved."""


def srgb_uint8(linear: np.ndarray) -> np.ndarray:
    """Linear RGB in [0, inf) -> 8-bit sRGB-like (gamma 2.2), clipped."""
    return np.round(255.0 * np.clip(linear, 0.0, 1.0) ** (1 / 2.2)).astype(np.uint8)
