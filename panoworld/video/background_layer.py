"""The warp-inpaint background layer: a 3D surface behind depth edges, coloured, relit and laid out for hidden walls."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numba import njit

from panoworld.geometry.erp_mesh import ErpMesh, grid_faces
from panoworld.geometry.raycast import Raycaster
from panoworld.room.layout_columns import ROOM_TOL
from panoworld.video.erp_fill import erp_gaussian_blur, erp_inpaint

if TYPE_CHECKING:
    from panoworld.room.plane_colors import FloorBeyond


@dataclass
class BackgroundLayer:
    """Surface synthesized behind foreground occluders of the source view, plus the source mesh's valid faces.

    `vertices`/`faces`/`colors` form the fill mesh (canonical frame): the valid faces of the source mesh followed by
    the layer faces; `layer_faces` counts the latter. `synthesized` marks the source grid pixels (h, w) that got a
    background vertex.
    """

    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int32
    colors: np.ndarray  # (V, 3) uint8
    layer_faces: int
    synthesized: np.ndarray  # (h, w) bool
    layer_depth: np.ndarray  # (h, w) float32, background depth at synthesized pixels, 0 elsewhere
    built: Raycaster | None = field(default=None, repr=False)  # one already built over these vertices and faces
    floor_map: FloorBeyond | None = field(default=None, repr=False)  # plane_colors: for the frames' 2D-filled pixels

    def raycaster(self) -> Raycaster:
        return self.built if self.built is not None else Raycaster(self.vertices, self.faces)


def erp_grid_shape(mesh: ErpMesh) -> tuple[int, int]:
    """(h, w) of the ERP vertex grid of a mesh built by mesh.erp_mesh_from_depth (h * w grid vertices + 2 poles)."""
    n = len(mesh.vertices) - 2
    h = int(round(np.sqrt(max(n, 0) / 2)))
    if h < 2 or 2 * h * h != n:
        raise ValueError(
            f"mesh has {len(mesh.vertices)} vertices: not an ERP grid mesh (h * 2h grid vertices + 2 poles) as written "
            "by the mesh stage"
        )
    return h, 2 * h


def _start(fn, *args, **kwargs) -> Future:
    """fn(*args, **kwargs) started on a thread of its own (numpy and OpenCV release the GIL in their loops)."""
    pool = ThreadPoolExecutor(max_workers=1)
    try:
        return pool.submit(fn, *args, **kwargs)
    finally:
        pool.shutdown(wait=False)  # the job runs on; its thread ends with it


def _stretch(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Max over edges of edge length / (nearer depth x angle between the rays), faces (F, 3) into points p (V, 3)."""
    p = np.ascontiguousarray(p, np.float64)
    depth = np.linalg.norm(p, axis=1)
    dirs = p / np.maximum(depth, 1e-12)[:, None]
    out = np.zeros(len(faces), np.float32)
    _stretch_kernel(p, dirs, depth, np.ascontiguousarray(faces, np.int64), out)  # one signature
    return out


@njit(cache=True, nogil=True)
def _stretch_kernel(p, dirs, depth, faces, out):  # pragma: no cover - numba
    """_stretch per face, numpy's arithmetic in numpy's order (tests/test_inpaint.py holds the numpy oracle)."""
    for f in range(faces.shape[0]):
        for e in range(3):
            a, b = faces[f, e], faces[f, (e + 1) % 3]
            x, y, z = p[a, 0] - p[b, 0], p[a, 1] - p[b, 1], p[a, 2] - p[b, 2]
            length = np.sqrt((x * x + y * y) + z * z)  # np.linalg.norm's order
            x, y, z = dirs[a, 0] - dirs[b, 0], dirs[a, 1] - dirs[b, 1], dirs[a, 2] - dirs[b, 2]
            chord = np.sqrt((x * x + y * y) + z * z)
            r = np.float32(length / max(min(depth[a], depth[b]) * chord, 1e-12))
            if r > out[f]:
                out[f] = r


def _surface_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals (h, w, 3) of an ERP grid of points (h, w, 3) from one-sided differences, each taken towards the
    neighbour (per axis, columns wrapped) whose depth is closer, so normals at depth edges follow their own surface."""
    depth = np.linalg.norm(points, axis=-1)

    def tangent(axis: int) -> np.ndarray:
        if axis == 1:
            nxt, prv = np.roll(points, -1, axis=1), np.roll(points, 1, axis=1)
            dn, dp = np.roll(depth, -1, axis=1), np.roll(depth, 1, axis=1)
        else:
            nxt = np.concatenate([points[1:], points[-1:]])
            prv = np.concatenate([points[:1], points[:-1]])
            dn = np.concatenate([depth[1:], depth[-1:] + np.inf])
            dp = np.concatenate([depth[:1] + np.inf, depth[:-1]])
        use_next = np.abs(dn - depth) <= np.abs(dp - depth)
        return np.where(use_next[..., None], nxt - points, points - prv)

    n = np.cross(tangent(0), tangent(1))
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def _grow_into_foreground(
    points: np.ndarray, seeds: np.ndarray, seed_mid: np.ndarray, seed_band: np.ndarray, margin: float,
    layout: tuple[float, ...] = (),
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Breadth-first growth (8-neighbours, columns wrapped) from background edge pixels seeds (h, w) of the ERP grid
    of points (h, w, 3) into the pixels in front of them: a pixel joins when its depth is below the mean `mid` depth
    of the pixels reaching it.

    Returns steps (h, w) (inf where never reached), reach (h, w), the band of the seeds that reached the pixel
    (growth stops after 2 * band + margin + 2 steps), and the background depth (h, w): the pixel's ray cut with the
    tangent plane of the seed it came from, or, where that ray grazes the plane, the seeds' geometric mean depth;
    never beyond the horizontal planes y = c of layout (the floor's and the ceiling's heights, y down); and the flat
    index (h, w) of that seed (-1 where never reached).
    """
    h, w = points.shape[:2]
    pts = points.reshape(-1, 3)
    d = np.linalg.norm(pts, axis=1)
    steps = np.full(h * w, np.inf)
    reach = np.zeros(h * w)
    mid = seed_mid.reshape(-1).copy()
    log_bg = np.log(np.where(d > 0, d, 1.0))
    origin = np.full(h * w, -1, np.int64)
    normal = _surface_normals(points).reshape(-1, 3)
    plane = np.concatenate([normal, (normal * pts).sum(axis=1, keepdims=True)], axis=1)  # n . x = c
    front = np.flatnonzero(seeds.reshape(-1))
    steps[front] = 0
    origin[front] = front
    reach[front] = seed_band.reshape(-1)[front]
    offsets = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
    k = 0
    while len(front):
        k += 1
        fi, fj = np.divmod(front, w)
        src, cand = [], []
        for di, dj in offsets:
            ni = fi + di
            ok = (ni >= 0) & (ni < h)
            src.append(front[ok])
            cand.append(ni[ok] * w + (fj[ok] + dj) % w)
        src = np.concatenate(src)
        cand = np.concatenate(cand)
        ok = ~np.isfinite(steps[cand]) & (d[cand] > 0) & (d[cand] < mid[src]) & (k <= 2 * reach[src] + margin + 2)
        src, cand = src[ok], cand[ok]
        if not len(cand):
            break
        front, first, inv = np.unique(cand, return_index=True, return_inverse=True)
        count = np.bincount(inv)
        mid[front] = np.bincount(inv, mid[src]) / count
        log_bg[front] = np.bincount(inv, log_bg[src]) / count
        origin[front] = origin[src[first]]
        plane[front] = plane[src[first]]
        reach[front] = np.zeros(len(front))
        np.maximum.at(reach, front[inv], reach[src])
        steps[front] = k
    bg = np.exp(log_bg)
    dirs = pts / np.maximum(d, 1e-12)[:, None]
    cos = (plane[:, :3] * dirs).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = plane[:, 3] / cos
    on_plane = (np.abs(cos) > 0.1) & (t > 0.5 * bg) & (t < 2.0 * bg)
    bg = np.where(on_plane, t, bg)
    for c in layout:  # the horizontal planes y = c bound every hidden surface: nothing lies below the floor
        with np.errstate(divide="ignore", invalid="ignore"):
            t = c / dirs[:, 1]
        bg = np.where((np.abs(dirs[:, 1]) > 0.05) & (t > 0), np.minimum(bg, t), bg)
    return steps.reshape(h, w), reach.reshape(h, w), bg.reshape(h, w).astype(np.float32), origin.reshape(h, w)


def floor_ceiling(depth: np.ndarray, valid: np.ndarray) -> tuple[float, ...]:
    """The heights y (canonical frame, y down) of the floor and ceiling planes found in an ERP depth map (H, W)
    (panoworld.room.floor.fit_planes), those found only."""
    from panoworld.room.floor import fit_planes

    floor_m, ceiling_m = fit_planes(depth, valid)
    return tuple(c for c in (floor_m, None if ceiling_m is None else -ceiling_m) if c is not None)


def build_background_layer(
    mesh: ErpMesh,
    max_translation: float,
    *,
    max_band_deg: float = 45.0,
    inpaint_radius: float = 3.0,
    max_edge_ratio: float = 12.0,
    side_depth_m: float = 0.0,
    edge_depth_ratio: float = 0.75,
    color_sigma_px: float = 0.0,
    layout_planes: bool = False,
    wall_layout: bool = False,
    shadow_ambient: float = 1.0,
    plane_colors: bool = True,
    next_room_colors: bool = False,
    ray_caster: bool = False,
) -> BackgroundLayer:
    """Extend the far side of every depth discontinuity of the source view behind its foreground occluder, and
    (side_depth_m > 0) the occluder's own surface back from its silhouette (occluder_sides).

    The discontinuities are the grid faces stretched by more than max_edge_ratio pixel footprints (the mesh stage's
    rule, whatever it did with them): their far vertices are background edge pixels where the nearest foreground
    across the edge is nearer than edge_depth_ratio x their depth (smaller steps, such as shelves in front of the
    books or a cabinet against the wall, are left to the 2D fill of the far side). From them a breadth-first
    growth enters the occluder (pixels nearer than the midpoint of the edge's near and far depth) for as many pixels
    as a camera moving at most `max_translation` metres from the source can uncover, max_translation *
    (1 / d_near - 1 / d_far) radians (capped at max_band_deg). Each pixel reached gets a background vertex on its
    ray: depth from the tangent plane of the background at the edge pixel it came from, colour inpainted (Telea,
    seam-aware) with the occluder masked, so both continue the background only; color_sigma_px > 0: instead the
    visible background's Gaussian-weighted mean colour of that sigma (grid pixels; layer_mean_color), no streaks
    across wide bands. layout_planes: no background depth beyond the floor and ceiling planes fitted to the source
    depth (floor_ceiling). wall_layout: the room's shell from the source view (panoworld.room.layout_columns: one wall
    per column, interpolated behind tall objects, and the floor and ceiling planes); pixels grown from an edge pixel
    on the shell take the shell's depth, and where that is a wall, the wall's colour seen at the same height beside
    the occluder (wall_layer). shadow_ambient < 1: the layer's colour relit (relight_layer). The side faces
    (side_depth_m > 0) come last among the layer faces. plane_colors: layer points on the floor plane beyond the
    room's shell (the next room through a doorway) take the colour of a top-down map of the floor seen beyond it
    (panoworld.room.plane_colors, before any relighting), and the layer keeps the map for the frames' 2D-filled pixels
    (WarpInpainter). next_room_colors: likewise, points beyond the shell between the floor and the ceiling take the
    colour of the next room's walls seen beyond it (and on the ceiling plane the ceiling's, plane_colors.NEXT_CEILING).
    ray_caster: the layer comes with its fill mesh's ray caster built (BackgroundLayer.built), while the colours are
    inpainted.
    """
    h, w = erp_grid_shape(mesh)
    n = h * w
    p = mesh.vertices[:n].astype(np.float64)
    depth = np.linalg.norm(p, axis=1).reshape(h, w)
    valid = depth > 0
    empty = np.zeros((h, w), bool)
    main_faces = mesh.faces[mesh.face_valid]
    none = BackgroundLayer(mesh.vertices, main_faces, mesh.colors, 0, empty, np.zeros((h, w), np.float32))
    if max_translation <= 0:
        return none

    # Background edge pixels: far vertices of stretched grid faces, with the nearest foreground depth across the edge.
    all_grid = grid_faces(h, w)
    grid = all_grid[valid.reshape(-1)[all_grid].all(axis=1)]
    bad = grid[_stretch(p, grid) > max_edge_ratio]
    if not len(bad):
        return none
    d = depth.reshape(-1)
    fd = d[bad]
    dmin, dmax = fd.min(axis=1), fd.max(axis=1)
    far = fd >= 0.5 * (dmin + dmax)[:, None]
    near_of = np.full(n, np.inf)
    np.minimum.at(near_of, bad[far], np.repeat(dmin, 3).reshape(-1, 3)[far])
    edge = (near_of < d * edge_depth_ratio).reshape(h, w)
    if not edge.any():
        return none
    near_of = near_of.reshape(h, w)
    floor_job = None
    if plane_colors or next_room_colors:  # from the source view alone: a thread works it out while the layer grows
        from panoworld.room.plane_colors import floor_beyond

        floor_job = _start(floor_beyond, p.reshape(h, w, 3), mesh.colors[:n].reshape(h, w, 3), valid,
                           floor=plane_colors, walls_ceiling=next_room_colors)

    px_angle = 2 * np.pi / w
    lat = (0.5 - (np.arange(h) + 0.5) / h) * np.pi
    cos_lat = np.maximum(np.cos(lat), 0.2)[:, None]  # a longitude step spans cos(lat) of a pixel's angle
    with np.errstate(divide="ignore"):
        parallax = max_translation * (1.0 / near_of - 1.0 / depth)
    band = np.where(edge, np.minimum(parallax, np.deg2rad(max_band_deg)) / px_angle / cos_lat * 1.2 + 2, 0.0)
    planes = floor_ceiling(depth, valid) if layout_planes or wall_layout else ()
    steps, reach, bg_depth, origin = _grow_into_foreground(
        p.reshape(h, w, 3), edge, 0.5 * (depth + near_of), band, inpaint_radius, planes if layout_planes else (),
    )
    hide = (steps <= 2 * reach + inpaint_radius + 2) | ~valid  # the occluder, masked for the colour inpainting
    wall = wall_layer(p.reshape(h, w, 3), mesh.colors[:n].reshape(h, w, 3), valid, planes, steps, origin, hide
                      ) if wall_layout else None
    if wall is not None:
        bg_depth = np.where(np.isfinite(wall[0]), wall[0], bg_depth).astype(np.float32)
    synth = (steps <= reach) & (bg_depth > depth * 1.02)
    src_rgb = mesh.colors[:n].reshape(h, w, 3)
    # the colours are inpainted by a thread (OpenCV releases the GIL) while the layer's geometry and ray caster are built
    if color_sigma_px > 0:
        color_job = _start(layer_mean_color, src_rgb, hide, color_sigma_px)
    else:
        color_job = _start(erp_inpaint, src_rgb, hide, radius=inpaint_radius)

    # Layer mesh: grid faces over synthesized pixels and the real background pixels next to them.
    s_flat = synth.reshape(-1)
    idx_new = np.full(n, -1, np.int64)
    idx_new[s_flat] = len(mesh.vertices) + np.arange(int(s_flat.sum()))
    usable = s_flat | valid.reshape(-1)
    grid = all_grid[usable[all_grid].all(axis=1) & s_flat[all_grid].any(axis=1)]
    dirs = p[s_flat] / d[s_flat, None]
    vertices = np.concatenate([mesh.vertices, (dirs * bg_depth.reshape(-1)[s_flat, None]).astype(np.float32)])
    faces = np.where(s_flat[grid], idx_new[grid], grid).astype(np.int32)
    faces = faces[_stretch(vertices.astype(np.float64), faces) <= max_edge_ratio]
    sides = occluder_sides(p.reshape(h, w, 3), mesh.colors[:n], bad, side_depth_m, len(vertices)
                           ) if side_depth_m > 0 else None
    fill_v = vertices if sides is None else np.concatenate([vertices, sides[0].astype(np.float32)])
    fill_f = np.concatenate([main_faces, faces, *([] if sides is None else [sides[2]])]).astype(np.int32)
    del all_grid, grid, near_of, parallax, band, steps, reach, origin, idx_new  # the ray caster's build adds ~250 MB
    built = Raycaster(fill_v, fill_f).build() if ray_caster and shadow_ambient >= 1 else None
    bg_color = color_job.result()
    floor_map = None if floor_job is None else floor_job.result()
    if wall is not None:
        bg_color = np.where(wall[2][..., None], wall[1], bg_color)
    colors = np.concatenate([mesh.colors, bg_color.reshape(-1, 3)[s_flat]])
    if floor_map is not None:
        colors[len(mesh.vertices):] = floor_map.paint(vertices[len(mesh.vertices):].astype(np.float64),
                                                   colors[len(mesh.vertices):])[0]
    if shadow_ambient < 1:
        vertices = vertices.astype(np.float32)
        shadows = Raycaster(vertices, np.concatenate([main_faces, faces]).astype(np.int32))
        colors[len(mesh.vertices):] = relight_layer(
            p.reshape(h, w, 3), src_rgb, valid, hide, synth, vertices[len(mesh.vertices):],
            colors[len(mesh.vertices):], shadows, shadow_ambient, inpaint_radius)
        built = shadows if sides is None else None
    if sides is not None:
        colors = np.concatenate([colors, sides[1]])
    return BackgroundLayer(
        fill_v.astype(np.float32),
        fill_f,
        colors.astype(np.uint8),
        len(fill_f) - len(main_faces),
        synth,
        np.where(synth, bg_depth, 0.0).astype(np.float32),
        built,
        floor_map,
    )


def relight_layer(points: np.ndarray, rgb: np.ndarray, valid: np.ndarray, hide: np.ndarray, synth: np.ndarray,
                  layer_points: np.ndarray, layer_rgb: np.ndarray, rc: Raycaster, ambient: float, radius: float
                  ) -> np.ndarray:
    """The background layer's colours layer_rgb (N, 3) at layer_points (N, 3) (the synth (h, w) pixels, in order)
    relit for the source view's ceiling lights (panoworld.room.fill_shadows): the layer's colour comes from the visible
    pixels around the occluder (hide); each point's colour is scaled in linear light by how much more or less of the
    lights reaches it than reached those pixels (shadow rays against the fill mesh rc), with ambient light this share
    of full light. Points beyond the room's walls (panoworld.room.layout_columns' shell; the next room through a doorway,
    lit by lights the source view does not see) keep their colour. Unchanged without lights."""
    from panoworld.room.fill_shadows import ceiling_lights, lit_fraction, shadow_gain
    from panoworld.room.floor import fit_planes
    from panoworld.room.layout_columns import shell_depth, wall_columns
    from panoworld.room.light import apply_gain

    depth = np.linalg.norm(points, axis=-1)
    floor_m, ceiling_m = fit_planes(depth, valid)
    lights, weights = ceiling_lights(points, rgb, valid, None if ceiling_m is None else -ceiling_m)
    if not len(lights) or not len(layer_points) or floor_m is None:
        return layer_rgb
    dirs = points / np.maximum(depth, 1e-12)[..., None]
    shell = shell_depth(wall_columns(points, valid, floor_m, -ceiling_m), dirs)[0][synth]
    inside = ~(np.linalg.norm(layer_points, axis=1) > ROOM_TOL * shell)  # unknown shell (nan): inside
    rim = cv2.dilate(hide.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=int(np.ceil(radius)) + 1) > 0
    rim &= valid & ~hide
    lit_src = np.ones(valid.shape, np.float32)
    lit_src[rim] = lit_fraction(rc, points[rim], lights, weights)
    donor = erp_inpaint(lit_src, hide, radius=radius)[synth]
    here = lit_fraction(rc, layer_points, lights, weights)
    return np.where(inside[:, None], apply_gain(layer_rgb, shadow_gain(here, donor, ambient).astype(np.float32)), layer_rgb)


def wall_layer(points: np.ndarray, rgb: np.ndarray, valid: np.ndarray, planes: tuple[float, ...], steps: np.ndarray,
               origin: np.ndarray, hide: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The background layer on the room's shell (build_background_layer's wall_layout): points (h, w, 3), rgb (h, w, 3)
    and valid (h, w) of the source grid; planes the floor's and ceiling's heights (floor_ceiling, both needed);
    steps / origin from _grow_into_foreground (the foreground: steps >= 1); hide: the pixels not to take colour from.

    Returns the shell's depth (h, w) at the grown pixels in front of it whose seed lies on the shell (within 5 %; inf
    elsewhere: pixels on the shell themselves keep their layer, e.g. a wall beside a doorway hiding the next room),
    the walls' colour (h, w, 3) there (layout_columns.wall_colors: seen wall pixels at the same height beside the
    occluder) and where that colour applies (h, w) bool (shell pixels on a wall with a known colour); None without
    both planes."""
    from panoworld.room.layout_columns import height_bin, shell_depth, wall_colors, wall_columns

    floor_y = [c for c in planes if c > 0]
    ceil_y = [c for c in planes if c < 0]
    if not floor_y or not ceil_y:
        return None
    h, w = valid.shape
    occluder = np.isfinite(steps) & (steps >= 1)
    walls = wall_columns(points, valid, floor_y[0], ceil_y[0])
    d = np.linalg.norm(points, axis=-1)
    dirs = points / np.maximum(d, 1e-12)[..., None]
    shell, on_wall = shell_depth(walls, dirs)
    seed_on_shell = (valid & (np.abs(d - shell) < 0.05 * shell)).reshape(-1)
    grown = origin.reshape(-1) >= 0
    use = np.zeros(h * w, bool)
    use[grown] = seed_on_shell[origin.reshape(-1)[grown]]
    use = use.reshape(h, w) & occluder & np.isfinite(shell) & (shell > d * 1.02)  # the pixel is in front of the shell
    bins = max(h // 4, 8)  # a bin about as tall as a source pixel row on a wall ~4 m away
    tex, known = wall_colors(walls, points, rgb, valid, bins)
    k = height_bin(walls, shell * dirs[..., 1], bins)
    cols = np.broadcast_to(np.arange(w), (h, w))
    color = np.clip(np.rint(tex[k, cols]), 0, 255).astype(np.uint8)
    paint = use & on_wall & known[k, cols]
    return np.where(use, shell, np.inf), color, paint


def layer_mean_color(rgb: np.ndarray, hide: np.ndarray, sigma: float) -> np.ndarray:
    """rgb (h, w, 3) uint8 with the hide (h, w) pixels replaced by the Gaussian-weighted (sigma pixels, seam-aware)
    mean colour of the pixels not hidden; where none lies within reach, the same at 2x, 4x, ... coarser scales
    (area-downsampled, so the wider means stay cheap)."""
    h, w = hide.shape
    known = (~hide).astype(np.float32)
    col, wt = rgb.astype(np.float32) * known[..., None], known
    out = rgb.astype(np.float32)
    todo = hide.copy()
    scale = 1
    while todo.any():
        hh, ww = wt.shape
        num, den = (erp_gaussian_blur(x, sigma, across_poles=True) for x in (col, wt))
        if scale > 1:
            num, den = (cv2.resize(x, (w, h), interpolation=cv2.INTER_LINEAR) for x in (num, den))
        ok = todo & (den > 1e-3)
        out[ok] = num[ok] / den[ok, None]
        todo &= ~ok
        if min(hh, ww) < 8:
            out[todo] = (col.reshape(-1, 3).sum(0) / max(float(wt.sum()), 1e-6)) if wt.sum() > 0 else 0
            break
        col, wt = (cv2.resize(x, (ww // 2, hh // 2), interpolation=cv2.INTER_AREA) for x in (col, wt))
        scale *= 2
    return np.where(hide[..., None], np.clip(np.rint(out), 0, 255), rgb).astype(np.uint8)


UPRIGHT_COS = 0.5
"""occluder_sides: a silhouette is upright when its surface normal's |cos| with the vertical is below this."""


def occluder_sides(points: np.ndarray, colors: np.ndarray, stretched: np.ndarray, side_depth_m: float, first: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The hidden side of each foreground occluder, guessed as a box's: straight back from its silhouette.

    points (h, w, 3): the source's ERP grid points, colours (h, w, 3); stretched (F, 3): flat grid faces spanning a
    depth discontinuity. Each face's far vertices (depth at least the midpoint of its near and far depth) are
    replaced by the silhouette point across the edge (the face's nearest vertex) moved against its surface normal
    by side_depth_m, or by the distance to the far vertex where that is shorter (an occluder standing against the
    background reaches it), coloured as the silhouette: a sheet from the silhouette straight back, which a camera
    moving around the occluder sees as its side (a cabinet's side between its front face and the wall) instead of
    background colour. Returns the new vertices (M, 3), their colours (M, 3) uint8 and the faces (K, 3) int32
    indexing flat grid vertices and the new vertices numbered from `first`."""
    h, w = points.shape[:2]
    p = points.reshape(-1, 3)
    d = np.linalg.norm(p, axis=1)
    normal = _surface_normals(points).reshape(-1, 3)
    normal *= -np.sign((normal * p).sum(axis=1, keepdims=True) + 1e-12)  # towards the source camera
    fd = d[stretched]
    dmin = fd.min(axis=1)
    far = fd >= 0.5 * (dmin + fd.max(axis=1))[:, None]
    keep = far.any(axis=1) & ~far.all(axis=1)
    f, far, dmin = stretched[keep], far[keep], dmin[keep]
    near_vertex = f[np.arange(len(f)), np.argmin(d[f], axis=1)]
    # only upright silhouettes (a cabinet's side): a sheet behind a top edge would hang over the floor under tables
    upright = np.abs(normal[near_vertex, 1]) < UPRIGHT_COS
    f, far, dmin, near_vertex = f[upright], far[upright], dmin[upright], near_vertex[upright]
    # each far vertex takes the nearest silhouette point across any of its faces
    fv = f[far]
    fn = np.repeat(dmin, far.sum(axis=1))
    src = np.repeat(near_vertex, far.sum(axis=1))
    order = np.lexsort((fn, fv))
    verts, first_of = np.unique(fv[order], return_index=True)
    sil = src[order][first_of]
    length = np.minimum(side_depth_m, np.linalg.norm(p[verts] - p[sil], axis=1))
    new_v = p[sil] - normal[sil] * length[:, None]
    index = np.full(len(p), -1, np.int64)
    index[verts] = first + np.arange(len(verts))
    faces = np.where(far, index[f], f).astype(np.int32)
    return new_v, colors.reshape(-1, 3)[sil].astype(np.uint8), faces
