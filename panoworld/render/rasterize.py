"""Exact ERP triangle rasteriser (numba, z-buffered, seam- and pole-exact) with the Embree ray caster as its reference."""

from __future__ import annotations

from contextlib import contextmanager

import numba
import numpy as np

from panoworld.core.conventions import check_erp_shape, check_pose, erp_lonlat_from_pixel, invert_pose
from panoworld.core.shapes import check_shape
from panoworld.geometry.raycast import Hits, Raycaster
from panoworld.io.conditions import WarpedFrame
from panoworld.render.cull_kernels import (
    _cluster_spheres,
    _cluster_vertices,
    _may_show,
    _morton_keys,
    _seen_clusters,
    _tile_far,
)
from panoworld.render.raster_kernels import (
    _NO_HIT,
    _POLAR_FRACTION,
    _raster_clusters,
    _raster_pass,
    _resolve_hits,
    _resolve_shaded,
    _vertex_pass,
    _vertex_pass_clusters,
)

CULL_CLUSTER = 1024
"""Faces per cluster of ErpRasterizer's occlusion culling (0 = none)."""
CULL_MIN_FACES = 6_000_000
"""Meshes of fewer faces are not culled: a frame of a 2 M-face single-panorama mesh cost 45 % more CPU culled and one
of a 5.2 M-face home of 7 panoramas the same, one of a 10.9 M-face home of 15 panoramas 37 % less (720 x 1440)."""
CULL_TILE = 8
"""Pixels per side of the z-buffer tiles the culling's clusters are tested against."""

# ---------------------------------------------------------------------------------------------- public API


def shade_hits(hits: Hits, faces: np.ndarray, colors: np.ndarray, face_valid: np.ndarray) -> WarpedFrame:
    """Hits (H, W) of a mesh -> WarpedFrame: barycentric vertex colours (V, 3) uint8, depth, mask = valid face hit.

    The CPU reference for the numba path's fused shading (used with Embree hits by the `raycast` backend).
    """
    face = hits.face
    hit = face >= 0
    safe = np.where(hit, face, 0)
    mask = hit & face_valid[safe]
    idx = faces[safe]  # (H, W, 3)
    col = (colors[idx].astype(np.float64) * hits.bary[..., None].astype(np.float64)).sum(axis=-2)
    rgb = np.clip(np.floor(col + 0.5), 0, 255).astype(np.uint8)
    rgb[~mask] = 0
    depth = np.where(mask, hits.distance, 0.0).astype(np.float32)
    return WarpedFrame(rgb, depth, mask)


def _check_mesh_arrays(vertices, faces, colors, face_valid):
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    dims = check_shape("vertices", vertices, "V 3")
    check_shape("faces", faces, "F 3", dims=dims)
    if len(faces) == 0:
        raise ValueError("cannot render an empty mesh (0 faces)")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"faces index vertices in [{faces.min()}, {faces.max()}] but there are {len(vertices)}")
    if colors is None:
        colors = np.full((len(vertices), 3), 128, np.uint8)
    colors = np.ascontiguousarray(colors, dtype=np.uint8)
    check_shape("colors", colors, "V 3", dims=dims)
    if face_valid is None:
        face_valid = np.ones(len(faces), bool)
    face_valid = np.ascontiguousarray(face_valid, dtype=np.bool_)
    check_shape("face_valid", face_valid, "F", dims=dims)
    return vertices, faces, colors, face_valid


class ErpRasterizer:
    """Numba ERP rasteriser of one triangle mesh; per-mesh buffers are shared by every pose it renders.

    vertices (V, 3) and faces (F, 3) as for Raycaster; colors (V, 3) uint8 and face_valid (F,) bool are needed only
    for shaded renders (defaults: grey, all valid). Results equal Raycaster.render_erp's up to float rounding.
    A mesh of cull_min_faces faces or more is culled per pose (cull_cluster 0 = never): clusters of cull_cluster nearby faces
    whose bounding sphere lies behind what the z-buffer already holds over its whole footprint are not rasterised (the
    clusters the previous pose showed go first), with the same result as without.
    """

    def __init__(self, vertices, faces, colors=None, face_valid=None, *, num_threads: int | None = None,
                 cull_cluster: int = CULL_CLUSTER, cull_min_faces: int = CULL_MIN_FACES):
        self.vertices, self.faces, self.colors, self.face_valid = _check_mesh_arrays(vertices, faces, colors, face_valid)
        self.num_threads = num_threads or numba.get_num_threads()
        self._vdata = np.empty((len(self.vertices), 8), np.float32)
        n_chunks = min(len(self.faces), 32 * self.num_threads)
        self._chunks = np.linspace(0, len(self.faces), n_chunks + 1).astype(np.int64)
        self._size: tuple[int, int] | None = None
        cull = cull_cluster and len(self.faces) >= max(cull_min_faces, 2 * cull_cluster)
        self._clusters = self._make_clusters(cull_cluster) if cull else None
        self._seen: np.ndarray | None = None  # the clusters the last frame showed
        self.rasterised = 0  # the clusters the last pose rasterised (with culling)

    def _make_clusters(self, size: int) -> dict:
        """Occlusion culling's clusters of `size` faces in Morton order of their centroids: the order, each
        cluster's faces (starts) and distinct vertices (vptr, vidx), bounding spheres and each face's cluster."""
        v = self.vertices
        cent = (v[self.faces[:, 0]] + v[self.faces[:, 1]] + v[self.faces[:, 2]]) / np.float32(3.0)
        lo, hi = cent.min(0).astype(np.float64), cent.max(0).astype(np.float64)
        order = np.argsort(_morton_keys(cent, lo, 2097151.0 / max(float((hi - lo).max()), 1e-9)), kind="stable")
        del cent
        starts = np.append(np.arange(0, len(order), size), len(order)).astype(np.int64)
        vptr, vidx = _cluster_vertices(self.faces, order, starts, len(v))
        n = len(starts) - 1
        centres, radii = np.empty((n, 3)), np.empty(n)
        _cluster_spheres(v, vptr, vidx, centres, radii)
        cluster_of = np.empty(len(order), np.int32)
        cluster_of[order] = np.repeat(np.arange(n, dtype=np.int32), np.diff(starts))
        return {"order": order, "starts": starts, "vptr": vptr, "vidx": vidx, "centres": centres, "radii": radii,
                "of": cluster_of}

    def _prepare(self, world_from_cam, height, width):
        check_pose(world_from_cam, "world_from_cam")
        check_erp_shape(height, width, "requested ERP render")
        if self._size != (height, width):
            lon, lat = erp_lonlat_from_pixel(np.arange(width) + 0.5, np.arange(height) + 0.5, height, width)
            self._tables = (np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon))
            rho_top = 0.5 * np.pi / height  # angular distance of the first row's centres from the pole
            delta = _POLAR_FRACTION * rho_top
            self._polar_sin = float(np.sin(delta))
            self._pad_polar = float(1.1 * 2.0 * np.arcsin(np.tan(delta) / np.tan(rho_top)) * width / (2 * np.pi))
            self._zbufs = np.full((self.num_threads, height * width), _NO_HIT, np.uint64)
            self._bbufs = np.zeros((self.num_threads, height * width, 2), np.float32)
            self._size = (height, width)
        cam_from_world = np.ascontiguousarray(invert_pose(np.asarray(world_from_cam, np.float64))[:3])
        if self._clusters is not None:
            self._prepare_culled(cam_from_world, height, width)
            return
        with self._parallel(max(1, len(self.vertices) // (8 * self.num_threads))):
            _vertex_pass(self.vertices, cam_from_world, height, width, self._polar_sin, self._vdata)
        with self._parallel(1):
            _raster_pass(
                self.faces, self._vdata, height, width, *self._tables, self._pad_polar, self._chunks, self._zbufs,
                self._bbufs,
            )

    def _prepare_culled(self, cam_from_world, height, width):
        """_prepare's z-buffering with occlusion culling: the clusters the last frame showed (all on the first
        frame), then those of the others that the z-buffer so far does not hide; the same buffers as without."""
        cl = self._clusters
        n = len(cl["radii"])
        first = np.arange(n) if self._seen is None else np.flatnonzero(self._seen)
        self.rasterised = 0
        self._raster_some(first, cam_from_world, height, width)
        rest = np.setdiff1d(np.arange(n), first, assume_unique=True)
        if len(rest):
            far = np.empty((-(-height // CULL_TILE), -(-width // CULL_TILE)), np.float32)
            show = np.empty(len(rest), bool)
            with self._parallel(1):
                _tile_far(self._zbufs, width, CULL_TILE, far)
                _may_show(rest, cl["centres"], cl["radii"], cam_from_world, far, CULL_TILE, height, width, show)
            self._raster_some(rest[show], cam_from_world, height, width)
        self._seen = np.zeros(n, bool)
        with self._parallel(4096):
            _seen_clusters(self._zbufs, cl["of"], self._seen)

    def _raster_some(self, clusters, cam_from_world, height, width):
        cl = self._clusters
        if not len(clusters):
            return
        clusters = np.ascontiguousarray(clusters, np.int64)
        self.rasterised += len(clusters)
        with self._parallel(1):
            _vertex_pass_clusters(self.vertices, cam_from_world, height, width, self._polar_sin, self._vdata,
                                  cl["vptr"], cl["vidx"], clusters)
            _raster_clusters(self.faces, cl["order"], cl["starts"], clusters, self._vdata, height, width,
                             *self._tables, self._pad_polar, self._zbufs, self._bbufs)

    @contextmanager
    def _parallel(self, chunksize: int):
        """Run numba kernels on self.num_threads threads handing out `chunksize` iterations at a time (dynamic
        scheduling: a thread that loses its core to another process does not hold up the others)."""
        prev_threads = numba.get_num_threads()
        numba.set_num_threads(self.num_threads)
        prev_chunk = numba.set_parallel_chunksize(chunksize)
        try:
            yield
        finally:
            numba.set_parallel_chunksize(prev_chunk)
            numba.set_num_threads(prev_threads)

    def render_erp(self, world_from_cam: np.ndarray, height: int, width: int) -> Hits:
        """Nearest face per ERP pixel centre: Hits(distance (H, W) inf = none, face (H, W) -1 = none, bary (H, W, 3))."""
        self._prepare(world_from_cam, height, width)
        dist = np.empty((height, width), np.float32)
        face = np.empty((height, width), np.int64)
        bary = np.empty((height, width, 3), np.float32)
        with self._parallel(8):
            _resolve_hits(self._zbufs, self._bbufs, width, dist, face, bary)
        return Hits(dist, face, bary)

    def render(self, world_from_cam: np.ndarray, height: int, width: int, out: WarpedFrame | None = None) -> WarpedFrame:
        """Warped colour, depth and validity mask at one pose (written into `out` if given)."""
        self._prepare(world_from_cam, height, width)
        if out is None:
            out = WarpedFrame(
                np.empty((height, width, 3), np.uint8), np.empty((height, width), np.float32),
                np.empty((height, width), bool),
            )
        with self._parallel(8):
            _resolve_shaded(
                self._zbufs, self._bbufs, self.faces, self.colors, self.face_valid, width, out.rgb, out.depth, out.mask
            )
        return out


class RaycastRenderer:
    """The Embree reference with ErpRasterizer's interface (exact, several times slower)."""

    def __init__(self, vertices, faces, colors=None, face_valid=None):
        self.vertices, self.faces, self.colors, self.face_valid = _check_mesh_arrays(vertices, faces, colors, face_valid)
        self.raycaster = Raycaster(self.vertices, self.faces)

    def render_erp(self, world_from_cam: np.ndarray, height: int, width: int) -> Hits:
        return self.raycaster.render_erp(world_from_cam, height, width)

    def render(self, world_from_cam: np.ndarray, height: int, width: int, out: WarpedFrame | None = None) -> WarpedFrame:
        frame = shade_hits(self.render_erp(world_from_cam, height, width), self.faces, self.colors, self.face_valid)
        if out is None:
            return frame
        out.rgb[...] = frame.rgb
        out.depth[...] = frame.depth
        out.mask[...] = frame.mask
        return out
