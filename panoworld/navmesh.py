"""Walkable-floor NavMesh from a scene mesh: floor height, heightfield, erosion, polygons, triangulation, A* + funnel."""

from __future__ import annotations

import heapq
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from panoworld.conventions import GLTF_FROM_WORLD, transform_points

NAVMESH_JSON = "navmesh.json"
NAVMESH_OBJ = "navmesh.obj"
NAVMESH_GLB = "navmesh.glb"
FORMAT_VERSION = 1
MIN_CAMERA_HEIGHT_M = 0.3
"""Horizontal triangles closer than this below the camera are never taken as the floor."""


class NoFloorError(ValueError):
    """The mesh has no walkable floor (no up-facing area below the camera, or nothing left after erosion)."""


@dataclass(kw_only=True)
class NavMeshParams:
    """How the walkable floor is extracted from a scene mesh (world frame, metres, up = -Y)."""

    cell_m: float = 0.03
    """Heightfield cell size in metres (rays are cast down at cell centres)."""
    agent_radius_m: float = 0.25
    """Agent (camera) radius: the floor is eroded by this distance from every obstacle and unseen cell."""
    agent_height_m: float = 1.8
    """Top of the obstacle band above the floor; raised to camera height + agent radius when the camera is higher."""
    step_height_m: float = 0.2
    """Geometry up to this height above the floor is walkable (rugs, thresholds); above it is an obstacle."""
    max_slope_deg: float = 15.0
    """Triangles tilted at most this much from horizontal vote for the floor height."""
    max_range_m: float = 12.0
    """Only geometry within this horizontal distance from the camera is considered."""
    min_floor_area_m2: float = 0.25
    """Minimum visible floor area (in the winning histogram bin) to accept a floor height."""
    simplify_m: float = 0.0
    """Polygon simplification tolerance (approxPolyDP) in metres; 0 = one cell. Compensated by extra erosion."""
    max_triangle_area_m2: float = 0.25
    """Largest NavMesh triangle ('triangle' quality meshing), so A* over triangles gives short corridors."""
    camera_footprint_m: float = 0.0
    """Unseen floor within this horizontal radius of the camera counts as walkable (tripod / nadir blind spot of
    real captures: the camera stood there); obstacles are never overridden. 0 = trust only what was seen."""
    max_erp_height: int = 192
    """ERP grid meshes (panoworld.mesh layout) with more rows are re-meshed from every s-th pixel first (speed)."""


@dataclass
class FloorGrid:
    """The heightfield raster: cell (i, j) has centre x = x0 + (j + 0.5) * cell, z = z0 + (i + 0.5) * cell."""

    x0: float
    z0: float
    cell: float
    walkable: np.ndarray
    """(Hz, Wx) bool: the downward ray hit a valid face within step height of the floor and no obstacle is there."""
    obstacle: np.ndarray
    """(Hz, Wx) bool: geometry between step height and the band top."""
    unseen: np.ndarray
    """(Hz, Wx) bool: the downward ray hit nothing, an invalid (stretched) face, or a hole below the floor."""
    free: np.ndarray
    """(Hz, Wx) bool: walkable cells eroded by the agent radius (all components)."""

    def cell_of(self, xz: np.ndarray) -> np.ndarray:
        """World (N, 2) x,z -> integer cells (N, 2) as (i, j)."""
        xz = np.asarray(xz, np.float64).reshape(-1, 2)
        return np.stack([np.floor((xz[:, 1] - self.z0) / self.cell), np.floor((xz[:, 0] - self.x0) / self.cell)], 1).astype(int)

    def xz_of(self, ij: np.ndarray) -> np.ndarray:
        """Cells (N, 2) as (i, j) (float allowed) -> world x,z of their centres (N, 2)."""
        ij = np.asarray(ij, np.float64).reshape(-1, 2)
        return np.stack([self.x0 + (ij[:, 1] + 0.5) * self.cell, self.z0 + (ij[:, 0] + 0.5) * self.cell], 1)


# ---------------------------------------------------------------- floor and heightfield


def _face_geometry(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (centroids (F, 3), areas (F,), |n_y| of the unit normals (F,))."""
    tri = vertices[faces].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ny = np.abs(n[:, 1]) / np.maximum(norm, 1e-20)
    return tri.mean(axis=1), 0.5 * norm, ny


def check_mesh(vertices: np.ndarray, faces: np.ndarray, face_valid: np.ndarray | None) -> np.ndarray:
    """Check shapes of vertices (V, 3), faces (F, 3), face_valid (F,) and return face_valid (all True if None)."""
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"{vertices.shape=} but expected (V, 3)")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{faces.shape=} but expected (F, 3)")
    if face_valid is None:
        return np.ones(len(faces), bool)
    face_valid = np.asarray(face_valid, bool)
    if face_valid.shape != (len(faces),):
        raise ValueError(f"{face_valid.shape=} but expected ({len(faces)},) like faces")
    return face_valid


def estimate_floor_y(
    vertices: np.ndarray, faces: np.ndarray, face_valid: np.ndarray | None = None, *, params: NavMeshParams, bin_m: float = 0.02
) -> tuple[float, float]:
    """Floor height y (world, up = -Y) from an area-weighted histogram of horizontal triangles below the camera.

    The camera is at the origin. Returns (floor_y, floor_area_m2 in the winning bin +- one bin).
    Raises NoFloorError when there is not enough horizontal area below the camera.
    """
    face_valid = check_mesh(vertices, faces, face_valid)
    cen, area, ny = _face_geometry(vertices, faces)
    cand = (
        face_valid
        & (ny >= np.cos(np.deg2rad(params.max_slope_deg)))
        & (cen[:, 1] > MIN_CAMERA_HEIGHT_M)
        & (np.hypot(cen[:, 0], cen[:, 2]) <= params.max_range_m)
        & np.isfinite(cen).all(axis=1)
    )
    if not cand.any():
        raise NoFloorError(
            f"no horizontal triangles more than {MIN_CAMERA_HEIGHT_M} m below the camera (is the floor visible?)"
        )
    y, w = cen[cand, 1], area[cand]
    edges = np.arange(MIN_CAMERA_HEIGHT_M, y.max() + 2 * bin_m, bin_m)
    hist, _ = np.histogram(y, bins=edges, weights=w)
    smooth = np.convolve(hist, [1.0, 1.0, 1.0], mode="same")
    k = int(np.argmax(smooth))
    if smooth[k] < params.min_floor_area_m2:
        raise NoFloorError(
            f"only {smooth[k]:.3f} m^2 of horizontal floor-like area below the camera "
            f"(need {params.min_floor_area_m2} m^2)"
        )
    sel = (y >= edges[max(k - 1, 0)]) & (y < edges[min(k + 2, len(edges) - 1)])
    order = np.argsort(y[sel])
    cw = np.cumsum(w[sel][order])
    floor_y = float(y[sel][order][np.searchsorted(cw, 0.5 * cw[-1])])
    return floor_y, float(smooth[k])


def erp_grid_shape(vertices: np.ndarray) -> tuple[int, int] | None:
    """(h, w) of an ErpMesh grid (vertex i * w + j = pixel (i, j) of an h x 2h ERP grid, then two poles), or None.

    Checks that the non-zero vertices point along the h x w ERP pixel-centre rays (any other mesh gives None).
    """
    from panoworld.conventions import dir_from_lonlat, erp_lonlat_from_pixel

    n = len(vertices) - 2
    h = int(round(np.sqrt(max(n, 0) / 2)))
    if h < 2 or 2 * h * h != n:
        return None
    v = vertices[:n].astype(np.float64)
    r = np.linalg.norm(v, axis=1)
    idx = np.flatnonzero(r > 0)[:: max(1, n // 4096)]
    if len(idx) == 0:
        return None
    d = dir_from_lonlat(*erp_lonlat_from_pixel(idx % (2 * h) + 0.5, idx // (2 * h) + 0.5, h, 2 * h))
    if np.max(np.linalg.norm(v[idx] / r[idx, None] - d, axis=1)) > 0.5 * np.pi / h:  # half a grid pixel
        return None
    return h, 2 * h


def downsample_erp_mesh(
    vertices: np.ndarray, faces: np.ndarray, face_valid: np.ndarray, max_height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Re-mesh an ErpMesh grid from every s-th pixel so that it has at most max_height rows.

    Returns (vertices, faces, face_valid, s); s = 1 and the input unchanged when the mesh is small or not an
    ERP grid mesh. Depth discontinuities are re-flagged by panoworld.mesh at the coarse grid.
    """
    from panoworld.mesh import erp_mesh_from_depth

    shape = erp_grid_shape(vertices)
    if shape is None or shape[0] <= max_height:
        return vertices, faces, face_valid, 1
    h, w = shape
    s = int(np.ceil(h / max_height))
    depth = np.linalg.norm(vertices[: h * w].astype(np.float64), axis=1).reshape(h, w).astype(np.float32)
    m = erp_mesh_from_depth(depth, np.zeros((h, w, 3), np.uint8), depth > 0, stride=s)
    return m.vertices, m.faces, m.face_valid, s


def band_top(floor_y: float, params: NavMeshParams) -> float:
    """Height above the floor up to which geometry blocks the agent (>= camera height + radius)."""
    return max(params.agent_height_m, floor_y + params.agent_radius_m)


def floor_grid(
    vertices: np.ndarray, faces: np.ndarray, face_valid: np.ndarray, floor_y: float, *, params: NavMeshParams
) -> FloorGrid:
    """Heightfield by rays cast down on a grid + obstacle band marking + erosion by the agent radius.

    Obstacles are cells whose downward ray (from the band top) first hits a face higher than step height, plus
    cells holding vertices or edge samples of valid faces inside the band (thin geometry between ray centres).
    Cells whose ray hits nothing, an invalid face, or a surface below floor - step are unseen (not walkable).
    Free = walkable cells at least agent_radius + one cell diagonal + simplify tolerance from any other cell.
    """
    import cv2

    from panoworld.raycast import Raycaster

    cell = params.cell_m
    top = band_top(floor_y, params)
    step = params.step_height_m
    height = floor_y - vertices[:, 1].astype(np.float64)  # above the floor
    rng_v = np.hypot(vertices[:, 0], vertices[:, 2])
    fh = height[faces]
    fh_min, fh_max = fh.min(axis=1), fh.max(axis=1)
    relevant = (rng_v[faces].min(axis=1) <= params.max_range_m) & (fh_max >= -2 * step) & (fh_min <= top)
    floorish = face_valid & relevant & (fh_min >= -step) & (fh_max <= step)
    if not floorish.any():
        raise NoFloorError(f"no valid triangles within {step} m of the floor height y = {floor_y:.3f} m")
    fv = np.unique(faces[floorish])
    pts = vertices[fv][:, [0, 2]].astype(np.float64)
    lo = np.minimum(pts.min(axis=0), 0.0) - 2 * cell
    hi = np.maximum(pts.max(axis=0), 0.0) + 2 * cell
    nx, nz = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()
    grid = FloorGrid(float(lo[0]), float(lo[1]), cell, *(np.zeros((nz, nx), bool) for _ in range(4)))

    rc = Raycaster(vertices, faces[relevant])
    valid_rel = face_valid[relevant]
    centers = grid.xz_of(np.stack(np.meshgrid(np.arange(nz), np.arange(nx), indexing="ij"), -1).reshape(-1, 2))
    origins = np.stack([centers[:, 0], np.full(len(centers), floor_y - top), centers[:, 1]], 1)
    dirs = np.broadcast_to(np.array([0.0, 1.0, 0.0]), origins.shape)
    hits = rc.cast(origins, dirs)
    hit = hits.face >= 0
    h = np.where(hit, top - hits.distance, -np.inf).reshape(nz, nx)
    ok_face = np.zeros(len(hit), bool)
    ok_face[hit] = valid_rel[hits.face[hit]]
    ok_face = ok_face.reshape(nz, nx)
    grid.obstacle = ok_face & (h > step)
    grid.walkable = ok_face & (np.abs(h) <= step)
    grid.unseen = ~(grid.obstacle | grid.walkable)
    if params.camera_footprint_m > 0:
        xz = grid.xz_of(np.argwhere(np.ones((nz, nx), bool)))
        under = (np.hypot(xz[:, 0], xz[:, 1]) <= params.camera_footprint_m).reshape(nz, nx) & grid.unseen
        grid.walkable |= under
        grid.unseen &= ~under

    # Vertices, and samples along edges longer than half a cell, of valid faces in the band: thin legs and
    # walls seen edge-on that rays through cell centres can miss.
    band = faces[face_valid & relevant & (fh_max > step) & (fh_min < top)]
    if len(band):
        p = [vertices[np.unique(band)].astype(np.float64)]
        e = np.concatenate([band[:, [0, 1]], band[:, [1, 2]], band[:, [2, 0]]])
        e0, e1 = vertices[e[:, 0]].astype(np.float64), vertices[e[:, 1]].astype(np.float64)
        n = np.ceil(np.linalg.norm(e1 - e0, axis=1) / (0.5 * cell)).astype(int)
        long = n > 1
        if long.any():
            e0, e1, n = e0[long], e1[long], n[long]
            idx = np.repeat(np.arange(len(n)), n - 1)
            t = (np.arange(len(idx)) - np.repeat(np.cumsum(n - 1) - (n - 1), n - 1) + 1) / np.repeat(n, n - 1)
            p.append(e0[idx] + t[:, None] * (e1 - e0)[idx])
        p = np.concatenate(p)
        ph = floor_y - p[:, 1]
        p = p[(ph > step) & (ph < top)]
        ij = grid.cell_of(p[:, [0, 2]])
        ij = ij[(ij[:, 0] >= 0) & (ij[:, 0] < nz) & (ij[:, 1] >= 0) & (ij[:, 1] < nx)]
        grid.obstacle[ij[:, 0], ij[:, 1]] = True
        grid.walkable[ij[:, 0], ij[:, 1]] = False

    walk = grid.walkable.copy()
    walk[[0, -1], :] = False
    walk[:, [0, -1]] = False
    dist = cv2.distanceTransform(walk.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * cell
    free = dist >= erosion_m(params)
    free = cv2.morphologyEx(free.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).astype(bool)
    grid.free = free
    return grid


def simplify_tolerance_m(params: NavMeshParams) -> float:
    return params.simplify_m if params.simplify_m > 0 else params.cell_m


def erosion_m(params: NavMeshParams) -> float:
    """Cell-centre distance kept from non-walkable cells: radius + half a cell diagonal + simplification slack."""
    return params.agent_radius_m + 0.5 * np.sqrt(2.0) * params.cell_m + simplify_tolerance_m(params)


# ---------------------------------------------------------------- polygons and triangulation


def _ring_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def polygons_from_mask(mask: np.ndarray, grid: FloorGrid, tol_m: float) -> list[np.ndarray]:
    """Boundary rings (K, 2) in world x,z of a raster region (through boundary cell centres), simplified by tol_m."""
    import cv2

    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    rings = []
    for c in contours:
        approx = cv2.approxPolyDP(c, tol_m / grid.cell, True)
        if len(approx) < 3:
            approx = c
        if len(approx) < 3:
            continue
        px = approx.reshape(-1, 2).astype(np.float64)  # (col, row)
        rings.append(grid.xz_of(px[:, ::-1]))
    return rings


def cross_section(rings: list[np.ndarray]):
    """manifold3d CrossSection of rings (even-odd), cleaned of self-intersections."""
    from manifold3d import CrossSection, FillRule

    return CrossSection([np.ascontiguousarray(r, dtype=np.float64) for r in rings], FillRule.EvenOdd)


def _pick_component(cs, xz: np.ndarray) -> tuple[list[np.ndarray], bool, float]:
    """The connected piece of a CrossSection containing xz (or the nearest one): (rings, contains, distance)."""
    best = None
    for piece in cs.decompose():
        rings = [np.asarray(r, np.float64) for r in piece.to_polygons()]
        segs = _ring_segments(rings)
        if _even_odd(xz[None], segs)[0]:
            return rings, True, 0.0
        d = float(_segment_distance(xz[None], segs)[0])
        if best is None or d < best[1]:
            best = (rings, d)
    if best is None:
        raise NoFloorError("no walkable floor is left after eroding by the agent radius")
    return best[0], False, best[1]


def _ring_segments(rings: list[np.ndarray]) -> np.ndarray:
    """All ring edges as (S, 2, 2)."""
    return np.concatenate([np.stack([r, np.roll(r, -1, axis=0)], 1) for r in rings], axis=0)


def _even_odd(points: np.ndarray, segs: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Point-in-polygon (even-odd rule) of points (N, 2) against ring segments (S, 2, 2) -> (N,) bool."""
    out = np.zeros(len(points), bool)
    a, b = segs[:, 0], segs[:, 1]
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk, None, :]
        cond = (a[None, :, 1] > p[..., 1]) != (b[None, :, 1] > p[..., 1])
        dy = np.where(cond, b[None, :, 1] - a[None, :, 1], 1.0)
        xint = a[None, :, 0] + (p[..., 1] - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / dy
        out[s : s + chunk] = (np.count_nonzero(cond & (p[..., 0] < xint), axis=1) % 2) == 1
    return out


def _segment_distance(points: np.ndarray, segs: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Distance of points (N, 2) to the nearest of segments (S, 2, 2) -> (N,)."""
    out = np.empty(len(points))
    a, ab = segs[:, 0], segs[:, 1] - segs[:, 0]
    ll = np.maximum((ab**2).sum(1), 1e-30)
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk, None, :]
        t = np.clip(((p - a) * ab).sum(-1) / ll, 0.0, 1.0)
        out[s : s + chunk] = np.sqrt(((a + t[..., None] * ab - p) ** 2).sum(-1).min(axis=1))
    return out


def triangulate_rings(rings: list[np.ndarray], max_area_m2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Constrained quality triangulation ('triangle' pq) of CCW outer rings and CW holes.

    Returns vertices (V, 2), CCW triangles (T, 3), adjacency (T, 3): the triangle across the edge opposite
    vertex k, or -1 on the boundary.
    """
    import triangle
    from manifold3d import triangulate

    verts, segs, holes = [], [], []
    base = 0
    for r in rings:
        n = len(r)
        verts.append(r)
        segs.append(np.stack([np.arange(n), (np.arange(n) + 1) % n], 1) + base)
        base += n
        if _ring_area(r) < 0:  # a hole: Triangle needs a point strictly inside it (a zero-area hole needs none)
            ccw = r[::-1].copy()
            tris = np.asarray(triangulate([ccw])).reshape(-1, 3)
            if len(tris):
                biggest = max(tris, key=lambda k: abs(_ring_area(ccw[k])))
                holes.append(ccw[biggest].mean(axis=0))
    data = {"vertices": np.concatenate(verts), "segments": np.concatenate(segs)}
    if holes:
        data["holes"] = np.asarray(holes)
    out = triangle.triangulate(data, f"pq25na{max_area_m2:.6f}")
    if "triangles" not in out or len(out["triangles"]) == 0:
        raise NoFloorError("the walkable floor polygon is degenerate (no triangles)")
    return np.asarray(out["vertices"], np.float64), np.asarray(out["triangles"], np.int32), np.asarray(out["neighbors"], np.int32)


# ---------------------------------------------------------------- the NavMesh


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


@dataclass
class NavMesh:
    """Triangulated walkable floor in world x,z at height floor_y (the agent's centre may be anywhere inside)."""

    vertices: np.ndarray
    """(V, 2) float64 x,z."""
    triangles: np.ndarray
    """(T, 3) int32, counter-clockwise in (x, z)."""
    adjacency: np.ndarray
    """(T, 3) int32: triangle across the edge opposite vertex k, -1 on the boundary."""
    rings: list[np.ndarray]
    """Boundary rings (K, 2): counter-clockwise outer rings and clockwise holes."""
    floor_y: float
    """Floor height in the world frame (up = -Y, so the camera height is floor_y - camera y)."""
    agent: dict = field(default_factory=dict)
    """agent_radius_m, agent_height_m, step_height_m, band_top_m used to build it."""
    info: dict = field(default_factory=dict)
    """Build facts (cell size, camera on NavMesh, timings...)."""
    grid: FloorGrid | None = field(default=None, repr=False)
    """The heightfield it was built from (only after build_navmesh, not stored on disk)."""

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, np.float64)
        self.triangles = np.asarray(self.triangles, np.int32)
        self.adjacency = np.asarray(self.adjacency, np.int32)
        self.rings = [np.asarray(r, np.float64) for r in self.rings]
        self._segs = _ring_segments(self.rings)
        tri = self.vertices[self.triangles]
        self._tri = tri
        self._centroids = tri.mean(axis=1)
        self._tri_area = 0.5 * _cross(tri[:, 0], tri[:, 1], tri[:, 2])

    # -- geometry queries

    @property
    def area(self) -> float:
        return float(self._tri_area.sum())

    @property
    def segments(self) -> np.ndarray:
        """Boundary edges (S, 2, 2)."""
        return self._segs

    def polygons(self) -> list[dict]:
        """Outer rings with the holes inside them: [{"outer": (K, 2), "holes": [(K, 2), ...]}]."""
        outers = [r for r in self.rings if _ring_area(r) > 0]
        holes = [r for r in self.rings if _ring_area(r) <= 0]
        out = [{"outer": o, "holes": []} for o in outers]
        for h in holes:
            for k, o in enumerate(outers):
                if _even_odd(h[:1], _ring_segments([o]))[0]:
                    out[k]["holes"].append(h)
                    break
        return out

    def contains(self, xz: np.ndarray) -> np.ndarray:
        """Points (N, 2) x,z -> (N,) bool, inside the walkable area (even-odd rule on the boundary rings)."""
        return _even_odd(_check_xz(xz), self._segs)

    def clearance(self, xz: np.ndarray) -> np.ndarray:
        """Signed distance (N,) of points (N, 2) to the NavMesh boundary: positive inside, negative outside."""
        xz = _check_xz(xz)
        d = _segment_distance(xz, self._segs)
        return np.where(self.contains(xz), d, -d)

    def locate(self, xz: np.ndarray, eps: float = 1e-9, chunk: int = 1024) -> np.ndarray:
        """Index (N,) of the triangle containing each point (N, 2), -1 outside."""
        xz = _check_xz(xz)
        out = np.full(len(xz), -1, np.int64)
        a, b, c = self._tri[:, 0], self._tri[:, 1], self._tri[:, 2]
        for s in range(0, len(xz), chunk):
            p = xz[s : s + chunk, None, :]
            inside = (_cross(a, b, p) >= -eps) & (_cross(b, c, p) >= -eps) & (_cross(c, a, p) >= -eps)
            hit = inside.any(axis=1)
            out[s : s + chunk] = np.where(hit, inside.argmax(axis=1), -1)
        return out

    def closest_point(self, xz: np.ndarray) -> np.ndarray:
        """Nearest point (N, 2) on the NavMesh (the point itself when inside), nudged 1 mm inside."""
        xz = _check_xz(xz)
        out = xz.copy()
        outside = ~self.contains(xz)
        if outside.any():
            a, ab = self._segs[:, 0], self._segs[:, 1] - self._segs[:, 0]
            p = xz[outside][:, None, :]
            t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab**2).sum(1), 1e-30), 0, 1)
            q = a + t[..., None] * ab
            k = ((q - p) ** 2).sum(-1).argmin(axis=1)
            q = q[np.arange(len(k)), k]
            tri = self.locate(q, eps=1e-7)
            tri = np.where(tri >= 0, tri, 0)
            out[outside] = q + 1e-3 * _unit(self._centroids[tri] - q)
        return out

    def blocked(self, a: np.ndarray, b: np.ndarray, chunk: int = 512) -> np.ndarray:
        """Whether each segment a[k] -> b[k] (N, 2) leaves the NavMesh -> (N,) bool.

        Blocked when the boundary meets the segment anywhere but at its end points (crossing or touching a
        boundary vertex) or its midpoint lies outside; ends may lie on the boundary, and segments may run along it.
        """
        a, b = _check_xz(a), _check_xz(b)
        out = np.zeros(len(a), bool)
        s0, s1 = self._segs[None, :, 0], self._segs[None, :, 1]
        for s in range(0, len(a), chunk):
            p, q = a[s : s + chunk, None], b[s : s + chunk, None]
            d1, d2 = _cross(p, q, s0), _cross(p, q, s1)
            d3, d4 = _cross(s0, s1, p), _cross(s0, s1, q)
            out[s : s + chunk] = ((d1 * d2 <= 0) & (d3 * d4 < 0)).any(axis=1)
        mid = 0.5 * (a[~out] + b[~out])
        out[~out] = self.clearance(mid) < -1e-9  # on the boundary counts as inside
        return out

    def segment_inside(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Whether each segment a[k] -> b[k] (N, 2) lies inside the NavMesh (ends inside, never leaving it)."""
        a, b = _check_xz(a), _check_xz(b)
        return self.contains(a) & self.contains(b) & ~self.blocked(a, b)

    def polyline_inside(self, pts: np.ndarray) -> np.ndarray:
        """(K - 1,) bool per segment of a polyline (K, 2)."""
        pts = _check_xz(pts)
        return self.segment_inside(pts[:-1], pts[1:])

    def ray_reach(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance (M,) from an inside point along unit directions (M, 2) to the first boundary crossing."""
        o = np.asarray(origin, np.float64).reshape(2)
        d = np.asarray(dirs, np.float64).reshape(-1, 2)
        a, e = self._segs[:, 0], self._segs[:, 1] - self._segs[:, 0]
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
        w = a[None] - o
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / denom
            u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / denom
        hit = (np.abs(denom) > 1e-15) & (t >= 0) & (u >= 0) & (u <= 1)
        return np.where(hit, t, np.inf).min(axis=1)

    def sample_points(self, n: int, rng: np.random.Generator | int | None = None, min_clearance: float = 0.0) -> np.ndarray:
        """n points (n, 2) uniformly over the area, optionally at least min_clearance from the boundary."""
        rng = np.random.default_rng(rng)
        out = np.zeros((0, 2))
        p = self._tri_area / self._tri_area.sum()
        for _ in range(50):
            m = max(2 * (n - len(out)), 16)
            t = rng.choice(len(p), size=m, p=p)
            r1, r2 = np.sqrt(rng.random(m)), rng.random(m)
            tri = self._tri[t]
            pts = (1 - r1)[:, None] * tri[:, 0] + (r1 * (1 - r2))[:, None] * tri[:, 1] + (r1 * r2)[:, None] * tri[:, 2]
            if min_clearance > 0:
                pts = pts[_segment_distance(pts, self._segs) >= min_clearance]
            out = np.concatenate([out, pts])
            if len(out) >= n:
                return out[:n]
        raise ValueError(f"could not sample {n} points with clearance >= {min_clearance} m (NavMesh too narrow)")

    def offset(self, delta_m: float, keep_xz: np.ndarray | None = None) -> NavMesh:
        """A new NavMesh grown (delta > 0) or shrunk (delta < 0) exactly (manifold3d offset, round joins).

        Shrinking can split it; keep_xz (2,) keeps only the piece containing (or nearest to) that point.
        """
        from manifold3d import JoinType

        cs = cross_section(self.rings).offset(delta_m, JoinType.Round, circular_segments=16)
        if cs.is_empty() or cs.area() <= 0:
            raise NoFloorError(f"nothing is left of the NavMesh after offsetting by {delta_m} m")
        if keep_xz is None:
            rings = [np.asarray(r, np.float64) for r in cs.to_polygons()]
        else:
            rings = _pick_component(cs, np.asarray(keep_xz, np.float64).reshape(2))[0]
        v, t, adj = triangulate_rings(rings, self.info.get("max_triangle_area_m2", 0.25))
        return NavMesh(v, t, adj, rings, self.floor_y, dict(self.agent), {**self.info, "offset_m": delta_m})

    # -- path finding

    def path(self, a_xz: np.ndarray, b_xz: np.ndarray) -> np.ndarray:
        """Shortest path (K, 2) from a to b inside the NavMesh: A* over triangle adjacency + funnel string pulling.

        Raises ValueError when an end point lies outside or the two are not connected.
        """
        a = np.asarray(a_xz, np.float64).reshape(2)
        b = np.asarray(b_xz, np.float64).reshape(2)
        ta, tb = self.locate(np.stack([a, b]))
        if ta < 0 or tb < 0:
            bad = "start" if ta < 0 else "goal"
            raise ValueError(f"path {bad} {(a if ta < 0 else b).round(3).tolist()} lies outside the NavMesh")
        corridor = self._astar(int(ta), int(tb), b)
        if corridor is None:
            raise ValueError(f"no path on the NavMesh from {a.round(3).tolist()} to {b.round(3).tolist()}")
        return self._shortcut(self._funnel(corridor, a, b))

    def _shortcut(self, pts: np.ndarray) -> np.ndarray:
        """Drop polyline vertices while the direct segment stays inside (A* corridors need not be the shortest)."""
        out = [0]
        while out[-1] < len(pts) - 1:
            i = out[-1]
            js = np.arange(i + 1, len(pts))
            ok = ~self.blocked(np.repeat(pts[i][None], len(js), 0), pts[js])
            out.append(int(js[np.flatnonzero(ok)].max()) if ok.any() else i + 1)
        return pts[out]

    def _astar(self, start: int, goal: int, goal_xz: np.ndarray) -> list[int] | None:
        c = self._centroids
        g = {start: 0.0}
        parent = {start: -1}
        heap = [(float(np.linalg.norm(c[start] - goal_xz)), start)]
        closed = set()
        while heap:
            _, t = heapq.heappop(heap)
            if t == goal:
                out = [t]
                while parent[out[-1]] >= 0:
                    out.append(parent[out[-1]])
                return out[::-1]
            if t in closed:
                continue
            closed.add(t)
            for nb in self.adjacency[t]:
                nb = int(nb)
                if nb < 0 or nb in closed:
                    continue
                ng = g[t] + float(np.linalg.norm(c[nb] - c[t]))
                if ng < g.get(nb, np.inf):
                    g[nb] = ng
                    parent[nb] = t
                    heapq.heappush(heap, (ng + float(np.linalg.norm(c[nb] - goal_xz)), nb))
        return None

    def _funnel(self, corridor: list[int], a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Simple stupid funnel algorithm (Mononen) over the portals of a triangle corridor."""
        portals = [(a, a)]
        for t0, t1 in zip(corridor[:-1], corridor[1:]):
            k = int(np.flatnonzero(self.adjacency[t0] == t1)[0])
            tri = self.triangles[t0]
            right = self.vertices[tri[(k + 1) % 3]]
            left = self.vertices[tri[(k + 2) % 3]]
            portals.append((left, right))
        portals.append((b, b))

        def area2(p, q, r):  # > 0 when r is clockwise (to the right) of p -> q
            return (r[0] - p[0]) * (q[1] - p[1]) - (q[0] - p[0]) * (r[1] - p[1])

        def same(p, q):
            return float(np.sum((p - q) ** 2)) < 1e-18

        pts = [a]
        apex = left = right = a
        apex_i = left_i = right_i = 0
        i = 1
        while i < len(portals):
            pl, pr = portals[i]
            if area2(apex, right, pr) <= 0.0:
                if same(apex, right) or area2(apex, left, pr) > 0.0:
                    right, right_i = pr, i
                else:
                    pts.append(left)
                    apex, apex_i = left, left_i
                    left = right = apex
                    left_i = right_i = apex_i
                    i = apex_i + 1
                    continue
            if area2(apex, left, pl) >= 0.0:
                if same(apex, left) or area2(apex, right, pl) < 0.0:
                    left, left_i = pl, i
                else:
                    pts.append(right)
                    apex, apex_i = right, right_i
                    left = right = apex
                    left_i = right_i = apex_i
                    i = apex_i + 1
                    continue
            i += 1
        if not same(pts[-1], b):
            pts.append(b)
        out = np.asarray(pts)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(out, axis=0), axis=1) > 1e-12])
        return out[keep]

    # -- I/O

    def to_json(self) -> dict:
        return {
            "format_version": FORMAT_VERSION,
            "frame": "canonical (camera of view 0 at the origin; x right, y down, z forward; up = -Y)",
            "floor_y": self.floor_y,
            "agent": self.agent,
            "cell_m": self.info.get("cell_m"),
            "area_m2": self.area,
            "polygons": [
                {"outer": p["outer"].tolist(), "holes": [h.tolist() for h in p["holes"]]} for p in self.polygons()
            ],
            "vertices": self.vertices.tolist(),
            "triangles": self.triangles.tolist(),
            "adjacency": self.adjacency.tolist(),
            "info": self.info,
        }

    def mesh3d(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (V, 3) at y = floor_y, faces (T, 3)) in the world frame, normals up (-Y)."""
        v = np.stack([self.vertices[:, 0], np.full(len(self.vertices), self.floor_y), self.vertices[:, 1]], 1)
        return v, self.triangles.copy()

    def save(self, out_dir: Path, glb: bool = True) -> list[str]:
        """Write navmesh.json, navmesh.obj (world frame) and navmesh.glb (glTF, Y up); returns the file names."""
        import trimesh

        out_dir = Path(out_dir)
        (out_dir / NAVMESH_JSON).write_text(json.dumps(self.to_json()))
        v, f = self.mesh3d()
        lines = ["# PanoWorld NavMesh: walkable floor, world frame (y down, up = -Y), metres"]
        lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
        (out_dir / NAVMESH_OBJ).write_text("\n".join(lines) + "\n")
        names = [NAVMESH_JSON, NAVMESH_OBJ]
        if glb:
            m = trimesh.Trimesh(transform_points(GLTF_FROM_WORLD, v), f, process=False)
            m.visual.face_colors = np.array([60, 200, 90, 160], np.uint8)
            (out_dir / NAVMESH_GLB).write_bytes(m.export(file_type="glb"))
            names.append(NAVMESH_GLB)
        return names


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-30)


def _check_xz(xz: np.ndarray) -> np.ndarray:
    xz = np.asarray(xz, np.float64)
    if xz.ndim == 1 and xz.shape == (2,):
        xz = xz[None]
    if xz.ndim != 2 or xz.shape[1] != 2:
        raise ValueError(f"{xz.shape=} but expected (N, 2) x,z points")
    return xz


def load_navmesh(path: Path | str) -> NavMesh:
    """Read a NavMesh from a navmesh artifact directory or a navmesh.json file."""
    path = Path(path)
    if path.is_dir():
        path = path / NAVMESH_JSON
    try:
        d = json.loads(path.read_text())
        rings = []
        for p in d["polygons"]:
            rings.append(np.asarray(p["outer"], np.float64))
            rings.extend(np.asarray(h, np.float64) for h in p["holes"])
        return NavMesh(
            np.asarray(d["vertices"], np.float64).reshape(-1, 2),
            np.asarray(d["triangles"], np.int32).reshape(-1, 3),
            np.asarray(d["adjacency"], np.int32).reshape(-1, 3),
            rings,
            float(d["floor_y"]),
            dict(d.get("agent", {})),
            dict(d.get("info", {})),
        )
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a readable NavMesh ({type(e).__name__}: {e})") from None


# ---------------------------------------------------------------- building


def build_navmesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    face_valid: np.ndarray | None = None,
    *,
    params: NavMeshParams | None = None,
    camera_xz: tuple[float, float] = (0.0, 0.0),
) -> NavMesh:
    """NavMesh of the walkable floor of a mesh (V, 3) / (F, 3) in the canonical frame (camera at the origin).

    face_valid (F,) False marks stretched triangles (treated as unseen, never floor). Keeps the connected
    walkable region under the camera, or the nearest one (info["camera_on_navmesh"] = False, with the distance).
    Raises NoFloorError when no walkable floor exists.
    """
    params = params or NavMeshParams()
    t0 = time.perf_counter()
    vertices = np.asarray(vertices, np.float32)
    faces = np.asarray(faces, np.int64)
    face_valid = check_mesh(vertices, faces, face_valid)
    timings = {}
    mesh_faces = len(faces)
    vertices, faces, face_valid, stride = downsample_erp_mesh(vertices, faces, face_valid, params.max_erp_height)
    timings["downsample_s"] = time.perf_counter() - t0
    t = time.perf_counter()
    floor_y, floor_area = estimate_floor_y(vertices, faces, face_valid, params=params)
    timings["floor_s"] = time.perf_counter() - t
    t = time.perf_counter()
    grid = floor_grid(vertices, faces, face_valid, floor_y, params=params)
    timings["heightfield_s"] = time.perf_counter() - t
    if not grid.free.any():
        raise NoFloorError(
            f"no floor cell is at least {params.agent_radius_m} m (agent radius) away from obstacles and unseen areas"
        )
    t = time.perf_counter()
    tol = simplify_tolerance_m(params)
    rings = polygons_from_mask(grid.free, grid, tol)
    if not rings:
        raise NoFloorError("the eroded walkable floor has no polygon")
    cam = np.asarray(camera_xz, np.float64)
    comp_rings, on_mesh, cam_dist = _pick_component(cross_section(rings), cam)
    timings["polygons_s"] = time.perf_counter() - t
    t = time.perf_counter()
    v, tri, adj = triangulate_rings(comp_rings, params.max_triangle_area_m2)
    timings["triangulate_s"] = time.perf_counter() - t
    agent = {
        "agent_radius_m": params.agent_radius_m,
        "agent_height_m": params.agent_height_m,
        "step_height_m": params.step_height_m,
        "band_top_m": band_top(floor_y, params),
    }
    info = {
        "cell_m": params.cell_m,
        "camera_height_m": floor_y,
        "floor_area_seen_m2": float(grid.walkable.sum() * params.cell_m**2),
        "floor_histogram_peak_m2": floor_area,
        "erosion_m": erosion_m(params),
        "simplify_m": tol,
        "max_triangle_area_m2": params.max_triangle_area_m2,
        "grid_shape": list(grid.free.shape),
        "camera_on_navmesh": on_mesh,
        "camera_distance_to_navmesh_m": cam_dist,
        "mesh_faces": int(mesh_faces),
        "erp_downsample": stride,
        "faces_used": int(len(faces)),
        "timings_s": {**timings, "total_s": time.perf_counter() - t0},
    }
    return NavMesh(v, tri, adj, comp_rings, floor_y, agent, info, grid)

