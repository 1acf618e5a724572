"""ERP renders of 3D Gaussians from 6 cube faces: the faces, their per-face cull, the compositing (torch, numba, gsplat)."""

from __future__ import annotations

import contextlib
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from panoworld.core.conventions import check_erp_shape, check_pose, erp_dirs, invert_pose
from panoworld.io.gaussian_set import Gaussians
from panoworld.render.splats import (
    RenderOutput,
    _background,
    _needs_grad,
    _prepare,
    _Prepared,
    _render_gsplat,
    _use_gsplat,
    cull_terms,
    project,
    rasterize_numba,
    rasterize_tiles,
    view_candidates,
)

# Rotations cam_from_face of the 6 cube faces (columns: face x, y, z axes in the ERP camera frame).
CUBE_FACES = {
    "+z": np.eye(3),
    "-z": np.diag([-1.0, 1.0, -1.0]),
    "+x": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    "-x": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
    "+y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "-y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
}

ERP_SUPERSAMPLE = 2
"""render_erp's default supersampling: the ERP is sampled at 2x its size in each axis from cube faces at 2x resolution
and area-downsampled (2x2 box), so splats finer than a pixel (per-pixel Gaussians at the input's resolution) average
instead of aliasing; about 1.7x the render time of 1."""
ERP_POLE_SCALE = 2.0
"""render_erp's default resolution of the two pole faces (+y, -y) relative to the others. ERP rows near a pole sample
longitude tan(lat) times more finely than a cube face does there, so finer pole faces keep the floor's and ceiling's
detail near the poles; the colour fit must use the same faces (gaussians.voxel_fusion.fit_height) and the source
footprint be wide enough that the finer faces show no cracks (gaussians.voxel_fusion.source_scale)."""


@dataclass
class ErpFace:
    """One cube face of an ERP render: its pinhole view and the ERP samples it serves."""

    world_from_face: np.ndarray
    f: float
    """Focal length = principal point - margin, pixels."""
    c: float
    n: int
    """Face size in pixels (with margin)."""
    index: torch.Tensor
    """(K,) flat indices of the supersampled ERP pixels taken from this face (those nearest its axis)."""
    grid: torch.Tensor
    """(K, 2) their grid_sample coordinates in the face."""

    def sample(self, img: torch.Tensor) -> torch.Tensor:
        """Face image (n, n, C) -> (C, K) bilinear samples at those pixels."""
        return F.grid_sample(img.permute(2, 0, 1)[None], self.grid[None, None], mode="bilinear",
                             padding_mode="border", align_corners=False)[0, :, 0]


def erp_faces(world_from_cam: np.ndarray, H: int, W: int, *, face_size: int | None = None, margin: int = 2,
              supersample: int = ERP_SUPERSAMPLE, pole_scale: float | None = None) -> list[ErpFace]:
    """The cube faces render_erp composes an (H, W) ERP at world_from_cam from (see there), those serving no sample
    left out."""
    pole_scale = ERP_POLE_SCALE if pole_scale is None else pole_scale
    if not pole_scale >= 1.0:
        raise ValueError(f"pole_scale={pole_scale!r} but expected >= 1")
    check_erp_shape(H, W, "requested ERP render")
    check_pose(world_from_cam, "world_from_cam")
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample={supersample!r} but expected a positive integer")
    s = int(supersample)
    world_from_cam = np.asarray(world_from_cam, dtype=np.float64)
    S0 = face_size or math.ceil(s * W / math.pi)
    dirs = torch.from_numpy(erp_dirs(s * H, s * W)).reshape(-1, 3)
    rots = [torch.as_tensor(R, dtype=torch.float32) for R in CUBE_FACES.values()]
    owner = torch.stack([(dirs @ R)[:, 2] for R in rots]).argmax(0)  # the face nearest each ray's direction
    faces = []
    for k, (name, R_face, R) in enumerate(zip(CUBE_FACES, CUBE_FACES.values(), rots)):
        index = (owner == k).nonzero().squeeze(1)
        if not index.numel():
            continue
        S = math.ceil(pole_scale * S0) if name in ("+y", "-y") else S0
        n = S + 2 * margin
        f = S / 2.0
        c = n / 2.0
        world_from_face = world_from_cam.copy()
        world_from_face[:3, :3] = world_from_cam[:3, :3] @ R_face
        d = dirs[index] @ R  # face-frame directions (K, 3)
        z = d[:, 2].clamp(min=1e-6)
        grid = torch.stack([(f * d[:, 0] / z + c) / n * 2 - 1, (f * d[:, 1] / z + c) / n * 2 - 1], -1)
        faces.append(ErpFace(world_from_face, f, c, n, index, grid))
    return faces


def face_candidates(offsets: torch.Tensor, r2: torch.Tensor, scale2: torch.Tensor, fc: ErpFace,
                    near: float) -> torch.Tensor:
    """render_gs.view_candidates for cube face fc: a superset of the Gaussians project keeps there."""
    return view_candidates(offsets, r2, scale2, fc.world_from_face[:3, :3].T, fc.f, fc.f, fc.c, fc.c, fc.n, fc.n, near)


def face_cull(prep: _Prepared, scales, centre: np.ndarray, near: float):
    """fc -> (the prepared Gaussians (scales (N, 3)) that cube face fc of a view centred at `centre` can show, their
    indices in prep): face_candidates' superset of those project keeps, in prep's order, so projecting them gives
    project's result on all of prep (render_erp and the colour fit's ErpColorOperator project each face so)."""
    offsets, r2, scale2 = cull_terms(prep.means, prep.opacity, scales, centre)

    def subset(fc: ErpFace) -> tuple[_Prepared, torch.Tensor]:
        cand = face_candidates(offsets, r2, scale2, fc, near)
        return _Prepared(prep.means[cand], prep.cov[cand], prep.opacity[cand], prep.color[cand]), cand

    return subset


def render_erp(
    gaussians: Gaussians, world_from_cam: np.ndarray, H: int, W: int, *, face_size: int | None = None,
    margin: int = 2, near: float = 0.01, background=None, supersample: int = ERP_SUPERSAMPLE,
    pole_scale: float | None = None, backend: str = "auto", pixels: np.ndarray | None = None,
) -> RenderOutput:
    """Render an equirectangular view (W = 2H) from 6 perspective cube faces resampled bilinearly with grid_sample.

    Each face has a 90 degree field of view plus `margin` pixels on every side; face_size defaults to
    ceil(supersample W / pi), which matches the supersampled ERP's angular resolution at the face centres. With
    supersample s > 1 the ERP is sampled at (s H, s W) and area-downsampled by s (colour, alpha and alpha-weighted
    depth averaged over each s x s block). depth is the expected Euclidean distance of the Gaussian centres (composited
    in each face's z order). pole_scale: the two faces holding the poles (+y, -y) at that many times the face size,
    as ERP rows near a pole sample longitude ever more finely (tan(latitude) times the face's pixel there); None =
    ERP_POLE_SCALE. The result is on the CPU whatever the backend.

    backend: how each face is composited. "torch": render_gs.rasterize_tiles (differentiable). "numba": the same
    image from the numba kernel's compositing weights (render_gs.face_weights; several times faster on CPU, equal to
    "torch" within 1e-5, no gradient: a ValueError when a Gaussian tensor requires grad and grad is enabled).
    "gsplat": CUDA (a face's depth is its expected z turned into distance along each pixel's ray). "auto": gsplat when
    the Gaussians are CUDA tensors and gsplat imports, else numba when no gradient is needed, else torch. The CPU
    paths project for each face only the Gaussians whose box can meet it (face_cull): the same render as projecting
    all of them on every face.

    pixels (H, W) bool: only these pixels are rendered, each with its value: the cube faces that sample none of them
    are not rendered, and the numba path composites only the face pixels their samples read (every other pixel holds
    0 or a part of its value).
    """
    if backend not in ("auto", "torch", "numba", "gsplat"):
        raise ValueError(f"backend={backend!r} but expected 'auto', 'torch', 'numba' or 'gsplat'")
    faces = erp_faces(world_from_cam, H, W, face_size=face_size, margin=margin, supersample=supersample,
                      pole_scale=pole_scale)
    if pixels is not None:
        keep = np.asarray(pixels, bool)
        if keep.shape != (H, W):
            raise ValueError(f"pixels.shape={keep.shape} but expected {(H, W)}")
        s = int(supersample)
        keep = torch.from_numpy(np.repeat(np.repeat(keep, s, 0), s, 1).reshape(-1))
        faces = [fc for fc in faces if bool(keep[fc.index].any())]
        need = {id(fc): face_taps(fc, keep[fc.index].numpy()) for fc in faces}
    if _use_gsplat(gaussians, backend):
        return _compose_erp(faces, H, W, supersample, lambda fc: _gsplat_face(gaussians, fc, near, background))
    grad = _needs_grad(gaussians)
    if backend == "numba" and grad:
        raise ValueError("backend='numba' renders without gradients but a Gaussian tensor requires grad: use 'torch'")
    centre = np.asarray(world_from_cam, dtype=np.float64)[:3, 3]
    bg = _background(background)
    if pixels is not None and faces and not grad:  # only what the faces rendered can show is prepared: the same render
        terms = cull_terms(gaussians.means, gaussians.opacities, gaussians.scales, centre)
        cand = torch.unique(torch.cat([face_candidates(*terms, fc, near) for fc in faces]))
        del terms
        gaussians = gaussians.subset(cand.numpy() if isinstance(gaussians.means, np.ndarray) else cand)
    rasterise = backend == "torch" or grad
    with contextlib.nullcontext() if rasterise else torch.no_grad():
        prep = _prepare(gaussians, centre)
        cull = face_cull(prep, gaussians.scales, centre, near)
        if rasterise:

            def torch_face(fc: ErpFace) -> RenderOutput:
                proj = project(cull(fc)[0], invert_pose(fc.world_from_face), fc.f, fc.f, fc.c, fc.c, fc.n, fc.n, near)
                return rasterize_tiles(proj, fc.n, fc.n, bg, raw=True, distance=True)

            return _compose_erp(faces, H, W, supersample, torch_face)
        # the faces on torch's threads: the kernel releases the GIL
        return _compose_erp(faces, H, W, supersample,
                            lambda fc: _numba_face(cull(fc)[0], fc, near, bg, None if pixels is None else need[id(fc)]),
                            max(1, torch.get_num_threads()))


@torch.no_grad()  # grad mode is per thread: render_erp's worker threads do not inherit its no_grad
def _numba_face(prep: _Prepared, fc: ErpFace, near: float, bg: torch.Tensor, need: np.ndarray | None = None
                ) -> RenderOutput:
    """One cube face raw as rasterize_tiles(raw=True, distance=True) returns it (render_gs.rasterize_numba), only on
    the face pixels `need` (n * n,) bool when given."""
    proj = project(prep, invert_pose(fc.world_from_face), fc.f, fc.f, fc.c, fc.c, fc.n, fc.n, near)
    return rasterize_numba(proj, fc.n, fc.n, bg, raw=True, distance=True, need=need)


def face_taps(fc: ErpFace, samples: np.ndarray) -> np.ndarray:
    """(n * n,) bool: the face pixels that ErpFace.sample's bilinear taps of its samples where samples (K,) bool read,
    and their neighbours (a margin for grid_sample's rounding)."""
    n = fc.n
    g = fc.grid.numpy().astype(np.float64)[np.asarray(samples, bool)]
    lo = np.floor(np.clip(((g + 1.0) * n - 1.0) / 2.0, 0.0, n - 1.0)).astype(np.int64)
    out = np.zeros((n, n), bool)
    for dy in (-1, 0, 1, 2):
        for dx in (-1, 0, 1, 2):
            out[np.clip(lo[:, 1] + dy, 0, n - 1), np.clip(lo[:, 0] + dx, 0, n - 1)] = True
    return out.reshape(-1)


def _compose_erp(faces: list[ErpFace], H: int, W: int, supersample: int, render_face, workers: int = 1) -> RenderOutput:
    """render_erp's resampling: each face's raw render (rgb over the background, sum of weight x distance, alpha),
    rendered on `workers` threads."""
    s = int(supersample)
    out = torch.zeros(5, s * H * s * W)
    if workers > 1:
        with ThreadPoolExecutor(workers) as pool:
            renders = list(pool.map(render_face, faces))
    else:
        renders = map(render_face, faces)
    for fc, face in zip(faces, renders):
        out[:, fc.index] = fc.sample(torch.cat([face.rgb, face.depth[..., None], face.alpha[..., None]], -1))
    out = out.reshape(5, s * H, s * W)
    if s > 1:
        out = F.avg_pool2d(out[None], s)[0]
    alpha = out[4]
    depth = torch.where(alpha > 0, out[3] / alpha.clamp(min=1e-12), torch.zeros_like(alpha))
    return RenderOutput(out[:3].permute(1, 2, 0).contiguous(), depth, alpha)


def _gsplat_face(gaussians: Gaussians, fc: ErpFace, near: float, background) -> RenderOutput:
    """One cube face through gsplat, raw as rasterize_tiles(raw=True, distance=True) returns it, on the CPU."""
    out = _render_gsplat(gaussians, fc.world_from_face, fc.f, fc.f, fc.c, fc.c, fc.n, fc.n, near, background)
    t = (torch.arange(fc.n, dtype=torch.float32) + 0.5 - fc.c) / fc.f
    ray_length = torch.sqrt(t[None, :] ** 2 + t[:, None] ** 2 + 1)
    alpha = out.alpha.float().cpu()
    return RenderOutput(out.rgb.float().cpu(), out.depth.float().cpu() * ray_length * alpha, alpha)
