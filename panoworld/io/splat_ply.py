"""INRIA 3D Gaussian Splatting .ply files (what 3DGS viewers open) and coloured point cloud .ply files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from panoworld.core.conventions import rotmat_from_quat_wxyz
from panoworld.core.shapes import check_shape
from panoworld.io.gaussian_set import Gaussians

NUM_REST = 45
"""f_rest_* properties of the full degree-3 layout (written with full_sh=True for tools that insist on it)."""
NORMAL_FIELDS = ["nx", "ny", "nz"]
"""Written only in the full layout (full_sh=True): 3DGS viewers and the INRIA loader ignore them."""
REST_PER_DEGREE = {0: 0, 1: 3, 2: 8, 3: 15}
"""Higher-order SH coefficients per colour channel up to each degree."""


def gaussian_fields(degree: int = 3, *, normals: bool = True) -> list[str]:
    """Vertex properties of the INRIA layout with SH up to `degree` (degree 3 with normals: 62 properties; degree 0
    without: 14)."""
    return (["x", "y", "z"] + (NORMAL_FIELDS if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * REST_PER_DEGREE[degree])]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


GAUSSIAN_FIELDS = gaussian_fields(3)


def used_sh_degree(sh_rest: np.ndarray) -> int:
    """The highest SH degree with a nonzero coefficient in sh_rest (N, K, 3)."""
    for degree in (3, 2, 1):
        lo, hi = REST_PER_DEGREE[degree - 1], REST_PER_DEGREE[degree]
        if sh_rest.shape[1] >= hi and np.any(sh_rest[:, lo:hi]):
            return degree
    return 0


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), 1e-7, 1 - 1e-7)
    return np.log(p / (1 - p))


def write_gaussians_ply(path: str | Path, gaussians: Gaussians, *, full_sh: bool = False) -> None:
    """Binary little-endian INRIA layout: x y z, f_dc_0..2, f_rest_* (channel-major, up to the highest SH degree the
    Gaussians use: none for view-independent colours), opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z).
    With full_sh the complete INRIA layout for tools that insist on it: nx ny nz (the axis of the smallest scale)
    after x y z and f_rest_0..44 (zero-padded to degree 3).

    Coordinates are our canonical world frame: metres, camera 0 = identity with OpenCV axes, so y points down
    (gravity), like COLMAP-trained INRIA scenes. Viewers that assume y up (SuperSplat, three.js-based ones) show it
    upside down until rotated 180 degrees about x.
    """
    g = gaussians.numpy()
    n = len(g)
    degree = 3 if full_sh else used_sh_degree(g.sh_rest)
    k = REST_PER_DEGREE[degree]
    rest = np.zeros((n, k, 3), np.float32)
    m = min(k, g.sh_rest.shape[1])
    rest[:, :m] = g.sh_rest[:, :m]
    cols = [g.means, g.sh_dc, rest.transpose(0, 2, 1).reshape(n, 3 * k),
            _logit(g.opacities)[:, None], np.log(np.maximum(g.scales, 1e-12)), g.quats]
    if full_sh:
        axes = rotmat_from_quat_wxyz(g.quats) if n else np.zeros((0, 3, 3))
        cols.insert(1, axes[np.arange(n), :, np.argmin(g.scales, axis=1)] if n else np.zeros((0, 3)))
    data = np.concatenate([np.asarray(c, "<f4").reshape(n, -1) for c in cols], 1)
    fields = gaussian_fields(degree, normals=full_sh)
    vertex = data.view([(name, "<f4") for name in fields]).reshape(n)  # each row one record, no copy
    PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(path))


def read_gaussians_ply(path: str | Path) -> Gaussians:
    """Read an INRIA-layout .ply (any SH degree 0-3) back into Gaussians; ValueError names a missing property."""
    try:
        ply = PlyData.read(str(path))
    except (OSError, ValueError, UnicodeDecodeError, PlyParseError) as e:
        raise ValueError(f"{path}: not a readable .ply file ({e})") from None
    if "vertex" not in ply:
        raise ValueError(f"{path}: no 'vertex' element; expected an INRIA 3DGS .ply")
    v = ply["vertex"].data
    names = set(v.dtype.names)
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)]
    need += [f"rot_{i}" for i in range(4)]
    missing = [n for n in need if n not in names]
    if missing:
        raise ValueError(f"{path}: vertex properties {missing} missing; expected an INRIA 3DGS .ply")
    n_rest = len([n for n in names if n.startswith("f_rest_")])
    if n_rest % 3 or n_rest // 3 not in (0, 3, 8, 15):
        raise ValueError(f"{path}: {n_rest} f_rest_* properties but expected 0, 9, 24 or 45")

    order = list(v.dtype.names)
    if v.flags.c_contiguous and v.dtype == np.dtype([(f, "<f4") for f in order]):  # all float32: one (N, P) block
        block = v.view("<f4").reshape(len(v), len(order))

        def cols(fields):
            idx = [order.index(f) for f in fields]
            if idx == list(range(idx[0], idx[0] + len(idx))):  # adjacent properties: a slice, not a gather (3x)
                return np.ascontiguousarray(block[:, idx[0] : idx[0] + len(idx)])
            return np.ascontiguousarray(block[:, idx])
    else:
        def cols(fields):
            return np.stack([np.asarray(v[f], np.float32) for f in fields], 1)

    k = n_rest // 3
    rest = cols([f"f_rest_{i}" for i in range(n_rest)]) if n_rest else np.zeros((len(v), 0), np.float32)
    return Gaussians(
        means=cols(["x", "y", "z"]),
        scales=np.exp(cols([f"scale_{i}" for i in range(3)])),
        quats=cols([f"rot_{i}" for i in range(4)]),  # as stored; renderers normalise
        opacities=(1.0 / (1.0 + np.exp(-np.asarray(v["opacity"], np.float64)))).astype(np.float32),
        sh_dc=cols(["f_dc_0", "f_dc_1", "f_dc_2"]),
        sh_rest=rest.reshape(len(v), 3, k).transpose(0, 2, 1).copy(),
    )


def write_points_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary point cloud: xyz (N, 3) float32 and rgb (N, 3) uint8 (or floats in [0, 1]) as red, green, blue."""
    xyz = np.asarray(xyz)
    rgb = np.asarray(rgb)
    check_shape("rgb", rgb, "N 3", dims=check_shape("xyz", xyz, "N 3"))
    if rgb.dtype != np.uint8:
        rgb = np.clip(np.round(rgb.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    vertex = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, c in enumerate("xyz"):
        vertex[c] = xyz[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        vertex[c] = rgb[:, i]
    PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(path))


def read_points_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of write_points_ply: (xyz (N, 3) float32, rgb (N, 3) uint8)."""
    v = PlyData.read(str(path))["vertex"].data
    xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32)
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.uint8)
    return xyz, rgb
