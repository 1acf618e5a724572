"""3D Gaussian rendering in pure torch on CPU: EWA projection, a 16x16-tile rasteriser, its brute-force oracle, pinhole views.

The image model is INRIA 3DGS's: Gaussians behind the near plane or with a degenerate 2D covariance are dropped,
the 2D covariance is J W Sigma W^T J^T + 0.3 I (J clamped at 1.3x the view's half-extent), per-pixel
alpha = min(0.99, o * exp(-d^T Sigma2d^-1 d / 2)) counts only when >= 1/255, Gaussians are composited front to
back in order of camera-space depth, and a pixel stops before the Gaussian that would bring its transmittance
below 1e-4. Pixel (row i, col j) has its centre at (j + 0.5, i + 0.5); u = fx x/z + cx.
The tile rasteriser bins each Gaussian into the tiles its alpha >= 1/255 ellipse touches, so it computes exactly
what the brute-force reference (every Gaussian at every pixel) computes.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
import torch

from panoworld.core.conventions import check_pose, invert_pose
from panoworld.core.rotations import rotmat_from_quat
from panoworld.io.gaussian_set import SH_C0, Gaussians

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
LOWPASS = 0.3
TILE = 16
NUMBA_TILE = 8
"""The numba paths bin Gaussians into 8 x 8 tiles (the torch rasteriser: 16 x 16), so each pixel scans fewer: the
same weights up to float32 rounding of the transmittance (a pixel's list holds every Gaussian whose box covers it, in
the same order), 1.7-1.9x less CPU on an 830k-Gaussian scene with differences <= 1.5e-6 (bench/bench_render_gs.py)."""
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
    1.445305721320277, -0.5900435899266435,
)


@dataclass
class RenderOutput:
    """A rendered view; torch float32 tensors."""

    rgb: torch.Tensor
    """(H, W, 3) colour composited over the background."""
    depth: torch.Tensor
    """(H, W) expected depth of the visible Gaussians (sum w z / alpha; 0 where alpha = 0): camera z for
    perspective views, Euclidean ray distance for ERP."""
    alpha: torch.Tensor
    """(H, W) accumulated opacity 1 - T."""


@dataclass
class Projected:
    """Gaussians projected into one view: only those that can touch the image, in input order."""

    xy: torch.Tensor
    """(P, 2) pixel coordinates of the centres."""
    conic: torch.Tensor
    """(P, 3) entries (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]."""
    z: torch.Tensor
    """(P,) camera-space depth (the compositing order)."""
    dist: torch.Tensor
    """(P,) Euclidean distance of the centres from the camera."""
    opacity: torch.Tensor
    """(P,)"""
    color: torch.Tensor
    """(P, 3)"""
    extent: torch.Tensor
    """(P, 2) half-widths in pixels (x, y) of the box holding the alpha >= 1/255 ellipse."""
    index: torch.Tensor | None = None
    """(P,) index of each projected Gaussian in the set passed to project."""


@dataclass
class _Prepared:
    means: torch.Tensor
    cov: torch.Tensor
    opacity: torch.Tensor
    color: torch.Tensor


def covariance_3d(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """(N, 3) scales, (N, 4) quats -> (N, 3, 3) covariances R diag(s^2) R^T."""
    M = rotmat_from_quat(quats) * scales[:, None, :]
    return M @ M.transpose(1, 2)


def eval_sh(sh_dc: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """INRIA's real SH up to degree 3: dc (N, 3), rest (N, K, 3), unit view dirs (N, 3) -> rgb (N, 3), clamped >= 0."""
    out = SH_C0 * sh_dc
    k = sh_rest.shape[1]
    if k >= 3:
        x, y, z = dirs.unbind(-1)
        x, y, z = x[:, None], y[:, None], z[:, None]
        s = sh_rest
        out = out - _SH_C1 * y * s[:, 0] + _SH_C1 * z * s[:, 1] - _SH_C1 * x * s[:, 2]
        if k >= 8:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            out = (
                out + _SH_C2[0] * xy * s[:, 3] + _SH_C2[1] * yz * s[:, 4] + _SH_C2[2] * (2 * zz - xx - yy) * s[:, 5]
                + _SH_C2[3] * xz * s[:, 6] + _SH_C2[4] * (xx - yy) * s[:, 7]
            )
            if k >= 15:
                out = (
                    out + _SH_C3[0] * y * (3 * xx - yy) * s[:, 8] + _SH_C3[1] * xy * z * s[:, 9]
                    + _SH_C3[2] * y * (4 * zz - xx - yy) * s[:, 10] + _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * s[:, 11]
                    + _SH_C3[4] * x * (4 * zz - xx - yy) * s[:, 12] + _SH_C3[5] * z * (xx - yy) * s[:, 13]
                    + _SH_C3[6] * x * (xx - 3 * yy) * s[:, 14]
                )
    return (out + 0.5).clamp(min=0.0)


def _t(a, dtype=torch.float32) -> torch.Tensor:
    return a.to(dtype) if isinstance(a, torch.Tensor) else torch.as_tensor(np.asarray(a), dtype=dtype)


def _prepare(g: Gaussians, cam_centre: np.ndarray) -> _Prepared:
    means = _t(g.means)
    dirs = means - torch.as_tensor(cam_centre, dtype=torch.float32)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    rest = _t(g.sh_rest)
    if rest.shape[1] and not rest.requires_grad and not bool(rest.any()):
        rest = rest[:, :0]  # all zero (a degree-3 .ply of degree-0 colours): the same colours without the terms
    color = eval_sh(_t(g.sh_dc), rest, dirs)
    return _Prepared(means, covariance_3d(_t(g.scales), _t(g.quats)), _t(g.opacities), color)


def project(
    prep: _Prepared, cam_from_world: np.ndarray, fx: float, fy: float, cx: float, cy: float, H: int, W: int,
    near: float = 0.01,
) -> Projected:
    """EWA-project prepared Gaussians into a pinhole view; keeps those whose alpha >= 1/255 ellipse meets the image."""
    R = torch.as_tensor(cam_from_world[:3, :3], dtype=torch.float32)
    t = torch.as_tensor(cam_from_world[:3, 3], dtype=torch.float32)
    pc = prep.means @ R.T + t
    keep = (pc[:, 2] > near) & (prep.opacity > ALPHA_MIN)
    idx = keep.nonzero().squeeze(1)
    pc = pc[idx]
    x, y, z = pc.unbind(-1)
    lim_l, lim_r = -1.3 * cx / fx, 1.3 * (W - cx) / fx
    lim_t, lim_b = -1.3 * cy / fy, 1.3 * (H - cy) / fy
    tx = (x / z).clamp(lim_l, lim_r) * z
    ty = (y / z).clamp(lim_t, lim_b) * z
    zero = torch.zeros_like(z)
    J = torch.stack(
        [torch.stack([fx / z, zero, -fx * tx / z**2], -1), torch.stack([zero, fy / z, -fy * ty / z**2], -1)], 1
    )
    T = J @ R
    cov2 = T @ prep.cov[idx] @ T.transpose(1, 2)
    a = cov2[:, 0, 0] + LOWPASS
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + LOWPASS
    det = a * c - b * b
    opacity = prep.opacity[idx]
    r2 = 2.0 * torch.log(opacity * 255.0)  # o exp(-r2 / 2) = 1/255 on the ellipse's border
    ext = torch.stack([(r2 * a).clamp(min=0).sqrt(), (r2 * c).clamp(min=0).sqrt()], -1) + 1e-3
    xy = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    lo = xy - ext
    hi = xy + ext
    first = torch.ceil(lo - 0.5)
    last = torch.floor(hi - 0.5)
    # Some pixel centre lies in the box, and the box meets the image.
    ok = (det > 0) & (first <= last).all(1) & (last[:, 0] >= 0) & (first[:, 0] <= W - 1)
    ok &= (last[:, 1] >= 0) & (first[:, 1] <= H - 1)
    ok = ok.nonzero().squeeze(1)
    det = det[ok]
    conic = torch.stack([c[ok] / det, -b[ok] / det, a[ok] / det], -1)
    return Projected(xy[ok], conic, z[ok], pc[ok].norm(dim=-1), opacity[ok], prep.color[idx[ok]], ext[ok], idx[ok])


def _alpha(proj: Projected, gid: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Alpha of Gaussians gid (..., G) at pixels px, py (..., P) -> (..., G, P), zero below 1/255."""
    dx = px[..., None, :] - proj.xy[gid][..., 0:1]
    dy = py[..., None, :] - proj.xy[gid][..., 1:2]
    con = proj.conic[gid]
    power = -0.5 * (con[..., 0:1] * dx * dx + con[..., 2:3] * dy * dy) - con[..., 1:2] * dx * dy
    alpha = (proj.opacity[gid][..., None] * torch.exp(power)).clamp(max=ALPHA_MAX)
    return torch.where((alpha >= ALPHA_MIN) & (power <= 0), alpha, torch.zeros_like(alpha))


def _composite_step(alpha: torch.Tensor, T: torch.Tensor, done: torch.Tensor):
    """alpha (..., G, P) in depth order, transmittance T (..., P) before them -> (weights, new T, new done)."""
    cp = torch.cumprod(1.0 - alpha, dim=-2)
    t_incl = T[..., None, :] * cp
    inc = (t_incl >= T_MIN) & ~done[..., None, :]
    t_excl = T[..., None, :] * torch.cat([torch.ones_like(cp[..., :1, :]), cp[..., :-1, :]], dim=-2)
    w = alpha * t_excl * inc
    T_new = torch.minimum(T, torch.where(inc, t_incl, torch.full_like(t_incl, 2.0)).amin(dim=-2))
    return w, T_new, done | (t_incl[..., -1, :] < T_MIN)


def rasterize_reference(proj: Projected, H: int, W: int, background: torch.Tensor, pixel_chunk: int = 2048) -> RenderOutput:
    """Brute force: every Gaussian at every pixel, globally depth-sorted (the test oracle of rasterize_tiles)."""
    order = torch.argsort(proj.z, stable=True)
    jj, ii = torch.meshgrid(torch.arange(W), torch.arange(H), indexing="xy")
    px_all = jj.reshape(-1).float() + 0.5
    py_all = ii.reshape(-1).float() + 0.5
    rgb, depth, T = [], [], []
    for s in range(0, H * W, pixel_chunk):
        px, py = px_all[s : s + pixel_chunk], py_all[s : s + pixel_chunk]
        alpha = _alpha(proj, order, px, py)
        T0 = torch.ones(px.shape[0])
        w, Tn, _ = _composite_step(alpha, T0, torch.zeros_like(T0, dtype=torch.bool))
        rgb.append(w.T @ proj.color[order])
        depth.append(w.T @ proj.z[order])
        T.append(Tn)
    return _finish(torch.cat(rgb), torch.cat(depth), torch.cat(T), background, H, W)


def _finish(rgb: torch.Tensor, depth: torch.Tensor, T: torch.Tensor, background: torch.Tensor, H: int, W: int) -> RenderOutput:
    alpha = 1.0 - T
    rgb = rgb + T[:, None] * background
    depth = torch.where(alpha > 0, depth / alpha.clamp(min=1e-12), torch.zeros_like(depth))
    return RenderOutput(rgb.reshape(H, W, 3), depth.reshape(H, W), alpha.reshape(H, W))


def bin_tiles(proj: Projected, H: int, W: int, tile: int = TILE):
    """Bin projected Gaussians into tile x tile tiles -> (ntx, nty, Gaussian indices sorted by (tile, depth), per-tile
    counts, per-tile starts into them)."""
    ntx, nty = -(-W // tile), -(-H // tile)
    P = proj.z.shape[0]
    # Pixel index range holding the alpha >= 1/255 box, then the tiles it covers.
    j0 = torch.ceil(proj.xy[:, 0] - proj.extent[:, 0] - 0.5).clamp(0, W - 1).long() // tile
    j1 = torch.floor(proj.xy[:, 0] + proj.extent[:, 0] - 0.5).clamp(0, W - 1).long() // tile
    i0 = torch.ceil(proj.xy[:, 1] - proj.extent[:, 1] - 0.5).clamp(0, H - 1).long() // tile
    i1 = torch.floor(proj.xy[:, 1] + proj.extent[:, 1] - 0.5).clamp(0, H - 1).long() // tile
    wx = j1 - j0 + 1
    n_per = wx * (i1 - i0 + 1)
    gid = torch.repeat_interleave(torch.arange(P), n_per)
    local = torch.arange(gid.shape[0]) - torch.repeat_interleave(torch.cumsum(n_per, 0) - n_per, n_per)
    tile = (i0[gid] + local // wx[gid]) * ntx + j0[gid] + local % wx[gid]
    rank = torch.empty(P, dtype=torch.long)
    rank[torch.argsort(proj.z, stable=True)] = torch.arange(P)
    order = torch.argsort(tile * max(P, 1) + rank[gid])
    counts = torch.bincount(tile, minlength=ntx * nty)
    return ntx, nty, gid[order], counts, torch.cumsum(counts, 0) - counts


def rasterize_tiles(
    proj: Projected, H: int, W: int, background: torch.Tensor, chunk: int = 32, raw: bool = False,
    distance: bool = False, weights: list | None = None,
) -> RenderOutput:
    """Tile rasteriser: bin Gaussians into 16x16 tiles, sort by (tile, depth), composite all tiles chunk by chunk.

    raw=True returns the un-normalised accumulated depth (sum w z) instead of the expected depth; distance=True
    accumulates the centres' Euclidean distances instead of their z. weights, when a list, receives per chunk the
    non-zero compositing weights as (flat pixel index (K,), Gaussian index in proj (K,), weight (K,)): the image is
    their sum of weight x colour plus the transmittance x background; the returned render then holds only the
    transmittance (alpha; rgb is transmittance x background, depth 0): colour and depth are not accumulated.
    """
    depth_of = proj.dist if distance else proj.z
    ntx, nty, sorted_g, counts, starts = bin_tiles(proj, H, W)
    n_tiles = ntx * nty
    local_pix = torch.arange(TILE * TILE)
    base_x = (torch.arange(n_tiles) % ntx) * TILE
    base_y = (torch.arange(n_tiles) // ntx) * TILE
    T = torch.ones(n_tiles, TILE * TILE)
    done = torch.zeros(n_tiles, TILE * TILE, dtype=torch.bool)
    acc_rgb = torch.zeros(n_tiles, TILE * TILE, 3)
    acc_z = torch.zeros(n_tiles, TILE * TILE)
    active = (counts > 0).nonzero().squeeze(1)
    k = 0
    offs = torch.arange(chunk)
    n_sorted = max(sorted_g.shape[0], 1)
    while active.numel():
        a = active
        valid = (k + offs)[None, :] < counts[a, None]
        g = sorted_g[(starts[a, None] + k + offs).clamp(max=n_sorted - 1)] if sorted_g.numel() else None
        px = (base_x[a, None] + local_pix % TILE).float() + 0.5
        py = (base_y[a, None] + local_pix // TILE).float() + 0.5
        alpha = _alpha(proj, g, px, py) * valid[..., None]
        w, T[a], done[a] = _composite_step(alpha, T[a], done[a])
        if weights is not None:
            ti, gi, pi = (w > 0).nonzero(as_tuple=True)
            y, x = base_y[a[ti]] + pi // TILE, base_x[a[ti]] + pi % TILE
            inside = (y < H) & (x < W)
            weights.append(((y * W + x)[inside], g[ti, gi][inside], w[ti, gi, pi][inside]))
        else:  # the weights' caller builds its own image from them
            acc_rgb[a] = acc_rgb[a] + torch.bmm(w.transpose(1, 2), proj.color[g])
            acc_z[a] = acc_z[a] + torch.bmm(w.transpose(1, 2), depth_of[g][..., None])[..., 0]
        k += chunk
        a_keep = (counts[a] > k) & ~done[a].all(1)
        active = a[a_keep]

    def image(x: torch.Tensor) -> torch.Tensor:
        c = x.shape[-1] if x.ndim == 3 else 1
        x = x.reshape(nty, ntx, TILE, TILE, c).permute(0, 2, 1, 3, 4).reshape(nty * TILE, ntx * TILE, c)
        return x[:H, :W].reshape(H * W, c)

    rgb, z, T = image(acc_rgb), image(acc_z)[:, 0], image(T)[:, 0]
    if raw:
        return RenderOutput((rgb + T[:, None] * background).reshape(H, W, 3), z.reshape(H, W), (1 - T).reshape(H, W))
    return _finish(rgb, z, T, background, H, W)


def face_weights(proj: Projected, H: int, W: int, chunk: int = 32, need: np.ndarray | None = None,
                 tile: int = TILE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """rasterize_tiles(weights=...)'s non-zero compositing weights, concatenated, from its numba kernel
    (splat_weights.tile_weights): (flat pixel index (K,) int32, Gaussian index in proj (K,) int32, weight (K,)
    float32). Equal to the torch path's up to the last bit of exp (tests/test_render_gs.py). need (H * W,) bool:
    only those pixels' weights (None: all); tiles without one are skipped. A smaller tile than the rasteriser's
    scans fewer Gaussians per pixel (the same weights but where a pixel's transmittance falls below T_MIN, which
    chunk it stops at)."""
    from panoworld.render.splat_weights import bin_tiles_numba, tile_weights

    ntx, nty, sorted_g, counts, starts = bin_tiles_numba(proj.xy.numpy(), proj.extent.numpy(), proj.z.numpy(), H, W,
                                                         tile)
    if need is None:
        need = np.zeros(0, bool)
    else:
        pad = np.zeros((nty * tile, ntx * tile), bool)
        pad[:H, :W] = np.asarray(need, bool).reshape(H, W)
        counts = np.where(pad.reshape(nty, tile, ntx, tile).any((1, 3)).reshape(-1), counts, 0)
    return tile_weights(proj.xy.numpy(), proj.conic.numpy(), proj.opacity.numpy(), sorted_g, starts, counts, ntx, H, W,
                        tile, chunk, need)


def _background(background) -> torch.Tensor:
    if background is None:
        return torch.zeros(3)
    bg = torch.as_tensor(np.asarray(background, dtype=np.float32)).reshape(-1)
    if bg.shape != (3,):
        raise ValueError(f"background.shape={tuple(bg.shape)} but expected (3,)")
    return bg


def render_perspective(
    gaussians: Gaussians, world_from_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float, H: int, W: int,
    *, near: float = 0.01, background=None, backend: str = "auto", reference: bool = False,
) -> RenderOutput:
    """Render a pinhole (OpenCV) view of the Gaussians; rgb (H, W, 3), depth (H, W) camera z, alpha (H, W).

    backend: "torch" (CPU tile rasteriser, differentiable), "numba" (the same image from the numba kernel's
    compositing weights, rasterize_numba: several times faster, no gradient), "gsplat" (CUDA, needs gsplat and CUDA
    tensors) or "auto" (gsplat when the Gaussians are CUDA tensors and gsplat imports, else numba when no gradient
    is needed, else torch). reference=True uses the brute-force oracle.
    """
    check_pose(world_from_cam, "world_from_cam")
    if H <= 0 or W <= 0:
        raise ValueError(f"image size {W}x{H} (WxH) must be positive")
    if backend not in ("auto", "torch", "numba", "gsplat"):
        raise ValueError(f"backend={backend!r} but expected 'auto', 'torch', 'numba' or 'gsplat'")
    if _use_gsplat(gaussians, backend):
        return _render_gsplat(gaussians, world_from_cam, fx, fy, cx, cy, H, W, near, background)
    grad = _needs_grad(gaussians)
    if backend == "numba" and grad:
        raise ValueError("backend='numba' renders without gradients but a Gaussian tensor requires grad: use 'torch'")
    world_from_cam = np.asarray(world_from_cam, dtype=np.float64)
    bg = _background(background)
    if not grad and not reference:  # only what the view can show is prepared and projected: the same image
        cand = view_candidates(*cull_terms(gaussians.means, gaussians.opacities, gaussians.scales, world_from_cam[:3, 3]),
                               world_from_cam[:3, :3].T, fx, fy, cx, cy, H, W, near)
        gaussians = gaussians.subset(cand.numpy() if isinstance(gaussians.means, np.ndarray) else cand)
    with torch.no_grad() if not grad else contextlib.nullcontext():
        prep = _prepare(gaussians, world_from_cam[:3, 3])
        proj = project(prep, invert_pose(world_from_cam), fx, fy, cx, cy, H, W, near)
        if reference:
            return rasterize_reference(proj, H, W, bg)
        if backend == "torch" or grad:
            return rasterize_tiles(proj, H, W, bg)
        return rasterize_numba(proj, H, W, bg)


def view_candidates(offsets: torch.Tensor, r2: torch.Tensor, scale2: torch.Tensor, cam_from_world_rot: np.ndarray,
                    fx: float, fy: float, cx: float, cy: float, H: int, W: int, near: float) -> torch.Tensor:
    """Indices of Gaussians (offsets (N, 3): centre - camera centre in the world; r2 (N,): 2 ln(255 opacity), 0 where
    project drops them; scale2 (N,): largest variance; float32) that project can keep for a pinhole view
    (cam_from_world_rot (3, 3)): a superset, from a bound of the box project puts around each centre (half-width
    sqrt(r2 a), a the 2D covariance's diagonal plus LOWPASS, at most (f/z)^2 (1 + (1.3 c / f)^2) scale2 + LOWPASS
    with c the principal point's larger distance to the image's sides, as the Jacobian is clamped at 1.3x that), with
    slack for float32 rounding (in one pass, in float64: render.splat_weights.view_candidate_indices)."""
    from panoworld.render.splat_weights import view_candidate_indices

    k = [1.0 + (1.3 * max(c, n - c) / f) ** 2 for f, c, n in ((fx, cx, W), (fy, cy, H))]
    rot = np.ascontiguousarray(cam_from_world_rot, np.float64)
    return torch.from_numpy(view_candidate_indices(_contiguous(offsets), _contiguous(r2), _contiguous(scale2), rot,
                                                   float(fx), float(fy), float(cx), float(cy), int(H), int(W),
                                                   float(near), k[0], k[1], float(LOWPASS)))


def _contiguous(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().numpy(), np.float32)


def cull_terms(means, opacities, scales, centre: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """view_candidates' offsets, r2 and scale2 of Gaussians (means (N, 3), opacities (N,), scales (N, 3)) seen from
    `centre` (3,), without gradients."""
    with torch.no_grad():
        offsets = _t(means).detach() - torch.as_tensor(np.asarray(centre, np.float32))
        o = _t(opacities).detach()
        # r2 > 0 for every opacity project keeps (> ALPHA_MIN), also where 255 o rounds to 1
        r2 = torch.where(o > ALPHA_MIN * 0.999, (2.0 * (255.0 * o).log()).clamp(min=1e-6), 0.0)
        return offsets, r2, _t(scales).detach().square().amax(1)


def _needs_grad(gaussians: Gaussians) -> bool:
    return torch.is_grad_enabled() and any(
        isinstance(a, torch.Tensor) and a.requires_grad
        for a in (gaussians.means, gaussians.scales, gaussians.quats, gaussians.opacities, gaussians.sh_dc,
                  gaussians.sh_rest))


def rasterize_numba(proj: Projected, H: int, W: int, background: torch.Tensor, *, raw: bool = False,
                    distance: bool = False, tile: int = NUMBA_TILE, need: np.ndarray | None = None) -> RenderOutput:
    """rasterize_tiles' image (same raw / distance meaning) summed in float64 from face_weights' weights: no
    gradient, equal to it within float32 rounding (tests/test_render_gs.py). need (H * W,) bool: only those pixels
    are composited (the others hold the background, alpha 0)."""
    from panoworld.render.splat_weights import weighted_sums

    pix, gid, w = face_weights(proj, H, W, tile=tile, need=need)
    depth_of = proj.dist if distance else proj.z
    values = torch.cat([proj.color, depth_of[:, None]], 1).detach().numpy()
    out = torch.from_numpy(weighted_sums(pix, gid, w, values, H * W).astype(np.float32))
    alpha = out[:, 4]
    if raw:
        return RenderOutput((out[:, :3] + (1 - alpha)[:, None] * background).reshape(H, W, 3), out[:, 3].reshape(H, W),
                            alpha.reshape(H, W))
    return _finish(out[:, :3], out[:, 3], 1 - alpha, background, H, W)


def _use_gsplat(gaussians: Gaussians, backend: str) -> bool:
    on_cuda = isinstance(gaussians.means, torch.Tensor) and gaussians.means.is_cuda
    return backend == "gsplat" or (backend == "auto" and on_cuda and _gsplat_available())


def _gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return torch.cuda.is_available()


def _render_gsplat(g, world_from_cam, fx, fy, cx, cy, H, W, near, background) -> RenderOutput:
    """gsplat's CUDA rasteriser (same INRIA image model); expected depth via render_mode RGB+ED."""
    try:
        from gsplat import rasterization
    except ImportError as e:
        raise ImportError("backend='gsplat' needs gsplat and a CUDA GPU: pip install gsplat") from e
    dev = torch.device("cuda")

    def t(a):
        return _t(a).to(dev)

    sh = torch.cat([t(g.sh_dc)[:, None], t(g.sh_rest)], 1)
    viewmat = torch.as_tensor(invert_pose(np.asarray(world_from_cam, np.float64)), dtype=torch.float32, device=dev)
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32, device=dev)
    bg = _background(background).to(dev)
    # The background is composited here: gsplat 1.5's packed path (its default) rejects its own background shape.
    colors, alphas, _ = rasterization(
        t(g.means), t(g.quats), t(g.scales), t(g.opacities), sh, viewmat[None], K[None], W, H,
        near_plane=near, sh_degree=g.sh_degree, render_mode="RGB+ED",
    )
    alpha = alphas[0, ..., 0]
    return RenderOutput(colors[0, ..., :3] + (1 - alpha)[..., None] * bg, colors[0, ..., 3], alpha)
