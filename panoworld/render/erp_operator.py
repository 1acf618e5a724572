"""The ERP render of fixed Gaussians as a sparse linear map of their colours (the colour fit's operator), optionally only on some pixels."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from numba import njit

from panoworld.core.conventions import invert_pose
from panoworld.io.gaussian_set import Gaussians
from panoworld.render.erp import ERP_SUPERSAMPLE, ErpFace, erp_faces, face_cull
from panoworld.render.splats import TILE, _Prepared, covariance_3d, face_weights, project


def _sampling(fc: ErpFace, rows: np.ndarray):
    """grid_sample's bilinear taps (align_corners False, border padding) of the face samples `rows` as a sparse
    (len(rows), n * n) matrix."""
    import scipy.sparse

    g = fc.grid.numpy().astype(np.float64)[rows]
    n = fc.n
    xy = np.clip(((g + 1.0) * n - 1.0) / 2.0, 0.0, n - 1.0)
    lo = np.floor(xy).astype(np.int64)
    fr = xy - lo
    r, cols, vals = [], [], []
    ar = np.arange(len(rows))
    for dy in (0, 1):
        for dx in (0, 1):
            w = (fr[:, 0] if dx else 1 - fr[:, 0]) * (fr[:, 1] if dy else 1 - fr[:, 1])
            x, y = lo[:, 0] + dx, lo[:, 1] + dy
            ok = (w > 0) & (x < n) & (y < n)
            r.append(ar[ok])
            cols.append((y * n + x)[ok])
            vals.append(w[ok])
    return scipy.sparse.csr_matrix((np.concatenate(vals).astype(np.float32), (np.concatenate(r), np.concatenate(cols))),
                                   shape=(len(rows), n * n))


class ErpColorOperator:
    """The ERP render of Gaussians at one pose as a linear map A of their colours (geometry fixed, black background):
    each cube face's compositing weights and its bilinear resampling as sparse matrices, pooled as render_erp does.
    A(colors (N, 3)) -> (H, W, 3); adjoint(image (H, W, 3)) -> A^T image (N, 3).

    mask (H, W) bool: only those ERP pixels are rendered (0 elsewhere): the face pixels their samples read are the
    only ones composited, and each face projects only the Gaussians whose box can meet it (erp_render.face_cull), so a view
    that counts only part of its pixels costs that part. On the kept pixels it equals the operator without a mask.
    tile: the weights kernel's tile size (face_weights); cov: the Gaussians' covariance_3d when already at hand.
    prune in [0, 1): each face pixel drops its smallest weights while their sum stays within this share of the
    pixel's total weight (prune_weights), so a render through the operator is off by at most that share of the
    brightest colour; 0 keeps every weight."""

    def __init__(self, gaussians: Gaussians, world_from_cam: np.ndarray, H: int, W: int, *,
                 supersample: int = ERP_SUPERSAMPLE, near: float = 0.01, pole_scale: float | None = None,
                 mask: np.ndarray | None = None, tile: int = TILE, cov: torch.Tensor | None = None,
                 prune: float = 0.0):
        import scipy.sparse

        if not 0.0 <= prune < 1.0:
            raise ValueError(f"prune={prune!r} but expected a share in [0, 1)")

        faces = erp_faces(world_from_cam, H, W, supersample=supersample, pole_scale=pole_scale)
        s = self.s = int(supersample)
        self.H, self.W, self.N = H, W, len(gaussians)
        means, opacity = torch.as_tensor(gaussians.means).float(), torch.as_tensor(gaussians.opacities).float()
        if cov is None:
            cov = covariance_3d(torch.as_tensor(gaussians.scales).float(), torch.as_tensor(gaussians.quats).float())
        prep = _Prepared(means, cov, opacity, torch.zeros(1, 3).expand(len(means), 3))  # colours: the operand
        cull = face_cull(prep, np.asarray(gaussians.scales, np.float32), np.asarray(world_from_cam)[:3, 3], near)
        keep_px = None
        if mask is not None:
            keep = np.asarray(mask, bool)
            if keep.shape != (H, W):
                raise ValueError(f"mask.shape={keep.shape} but expected {(H, W)}")
            keep_px = np.repeat(np.repeat(keep, s, 0), s, 1).reshape(-1)  # the supersampled samples kept

        def build(fc: ErpFace):
            index = fc.index.numpy()
            rows = np.arange(len(index)) if keep_px is None else np.flatnonzero(keep_px[index])
            if not len(rows):
                return None
            S = _sampling(fc, rows)
            need = np.zeros(fc.n * fc.n, bool)
            need[S.indices] = True
            sub, cand = cull(fc)
            proj = project(sub, invert_pose(fc.world_from_face), fc.f, fc.f, fc.c, fc.c, fc.n, fc.n, near)
            pix, gid, w = face_weights(proj, fc.n, fc.n, need=None if keep_px is None else need, tile=tile)
            # scipy: COO -> CSR is a counting sort, 32-bit indices, and the transpose a free CSC view
            A = scipy.sparse.csr_matrix((w, (pix, cand.numpy().astype(np.int32)[proj.index.numpy()[gid]])),
                                        shape=(fc.n * fc.n, self.N))
            if prune > 0:
                A = prune_weights(A, prune)
            return index[rows], S, A

        # The faces on torch's threads (the kernel releases the GIL), the largest (the pole faces) first.
        with ThreadPoolExecutor(max(1, torch.get_num_threads())) as pool:
            by_size = sorted(range(len(faces)), key=lambda k: -faces[k].n)
            done = dict(zip(by_size, pool.map(build, [faces[k] for k in by_size])))
        self.faces = [done[k] for k in range(len(faces)) if done[k] is not None]

    def restricted(self, cols: np.ndarray) -> ErpColorOperator:
        """The same operator on the Gaussians `cols` (sorted indices) alone, A's columns renumbered: colours (len(cols),
        3) in, A^T image (len(cols), 3) out. A ValueError when a Gaussian not in cols has a weight."""
        import copy

        import scipy.sparse

        remap = np.full(self.N, -1, np.int32)
        remap[np.asarray(cols)] = np.arange(len(cols), dtype=np.int32)
        out = copy.copy(self)
        out.N, out.faces = len(cols), []
        for index, S, A in self.faces:
            j = remap[A.indices]
            if len(j) and j.min() < 0:
                raise ValueError("a Gaussian with a weight is not in cols")
            out.faces.append((index, S, scipy.sparse.csr_matrix((A.data, j, A.indptr), shape=(A.shape[0], len(cols)))))
        return out

    def read_rows(self) -> ErpColorOperator:
        """The same operator holding only the face pixels some ERP sample reads (A's other rows, a pole face's corners
        and the margins, dropped; S's columns renumbered): the same products to the last bit, in less memory."""
        import copy

        import scipy.sparse

        out = copy.copy(self)
        out.faces = []
        for index, S, A in self.faces:
            read = np.zeros(A.shape[0], bool)
            read[S.indices] = True
            rows = np.flatnonzero(read)
            renum = np.cumsum(read, dtype=np.int32) - 1
            S = scipy.sparse.csr_matrix((S.data, renum[S.indices], S.indptr), shape=(S.shape[0], len(rows)))
            out.faces.append((index, S, A[rows]))
        return out

    def __call__(self, colors: torch.Tensor) -> torch.Tensor:
        c = np.ascontiguousarray(colors.detach().numpy(), np.float32)
        out = np.zeros((self.s * self.H * self.s * self.W, 3), np.float32)
        for (index, _, _), face in zip(self.faces, self._per_face(lambda f: _times(f[1], _times(f[2], c)))):
            out[index] = face
        out = out.reshape(self.H, self.s, self.W, self.s, 3).mean((1, 3)) if self.s > 1 else \
            out.reshape(self.H, self.W, 3)
        return torch.from_numpy(np.ascontiguousarray(out))

    def adjoint(self, image: torch.Tensor) -> torch.Tensor:
        r = image.detach().numpy().astype(np.float32)
        if self.s > 1:  # the pooling's adjoint: each sample gets its pixel's value / s^2
            r = np.broadcast_to(r[:, None, :, None] / self.s**2, (self.H, self.s, self.W, self.s, 3))
        r = np.ascontiguousarray(r, np.float32).reshape(-1, 3)
        return torch.from_numpy(sum(self._per_face(lambda f: _times_t(f[2], _times_t(f[1], r[f[0]]))),
                                    np.zeros((self.N, 3), np.float32)))

    def _per_face(self, fn) -> list:
        """fn((sample index, sampling, weights)) for every face, in face order, on torch's threads (scipy's sparse
        products release the GIL)."""
        with ThreadPoolExecutor(max(1, torch.get_num_threads())) as pool:
            return list(pool.map(fn, self.faces))


def prune_weights(m, share: float):
    """The CSR matrix m (rows, cols) float32 without, in each row, its smallest entries whose sum stays within share
    of the row's sum (ties: the earlier entry first); the others keep their order."""
    import scipy.sparse

    keep = np.ones(len(m.data), bool)
    indptr = np.zeros_like(m.indptr)
    _prune_rows(m.indptr, m.data, np.float64(share), keep, indptr)
    return scipy.sparse.csr_matrix((m.data[keep], m.indices[keep], indptr), shape=m.shape)


@njit(cache=True, nogil=True)
def _prune_rows(indptr, data, share, keep, out_indptr):
    """keep[p] = False for prune_weights' dropped entries; out_indptr: the kept entries' row pointers."""
    for i in range(indptr.shape[0] - 1):
        a, b = indptr[i], indptr[i + 1]
        kept = b - a
        if kept > 1:
            row = data[a:b].astype(np.float64)
            budget = share * row.sum()
            dropped = 0.0
            for k in np.argsort(row, kind="mergesort"):
                dropped += row[k]
                if dropped > budget:
                    break
                keep[a + k] = False
                kept -= 1
        out_indptr[i + 1] = out_indptr[i] + kept


def _times(m, x: np.ndarray) -> np.ndarray:
    """m @ x for a CSR matrix m (float32) and x (cols, 3) float32: scipy's product, the same sums in the same order."""
    out = np.zeros((m.shape[0], 3), np.float32)
    _csr_times(m.indptr, m.indices, m.data, x, out)
    return out


def _times_t(m, y: np.ndarray) -> np.ndarray:
    """m.T @ y for a CSR matrix m (float32) and y (rows, 3) float32: scipy's product, the same sums in the same order."""
    out = np.zeros((m.shape[1], 3), np.float32)
    _csr_times_t(m.indptr, m.indices, m.data, np.ascontiguousarray(y), out)
    return out


@njit(cache=True, nogil=True)
def _csr_times(indptr, indices, data, x, out):
    for i in range(indptr.shape[0] - 1):
        a0, a1, a2 = out[i, 0], out[i, 1], out[i, 2]
        for p in range(indptr[i], indptr[i + 1]):
            j, w = indices[p], data[p]
            a0 += w * x[j, 0]
            a1 += w * x[j, 1]
            a2 += w * x[j, 2]
        out[i, 0], out[i, 1], out[i, 2] = a0, a1, a2


@njit(cache=True, nogil=True)
def _csr_times_t(indptr, indices, data, y, out):
    for i in range(indptr.shape[0] - 1):
        y0, y1, y2 = y[i, 0], y[i, 1], y[i, 2]
        for p in range(indptr[i], indptr[i + 1]):
            j, w = indices[p], data[p]
            out[j, 0] += w * y0
            out[j, 1] += w * y1
            out[j, 2] += w * y2
