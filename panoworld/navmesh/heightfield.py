"""Floor height, heightfield by down-cast rays, obstacle band, blind-spot filling and erosion of a scene mesh."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from panoworld.core.errors import InputError, NoFloorError
from panoworld.core.limits import MAX_FLOOR_CELLS
from panoworld.core.params import param
from panoworld.core.shapes import check_shape

MIN_CAMERA_HEIGHT_M = 0.3
"""Horizontal triangles closer than this below the camera are never taken as the floor."""
RIM_WALKABLE_FRACTION = 0.8
"""An unseen region is assumed to be floor only when at least this share of the cells around it is walkable floor."""


@dataclass(kw_only=True)
class NavMeshParams:
    """How the walkable floor is extracted from a scene mesh (world frame, metres, up = -Y)."""

    cell_m: float = param(0.03, ge=0.005, le=0.5)
    """Heightfield cell size in metres (rays are cast down at cell centres)."""
    agent_radius_m: float = param(0.25, ge=0, le=2.0)
    """Agent (camera) radius: the floor is eroded by this distance from every obstacle and unseen cell."""
    agent_height_m: float = param(1.8, gt=0)
    """Top of the obstacle band above the floor; raised to camera height + agent radius when the camera is higher."""
    step_height_m: float = param(0.2, ge=0)
    """Geometry up to this height above the floor is walkable (rugs, thresholds); above it is an obstacle."""
    max_slope_deg: float = param(15.0, ge=0, lt=90)
    """Triangles tilted at most this much from horizontal vote for the floor height."""
    max_range_m: float = param(12.0, gt=0, le=100.0)
    """Only geometry within this horizontal distance from the camera is considered."""
    min_floor_area_m2: float = 0.25
    """Minimum visible floor area (in the winning histogram bin) to accept a floor height; with a bounded snap
    distance (a home's capture points), also the least area of a floor piece that a camera standing on no piece is
    snapped to, when one lies within reach (else the nearest; one panorama keeps the nearest piece and its no-room
    decision)."""
    simplify_m: float = param(0.0, ge=0)
    """Polygon simplification tolerance (approxPolyDP) in metres; 0 = one cell. Compensated by extra erosion."""
    max_triangle_area_m2: float = 0.25
    """Largest NavMesh triangle ('triangle' quality meshing), so A* over triangles gives short corridors."""
    camera_footprint_m: float = param(0.0, ge=0)
    """Unseen floor within this horizontal radius of the camera counts as walkable (tripod / nadir blind spot of
    real captures: the camera stood there); obstacles are never overridden. 0 = only what blind_spot_m decides."""
    blind_spot_m: float = param(1.5, ge=0)
    """Automatic rig blind spot: the unseen region under the camera counts as walkable when it lies within this
    horizontal radius and at least RIM_WALKABLE_FRACTION of the cells around it are walkable floor (the floor is
    seen all around the capture rig). 0 = off."""
    fill_holes_m2: float = 0.25
    """Unseen holes of at most this area surrounded by walkable floor (sensor dropouts, LiDAR gaps) count as
    walkable; a region where rays hit something below the floor (a stairwell) never does. 0 = off."""
    max_erp_height: int = param(192, ge=0)
    """ERP grid meshes (panoworld.geometry.erp_mesh layout) with more rows are re-meshed from every s-th pixel first (speed)."""


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
    assumed: np.ndarray | None = None
    """(Hz, Wx) bool: unseen cells assumed walkable (the rig's blind spot, small dropouts), included in walkable."""
    assumptions: dict = field(default_factory=dict)
    """What was assumed: blind spot area and radius, holes filled (see fill_blind_spots)."""

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
    check_shape("vertices", vertices, "V 3")
    dims = check_shape("faces", faces, "F 3")
    if face_valid is None:
        return np.ones(len(faces), bool)
    face_valid = np.asarray(face_valid, bool)
    check_shape("face_valid", face_valid, "F", dims=dims)
    return face_valid


def estimate_floor_y(
    vertices: np.ndarray, faces: np.ndarray, face_valid: np.ndarray | None = None, *, params: NavMeshParams, bin_m: float = 0.02
) -> tuple[float, float]:
    """Floor height y (world, up = -Y) from an area-weighted histogram of horizontal triangles below the camera.

    The camera is at the origin. Returns (floor_y, floor_area_m2 in the winning bin +- one bin).
    Raises NoFloorError when there is not enough horizontal area below the camera.
    """
    face_valid = check_mesh(vertices, faces, face_valid)
    # Only faces with a vertex more than MIN_CAMERA_HEIGHT_M below the camera can have their centroid there (a fused
    # home holds millions of faces: the geometry of the rest is never computed).
    below = np.flatnonzero(face_valid & (np.asarray(vertices)[:, 1][faces].max(axis=1) > MIN_CAMERA_HEIGHT_M))
    faces = faces[below]
    cen, area, ny = _face_geometry(vertices, faces)
    cand = (
        (ny >= np.cos(np.deg2rad(params.max_slope_deg)))
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
    from panoworld.core.conventions import dir_from_lonlat, erp_lonlat_from_pixel

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
    ERP grid mesh. Depth discontinuities are re-flagged by panoworld.geometry.erp_mesh at the coarse grid.
    """
    from panoworld.geometry.erp_mesh import erp_mesh_from_depth

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
    vertices: np.ndarray, faces: np.ndarray, face_valid: np.ndarray, floor_y: float, *, params: NavMeshParams,
    camera_xz: tuple[float, float] | np.ndarray = (0.0, 0.0),
) -> FloorGrid:
    """Heightfield by rays cast down on a grid + obstacle band marking + erosion by the agent radius.

    camera_xz (2,) or (K, 2): the camera(s) whose blind spot under the rig may be assumed floor (fill_blind_spots).

    Obstacles are cells whose downward ray (from the band top) first hits a face higher than step height, plus
    cells holding vertices or edge samples of valid faces inside the band (thin geometry between ray centres).
    Cells whose ray hits nothing, an invalid face, or a surface below floor - step are unseen (not walkable).
    Free = walkable cells at least agent_radius + one cell diagonal + simplify tolerance from any other cell.
    """
    import cv2

    from panoworld.geometry.raycast import Raycaster

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
    if nx * nz > MAX_FLOOR_CELLS:
        ext = hi - lo
        raise InputError(f"the walkable floor spans {ext[0]:.0f} m x {ext[1]:.0f} m: a NavMesh grid of {nx * nz:,} cells "
                         f"of {cell} m, over the limit of {MAX_FLOOR_CELLS:,}; are the capture points (poses.json) "
                         "of one home? Otherwise raise navmesh.cell_m")
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
    drop = ok_face & (h < -step)

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

    fill_blind_spots(grid, drop, params, camera_xz)
    walk = grid.walkable.copy()
    walk[[0, -1], :] = False
    walk[:, [0, -1]] = False
    dist = cv2.distanceTransform(walk.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * cell
    free = dist >= erosion_m(params)
    free = cv2.morphologyEx(free.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).astype(bool)
    grid.free = free
    return grid


def fill_blind_spots(grid: FloorGrid, drop: np.ndarray, params: NavMeshParams, camera_xz=(0.0, 0.0)) -> dict:
    """Mark unseen regions walkable that can only be floor nobody saw: in place on grid, returns grid.assumptions.

    Candidates are unseen cells that are no obstacle and no drop (drop (Hz, Wx): rays hit below the floor).
    Filled: the 8-connected region of candidates within blind_spot_m of the camera that holds the camera (the
    capture rig hides the floor it stands on; camera_xz (K, 2): under each of several cameras, a home's capture
    points: blind_spot_m2 summed, radius the largest, rim share the smallest), and components of candidates of at most fill_holes_m2 that do not
    touch the grid border; each only when its rim (the cells next to it) is at least RIM_WALKABLE_FRACTION
    walkable floor.
    """
    import cv2

    nz, nx = grid.walkable.shape
    cams = np.asarray(camera_xz, np.float64).reshape(-1, 2)
    xz = grid.xz_of(np.argwhere(np.ones((nz, nx), bool)))
    assumed = np.zeros((nz, nx), bool)
    info = {"blind_spot_m2": 0.0, "blind_spot_radius_m": 0.0, "blind_spot_rim_walkable": None,
            "holes_filled": 0, "holes_filled_m2": 0.0}
    cand = grid.unseen & ~grid.obstacle & ~drop
    n, labels, stats, _ = cv2.connectedComponentsWithStats(cand.astype(np.uint8), connectivity=8)
    if n > 1:
        # Rim cells take the largest neighbouring label (exact in float32 below 2^24 labels).
        near = cv2.dilate(labels.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.int64)
        rim = (labels == 0) & (near > 0)
        rim_total = np.bincount(near[rim], minlength=n)
        rim_walk = np.bincount(near[rim], weights=grid.walkable[rim].astype(np.float64), minlength=n)
        frac = rim_walk / np.maximum(rim_total, 1)
        x, y, w, h = (stats[:, k] for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        inner = (x > 0) & (y > 0) & (x + w < nx) & (y + h < nz)
        ok = inner & (frac >= RIM_WALKABLE_FRACTION)
        ok[0] = False
        area = stats[:, cv2.CC_STAT_AREA] * grid.cell**2
        holes = ok & (area <= params.fill_holes_m2)
        rims = []
        for cam_xz in cams:
            cam = grid.cell_of(cam_xz)[0]
            if not (params.blind_spot_m > 0 and 0 <= cam[0] < nz and 0 <= cam[1] < nx and cand[cam[0], cam[1]]):
                continue
            holes[labels[cam[0], cam[1]]] = False
            # The camera's unseen region cut at blind_spot_m (where it leaks past a wall the rim shows it).
            near_cam = (np.hypot(xz[:, 0] - cam_xz[0], xz[:, 1] - cam_xz[1]) <= params.blind_spot_m).reshape(nz, nx)
            _, spot = cv2.connectedComponents((cand & near_cam).astype(np.uint8), connectivity=8)
            spot = spot == spot[cam[0], cam[1]]
            ring = cv2.dilate(spot.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~spot
            share = float(grid.walkable[ring].mean()) if ring.any() else 0.0
            rims.append(share)
            if share >= RIM_WALKABLE_FRACTION:
                assumed |= spot
                ij = np.argwhere(spot)
                info["blind_spot_m2"] += float(spot.sum() * grid.cell**2)
                info["blind_spot_radius_m"] = max(info["blind_spot_radius_m"], float(
                    np.max(np.linalg.norm(grid.xz_of(ij) - cam_xz, axis=1)) + 0.5 * grid.cell))
        if rims:
            info["blind_spot_rim_walkable"] = min(rims)
        assumed |= holes[labels]
        info.update(holes_filled=int(holes.sum()), holes_filled_m2=float(area[holes].sum()))
    if params.camera_footprint_m > 0:
        for cam_xz in cams:
            d = np.hypot(xz[:, 0] - cam_xz[0], xz[:, 1] - cam_xz[1]).reshape(nz, nx)
            assumed |= (d <= params.camera_footprint_m) & grid.unseen & ~grid.obstacle
    info["assumed_m2"] = float(assumed.sum() * grid.cell**2)
    grid.walkable |= assumed
    grid.unseen &= ~assumed
    grid.assumed = assumed
    grid.assumptions = info
    return info


def simplify_tolerance_m(params: NavMeshParams) -> float:
    return params.simplify_m if params.simplify_m > 0 else params.cell_m


def erosion_m(params: NavMeshParams) -> float:
    """Cell-centre distance kept from non-walkable cells: radius + half a cell diagonal + simplification slack."""
    return params.agent_radius_m + 0.5 * np.sqrt(2.0) * params.cell_m + simplify_tolerance_m(params)

