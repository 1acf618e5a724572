"""Per-pixel Gaussians of the source panorama, and the test of which observations of other frames it already explains."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch
from numba import njit

from panoworld.core.conventions import erp_pixel_from_dir, invert_pose
from panoworld.gaussians.fusion import ContextSource, frame_observations, gaussians_from_cov, voxel_fusion
from panoworld.gaussians.fusion_params import FusionParams, SourcePixelParams
from panoworld.geometry.voxels import bbox_extent
from panoworld.io.gaussian_set import FusionResult, Gaussians, rgb_to_sh_dc


def pole_thinning(height: int, width: int) -> np.ndarray:
    """(H, W) bool: ERP pixels kept when each row keeps every k-th column, k = the largest power of two <= 1 / cos(lat)
    (at most W / 8), so kept pixels are 0.5-1x as wide as tall on the sphere (about 78 % of all pixels)."""
    lat = (np.arange(height) + 0.5) / height * np.pi - np.pi / 2
    k = 2 ** np.floor(np.log2(1.0 / np.maximum(np.cos(lat), 1e-6)))
    k = np.minimum(k, max(width // 8, 1)).astype(int)
    return (np.arange(width)[None, :] % k[:, None]) == 0


def pixel_gaussians(rgb: np.ndarray, depth: np.ndarray, world_from_cam: np.ndarray, params: FusionParams,
                    *, thin_poles: bool = True) -> Gaussians:
    """One Gaussian per valid pixel of an ERP frame (rgb (H, W, 3), depth (H, W) metres, pose (4, 4)).

    Each is the pixel's surface footprint (frame_observations' parallelogram covariance) times params.scale_factor,
    flat along the surface normal (at least min_scale * voxel_size thick); with thin_poles, rows near the poles keep
    every k-th pixel (pole_thinning) with a k times wider footprint along the row.
    """
    h, w = depth.shape
    obs = frame_observations(rgb, depth, world_from_cam, params)
    steps = obs.steps
    if thin_poles:
        keep_px = pole_thinning(h, w).ravel()
        k_row = np.bincount(np.arange(h).repeat(w), weights=1.0 - keep_px, minlength=h)
        k_row = w / np.maximum(w - k_row, 1)  # columns per kept pixel in each row
        sel = keep_px[obs.pixels.numpy()]
        obs = obs.subset(torch.from_numpy(sel))
        k = torch.from_numpy(k_row[obs.pixels.numpy() // w])
        steps = obs.steps.clone()
        steps[:, 0] *= k[:, None]
    cov = torch.einsum("mki,mkj->mij", steps, steps) / 12.0
    return gaussians_from_cov(obs.points, cov, obs.colors, params, max_scale_m=np.inf)


@njit(cache=True, inline="always")
def _cam_point(cam_from_world, points, m):
    """World point m of points (M, 3) in the camera frame, (x, y, z), summed in one fixed order (both lookups')."""
    x = cam_from_world[0, 3]
    y = cam_from_world[1, 3]
    z = cam_from_world[2, 3]
    for k in range(3):
        x += cam_from_world[0, k] * points[m, k]
        y += cam_from_world[1, k] * points[m, k]
        z += cam_from_world[2, k] * points[m, k]
    return x, y, z


@njit(cache=True, nogil=True)
def _source_lookup_exact(points, cam_from_world, depth, dist, d_src):
    """SourceVisibility._lookup fused per point: camera-frame distance and the ERP depth pixel the point falls in (libm's
    atan2; _source_lookup's oracle). Serial: voxel fusion calls it from two frame threads at once (nogil), which a
    parallel kernel would oversubscribe."""
    h, w = depth.shape
    for m in range(points.shape[0]):
        x, y, z = _cam_point(cam_from_world, points, m)
        r = math.sqrt(x * x + y * y + z * z)
        dist[m] = r
        if not r < math.inf:  # NaN or infinite points fall in no pixel
            d_src[m] = math.nan
            continue
        u = (math.atan2(x, z) / (2.0 * math.pi) + 0.5) * w
        v = (0.5 - math.atan2(-y, math.hypot(x, z)) / math.pi) * h
        j = int(math.floor(u)) % w
        i = min(max(int(math.floor(v)), 0), h - 1)
        d_src[m] = depth[i, j]


_ATAN_MARGIN = 1e-9
"""Radians: _fast_atan2 is within 1e-11 of atan2 (a degree-13 odd polynomial after reduction to |t| <= tan(pi/8)), so
a pixel coordinate farther than this from a pixel edge floors the same with either; nearer ones take libm's."""


@njit(cache=True, inline="always", error_model="numpy")  # x / 0 is inf or NaN, not an exception
def _fast_atan2(y, x):
    """atan2 within 1e-11 (a degree-13 odd polynomial after reduction to |t| <= tan(pi/8)), without branches (selects
    only, so the loop calling it vectorises)."""
    ax = abs(x)
    ay = abs(y)
    t = min(ax, ay) / max(ax, ay)
    big = t > 0.41421356237309503
    t = (t - 1.0) / (t + 1.0) if big else t
    t2 = t * t
    p = 0.04556780313367663
    p = p * t2 - 0.08372000195252803
    p = p * t2 + 0.11022372113456373
    p = p * t2 - 0.14279716045782156
    p = p * t2 + 0.19999789656281627
    p = p * t2 - 0.33333330063788086
    p = p * t2 + 0.9999999998526478
    a = (0.25 * math.pi if big else 0.0) + p * t
    a = 0.5 * math.pi - a if ay > ax else a
    a = math.pi - a if x < 0.0 else a
    return -a if y < 0.0 else a


@njit(cache=True, nogil=True, error_model="numpy")
def _source_lookup(points, cam_from_world, depth, dist, d_src):
    """_source_lookup_exact's results, bit for bit, for about half its time: the pixel from _fast_atan2 where the
    point is not within _ATAN_MARGIN of a pixel edge (all but ~1e-6 of them), from libm's atan2 and hypot otherwise."""
    h, w = depth.shape
    n = points.shape[0]
    uu = np.empty(n)
    vv = np.empty(n)
    for m in range(n):  # no branch: vectorised
        x, y, z = _cam_point(cam_from_world, points, m)
        dist[m] = math.sqrt(x * x + y * y + z * z)
        uu[m] = (_fast_atan2(x, z) / (2.0 * math.pi) + 0.5) * w
        vv[m] = (0.5 - _fast_atan2(-y, math.sqrt(x * x + z * z)) / math.pi) * h
    mu = _ATAN_MARGIN * w / (2.0 * math.pi)
    mv = _ATAN_MARGIN * h / math.pi
    for m in range(n):
        if not dist[m] < math.inf:  # NaN or infinite points fall in no pixel
            d_src[m] = math.nan
            continue
        u = uu[m]
        v = vv[m]
        fu = u - math.floor(u)  # NaN (0 / 0 at the camera centre or a pole's longitude) fails both tests below
        fv = v - math.floor(v)
        if not (mu < fu < 1.0 - mu and mv < fv < 1.0 - mv):  # near a pixel edge: libm's pixel, as the exact kernel
            x, y, z = _cam_point(cam_from_world, points, m)
            if not mu < fu < 1.0 - mu:
                u = (math.atan2(x, z) / (2.0 * math.pi) + 0.5) * w
            if not mv < fv < 1.0 - mv:
                v = (0.5 - math.atan2(-y, math.hypot(x, z)) / math.pi) * h
        j = int(math.floor(u)) % w
        i = min(max(int(math.floor(v)), 0), h - 1)
        d_src[m] = depth[i, j]


class SourceVisibility:
    """What the source view sees: its ERP depth (H, W) metres (0/NaN/inf = unknown) and world_from_cam (4, 4); near:
    the radius (metres) around its camera centre known to be free whatever the depth (the capture rig stood there)."""

    def __init__(self, depth: np.ndarray, world_from_cam: np.ndarray, tol: float, near: float = 0.0):
        self.depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan).astype(np.float64)
        self.world_from_cam = np.asarray(world_from_cam, np.float64)
        self.cam_from_world = invert_pose(self.world_from_cam)
        self.tol = tol
        self.near = near

    def _lookup(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance of world points (M, 3) from the source, the source's depth along their ray (NaN = none));
        _lookup_reference (conventions.erp_pixel_from_dir) is its test oracle."""
        points = np.ascontiguousarray(points, np.float64)
        dist = np.empty(len(points))
        d_src = np.empty(len(points))
        _source_lookup(points, self.cam_from_world, self.depth, dist, d_src)
        return dist, d_src

    def _lookup_reference(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.einsum("ij,mj->mi", self.cam_from_world[:3, :3], points) + self.cam_from_world[:3, 3]
        dist = np.linalg.norm(p, axis=1)
        h, w = self.depth.shape
        u, v = erp_pixel_from_dir(p / np.maximum(dist, 1e-12)[:, None], h, w)
        j = np.mod(np.floor(u).astype(np.int64), w)
        i = np.clip(np.floor(v).astype(np.int64), 0, h - 1)
        return dist, self.depth[i, j]

    def explained(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool for world points (M, 3): on the source's visible surfaces or in front of them (within tol of its
        depth, relative, or nearer), i.e. the per-pixel Gaussians already stand for them or they would float in
        front of what the source saw; points within `near` of its camera centre too, depth or not. Points behind the
        source's surfaces or where it has no depth are not."""
        dist, d_src = self._lookup(points)
        with np.errstate(invalid="ignore"):
            return (np.isfinite(d_src) & (dist <= d_src * (1.0 + self.tol))) | (dist < self.near)

    def poking_through(self, g: Gaussians, reach: float = 3.0) -> np.ndarray:
        """(N,) bool: Gaussians behind the source's surface by less than reach x their largest scale, i.e. whose
        splat reaches through a surface the source saw (inside a wall, they show only as a smear on it)."""
        dist, d_src = self._lookup(np.asarray(g.means, np.float64))
        with np.errstate(invalid="ignore"):
            return np.isfinite(d_src) & (dist - d_src < reach * np.asarray(g.scales).max(1))


def merge_gaussians(parts: list[Gaussians]) -> Gaussians:
    """One Gaussians set from several (same SH degree)."""
    return Gaussians(*(np.concatenate([getattr(g, f) for g in parts]) for f in
                       ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")))


def source_anchored_fusion(frames: ContextSource, params: SourcePixelParams, *, thin_poles: bool = True, back_sides=None,
                           progress: bool = False) -> FusionResult:
    """Per-pixel Gaussians of the source view (video frame 0, at params.source_height rows; 0 = as the other frames)
    plus voxel fusion of what the other frames see that the source does not (SourceVisibility with tolerance
    params.source_tol) in voxels of params.unseen_voxel_size (0 = params.voxel_size), less those poking through the
    source's surfaces: the capture point keeps the input's full detail, the rest of the room is fused as before. The
    per-pixel Gaussians' scale_factor is params.source_scale. Without frame 0 among the frames it is plain voxel
    fusion. params.fit_iters > 0: the colours are then fitted to frame 0 at its pose (fit_colors, at fit_height rows;
    0 = source_height), and with fit_views > 0 to that many other frames spread over the path within fit_view_reach
    metres (view_targets(), at fit_view_height rows, each pixel weighted fit_view_weight against 1 for the capture
    point's) where they see what the source saw; fit_sh_degree 1 fits view-dependent colours (degree-1 SH, damped by
    fit_sh_damping) to those views (fit_views_sh_only: those only, the colours seen from the capture point are its
    fit's alone). back_sides: a callable (pix, rgb, depth, world_from_cam) -> back_sides.BackSides whose Gaussians
    join the result."""
    if not frames.indices or frames.indices[0] != 0:
        return voxel_fusion(frames, params, progress=progress)
    p = params
    src = replace(frames, height=min(p.source_height or frames.height, frames.stored_height))
    rgb, depth, pose = src.frame(0)
    pix = pixel_gaussians(rgb, depth, pose, replace(p, scale_factor=p.source_scale), thin_poles=thin_poles)
    rest = replace(frames, rgb_paths=frames.rgb_paths[1:], depth_paths=frames.depth_paths[1:],
                   world_from_cam=frames.world_from_cam[1:], indices=frames.indices[1:])
    vis = SourceVisibility(depth, pose, p.source_tol)
    result = fuse_unseen(pix, rest, vis, p, unseen_voxel_size=p.unseen_voxel_size, progress=progress)
    if back_sides is not None:
        back = back_sides(pix, rgb, depth, pose)
        result.gaussians, result.back_sides = merge_gaussians([result.gaussians, back.gaussians]), back.stats
    if p.fit_iters > 0:
        if p.fit_height and p.fit_height != src.height:
            rgb = replace(frames, height=min(p.fit_height, frames.stored_height)).rgb_at(0)  # its depth is not needed
        extra = view_targets(rest, vis, p.fit_views, p.fit_view_height, p.fit_view_reach, p.fit_view_weight)
        result.gaussians, result.color_fit = fit_colors(result.gaussians, rgb, pose, iters=p.fit_iters, extra=extra,
                                                        sh_degree=p.fit_sh_degree if extra else 0,
                                                        sh_damping=p.fit_sh_damping,
                                                        views_sh_only=p.fit_views_sh_only)
        result.fit_render = result.color_fit.pop("render")
        result.color_fit.update(iters=p.fit_iters, height=int(rgb.shape[0]))
        if extra:
            result.color_fit.update(views_from_aside=len(extra), sh_degree=p.fit_sh_degree)
    return result


def spread_frames(centres: np.ndarray, k: int) -> list[int]:
    """Indices of k camera centres (M, 3) spread out from the origin (the capture point): each the farthest from the
    origin and the ones already picked (farthest-point order)."""
    centres = np.asarray(centres, np.float64)
    near = np.linalg.norm(centres, axis=1)
    picked: list[int] = []
    for _ in range(min(k, len(centres))):
        i = int(np.argmax(near))
        picked.append(i)
        near = np.minimum(near, np.linalg.norm(centres - centres[i], axis=1))
    return picked


def view_targets(frames: ContextSource, vis: SourceVisibility, k: int, height: int, reach: float = 0.0,
                 weight: float = 1.0) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """k frames spread over the path (spread_frames; only those within `reach` metres of the capture point when > 0)
    at `height` rows as colour-fit views (rgb, world_from_cam, pixel weights): `weight` where the frame sees a surface
    the source saw (vis.explained), 0 elsewhere (generated content, no depth)."""
    from panoworld.core.conventions import points_from_depth

    if k <= 0 or not len(frames):
        return []
    src = replace(frames, height=min(height, frames.stored_height))
    centres = np.asarray(src.world_from_cam)[:, :3, 3] - vis.world_from_cam[:3, 3]
    near = np.flatnonzero(np.linalg.norm(centres, axis=1) <= reach) if reach > 0 else np.arange(len(centres))
    out = []
    for i in near[spread_frames(centres[near], k)]:
        rgb, depth, pose = src.frame(i)
        ok = np.isfinite(depth) & (depth > 0)
        pts = points_from_depth(np.where(ok, depth, 0.0), pose).reshape(-1, 3)
        out.append((rgb, pose, weight * (ok.reshape(-1) & vis.explained(pts)).reshape(depth.shape).astype(np.float32)))
    return out


def fuse_unseen(pix: Gaussians, frames: ContextSource, vis, params: FusionParams, *, unseen_voxel_size: float = 0.0,
                progress: bool = False) -> FusionResult:
    """The source Gaussians pix plus voxel fusion of what `frames` see that the source(s) do not (vis: a
    SourceVisibility, or any object with its explained / poking_through) in voxels of unseen_voxel_size (0 =
    params.voxel_size), less the voxel Gaussians poking through a surface the source saw. Frames that add nothing
    (every pixel explained or without depth) leave the source Gaussians alone: a valid scene."""
    if not len(frames):
        return FusionResult(pix, len(pix), 0, 0, bbox_extent(pix.means), params.voxel_size, num_source=len(pix))
    vox_params = replace(params, voxel_size=unseen_voxel_size) if unseen_voxel_size > 0 else params
    fused = voxel_fusion(frames, vox_params, progress=progress, keep_points=lambda p: ~vis.explained(p),
                         empty_ok=len(pix) > 0)
    poking = vis.poking_through(fused.gaussians)
    g = merge_gaussians([pix, fused.gaussians.subset(~poking)])
    return FusionResult(g, fused.num_observations + len(pix), fused.num_voxels, fused.num_pruned + int(poking.sum()),
                        bbox_extent(g.means), vox_params.voxel_size, num_source=len(pix))


def fit_colors(g: Gaussians, target: np.ndarray, world_from_cam: np.ndarray, *, iters: int = 10, damping: float = 0.01,
               supersample: int = 1, pole_scale: float | None = None,
               extra: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = (), tile: int = 8, sh_degree: int = 0,
               sh_damping: float = 0.001, views_sh_only: bool = False, views_seen_only: bool = True,
               cov: torch.Tensor | None = None) -> tuple[Gaussians, dict]:
    """Gaussians whose colours (SH DC) are refitted so their ERP render at world_from_cam matches target (H, W, 3)
    uint8 or [0, 1]: the render is linear in the colours for fixed geometry (erp_operator.ErpColorOperator), so this
    is `iters` steps of damped conjugate-gradient least squares, min |A c - y|^2 + damping |c - c0|^2 from the current
    colours c0 (damping per unit of compositing weight: Gaussians the view barely sees stay put), clipped to [0, 1].
    extra: more views (target, world_from_cam, weight (h, w) >= 0) whose weighted squared errors join the objective
    (their own sizes, supersample 1; only their pixels of weight > 0 are rendered). sh_degree 1: the degree-1 SH
    coefficients s are fitted too: view k sees c + (b_k - b_0) . s, c the colour from the capture point, b_k the basis
    SH_C1 (-y, z, -x) of the unit direction (x, y, z) from view k's centre (render_gs.eval_sh's), so s carries only
    what changes away from the capture point, damped by sh_damping per unit of compositing weight towards its current
    value (0 for a set without it): a Gaussian seen from one side keeps one colour. pole_scale: the operators' (None =
    render_erp's default); tile: their weights kernel's tile size (8: fewer Gaussians scanned per pixel than the
    rasteriser's 16, the same weights). Returns the Gaussians (sh_rest of degree >= sh_degree) and {"rmse_before",
    "rmse_after"} of the render at world_from_cam, and "render": that render of the fitted Gaussians, (rgb (H, W, 3),
    alpha (H, W)) float32 numpy. views_sh_only (with sh_degree 1 and extra): c is fitted to the capture point alone
    (the fit without extra, so its render there is that fit's) and the views fit s only, with c fixed; with
    views_seen_only the CG runs on the Gaussians a view sees alone (the others' gradient is 0, so they keep the
    capture fit's colours: the same fit for less CPU; False: on all, as the tests' reference). cov: the Gaussians'
    covariance_3d when at hand."""
    from panoworld.render.erp_operator import ErpColorOperator
    from panoworld.render.splats import _SH_C1, covariance_3d

    if sh_degree not in (0, 1):
        raise ValueError(f"sh_degree={sh_degree!r} but expected 0 or 1")

    def as_float(img):
        return torch.as_tensor(np.asarray(img, np.float32) / (255.0 if img.dtype == np.uint8 else 1.0))

    h, w = target.shape[:2]
    y = as_float(target)
    if cov is None:
        cov = covariance_3d(torch.as_tensor(g.scales).float(), torch.as_tensor(g.quats).float())
    sh_only = bool(views_sh_only and sh_degree and len(extra))
    if sh_only:  # the capture point's fit alone; its colours stay, the views below move s only
        g, info = fit_colors(g, target, world_from_cam, iters=iters, damping=damping, supersample=supersample,
                             pole_scale=pole_scale, tile=tile, cov=cov)
        op = None
    else:
        op = ErpColorOperator(g, world_from_cam, h, w, supersample=supersample, pole_scale=pole_scale, tile=tile,
                              cov=cov)
    views = [(op, y, None)]  # (operator, target, sqrt of the pixel weights or None)
    poses = [world_from_cam]
    for img, pose, wt in extra:
        m = torch.as_tensor(np.sqrt(np.asarray(wt, np.float32)))[..., None]
        views.append((ErpColorOperator(g, pose, img.shape[0], img.shape[1], supersample=1, pole_scale=pole_scale,
                                       mask=np.asarray(wt) > 0, tile=tile, cov=cov), as_float(img) * m, m))
        poses.append(pose)
    g_all, act = g, None
    if sh_only and views_seen_only:  # the Gaussians some view sees: only their s moves
        act = np.flatnonzero(sum(v[0].adjoint(v[2].expand_as(v[1]).square()) for v in views[1:])[:, 0].numpy() > 0)
        views = [views[0]] + [(A.restricted(act), t, m) for A, t, m in views[1:]]
        g = g.subset(act)
    n = len(g)
    basis = []  # per view (N, 3): the degree-1 SH basis of each Gaussian's direction from its centre, less the
    if sh_degree:  # capture point's: c is the colour seen from there, s only what changes from elsewhere
        means = torch.as_tensor(np.asarray(g.means, np.float32))

        def sh1(pose):
            d = means - torch.as_tensor(np.asarray(pose, np.float32)[:3, 3])
            d = d / d.norm(dim=1, keepdim=True).clamp(min=1e-12)
            return _SH_C1 * torch.stack([-d[:, 1], d[:, 2], -d[:, 0]], 1)

        b0 = sh1(world_from_cam)
        basis = [torch.zeros(n, 3)] + [sh1(pose) - b0 for pose in poses[1:]]
        # the unknowns are s times each Gaussian's RMS basis change (a diagonal preconditioner: CG's few steps
        # otherwise hardly move coefficients whose basis changes little between the views)
        rho = (sum(b.square().sum(1) for b in basis) / max(len(basis) - 1, 1)).sqrt().clamp(min=1e-3)[:, None]
        basis = [b / rho for b in basis]

    def color(k, x):  # the unknowns (N, 3) or (N, 12: c, then s (3 basis x 3 channels)) -> view k's colours (N, 3)
        if not sh_degree or k == 0:
            return x[:, :3]
        return x[:, :3] + torch.einsum("nj,njc->nc", basis[k], x[:, 3:].reshape(n, 3, 3))

    def fwd(k, x):
        A, _, m = views[k]
        return A(color(k, x)) if m is None else A(color(k, x)) * m

    ks = range(1 if sh_only else 0, len(views))  # the views in the objective (view 0 does not see s)

    def grad(r):  # sum over the views of the adjoint of r (per view (h, w, 3)), as the unknowns
        out = torch.zeros(n, 12 if sh_degree else 3)
        for k in ks:
            A, _, m = views[k]
            gc = A.adjoint(r[k] if m is None else r[k] * m)
            if not sh_only:
                out[:, :3] += gc
            if sh_degree and k:
                out[:, 3:].view(n, 3, 3).add_(basis[k][:, :, None] * gc[:, None, :])
        return out

    c0 = torch.from_numpy(g.base_colors())
    rest0 = np.asarray(g.sh_rest, np.float32)
    if sh_degree:
        s0 = np.zeros((n, 3, 3), np.float32)
        s0[:, : rest0.shape[1]] = rest0[:, :3]
        s0 = torch.from_numpy(s0)
        c0 = torch.cat([c0 + torch.einsum("nj,njc->nc", b0, s0), (s0 * rho[:, :, None]).reshape(n, 9)], 1)
    ones = [torch.ones_like(v[1]) if v[2] is None else v[2].expand_as(v[1]).clone() for v in views]
    seen = sum(views[k][0].adjoint(ones[k] if views[k][2] is None else ones[k] * views[k][2])
               for k in ks)[:, :1].clamp(min=1e-3)  # each Gaussian's compositing weight
    lam = damping * seen if not sh_degree else \
        torch.cat([damping * seen.expand(n, 3), (sh_damping * seen / rho.square()).expand(n, 9)], 1)

    x = c0.clone()
    r = {k: views[k][1] - fwd(k, x) for k in ks}
    rmse0 = info["rmse_before"] if sh_only else float(r[0].square().mean().sqrt())
    s = grad(r)  # the gradient of the damped objective at c0 (damping term 0)
    p, gamma = s.clone(), float(s.square().sum())
    for _ in range(iters):
        q = {k: fwd(k, p) for k in ks}
        alpha = gamma / max(float(sum(qk.square().sum() for qk in q.values()) + (lam * p.square()).sum()), 1e-20)
        x = x + alpha * p
        r = {k: r[k] - alpha * q[k] for k in ks}
        s = grad(r).sub_(lam * (x - c0))
        gamma_new = float(s.square().sum())
        p, gamma = s + gamma_new / max(gamma, 1e-20) * p, gamma_new
    x[:, :3] = x[:, :3].clamp(0.0, 1.0)
    if not sh_only:
        img = op(x[:, :3])
        rmse1 = float((y - img).square().mean().sqrt())
    sh_rest = g.sh_rest
    if sh_degree:
        sh_rest = np.zeros((n, max(3, rest0.shape[1]), 3), np.float32)
        sh_rest[:, : rest0.shape[1]] = rest0
        coef = x[:, 3:].reshape(n, 3, 3) / rho[:, :, None]
        sh_rest[:, :3] = coef.numpy()
        x[:, :3] -= torch.einsum("nj,njc->nc", b0, coef)  # the DC: c less the capture point's part
    out = Gaussians(g.means, g.scales, g.quats, g.opacities, rgb_to_sh_dc(x[:, :3].numpy()).astype(np.float32), sh_rest)
    if act is not None:  # the Gaussians no view sees keep the capture fit's colours
        dc, rest = np.array(g_all.sh_dc, np.float32), np.zeros((len(g_all),) + sh_rest.shape[1:], np.float32)
        rest[:, : g_all.sh_rest.shape[1]] = g_all.sh_rest
        dc[act], rest[act] = out.sh_dc, sh_rest
        out = Gaussians(g_all.means, g_all.scales, g_all.quats, g_all.opacities, dc, rest)
    if sh_only:  # the capture point sees c, which is its own fit's: that fit's render and error stand
        return out, {"rmse_before": rmse0, "rmse_after": info["rmse_after"], "render": info["render"]}
    alpha = op(torch.ones(n, 3))[..., 0]  # the weights of each pixel sum to its opacity 1 - T
    return out, {"rmse_before": rmse0, "rmse_after": rmse1, "render": (img.numpy(), alpha.numpy())}
