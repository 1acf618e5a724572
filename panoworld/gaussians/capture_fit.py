"""A home's colours fitted at every capture point: least-squares (degree-1 SH) colours so the scene reproduces each panorama."""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from panoworld.core.memory import release_free_memory
from panoworld.io.gaussian_set import Gaussians, rgb_to_sh_dc
from panoworld.render.metrics import psnr

FIT_TILE = 8
"""The operators' weights-kernel tile (render.splats.face_weights): fewer Gaussians scanned per pixel than the
rasteriser's 16, the same weights."""
PIXEL_WEIGHT = 0.25
"""A Gaussian's typical compositing weight in a pixel it covers: its colour's data term is about this times its
compositing weight over the views (the damping's unit), which sets the preconditioner of the degree-1 terms."""


def sh1_basis(means: np.ndarray, centre: np.ndarray) -> torch.Tensor:
    """(N, 3) degree-1 SH basis SH_C1 (-y, z, -x) of the unit direction (x, y, z) from centre (3,) to each of means
    (N, 3): the weights of a Gaussian's three f_rest coefficients in the colour seen from there (render.splats.eval_sh)."""
    from panoworld.render.splats import _SH_C1

    d = torch.as_tensor(np.asarray(means, np.float32) - np.asarray(centre, np.float32))
    d = d / d.norm(dim=1, keepdim=True).clamp(min=1e-12)
    return _SH_C1 * torch.stack([-d[:, 1], d[:, 2], -d[:, 0]], 1)


def fit_capture_colors(g: Gaussians, views: list[tuple[np.ndarray, np.ndarray]], *, height: int = 256,
                       supersample: int = 2, iters: int = 20, damping: float = 0.01, sh_degree: int = 1,
                       sh_damping: float = 0.001, max_bytes: float = float("inf"), prune: float = 0.0,
                       smooth: bool = False, min_psnr: float = 0.0, max_rounds: int = 1, progress: bool = False
                       ) -> tuple[Gaussians, dict]:
    """Gaussians g whose colours are refitted so their ERP render (height rows, supersample: render_erp's sampling)
    at each view's world_from_cam (4, 4) reproduces its target (H, W, 3) uint8 or [0, 1], area-resized to height rows.

    For fixed geometry each render is linear in the colours (render.erp_operator.ErpColorOperator), so this is
    `iters` steps of Jacobi-preconditioned conjugate-gradient least squares over all views at once (each unknown
    scaled by the square root of its compositing weight over the views): min sum_k |A_k c_k - y_k|^2 +
    damping |c - c0|^2 + sh_damping |s - s0|^2, the damping per unit of each Gaussian's compositing weight (Gaussians
    the views barely see keep their colours). With sh_degree 1 view k sees c_k = c + (B_k - B) s: s the degree-1
    coefficients, B_k their basis in the direction from view k (sh1_basis) and B its mean over the views weighted by
    what each sees of the Gaussian, so c is the colour from that mean direction and s only tells the views apart: a
    surface two capture points see differently shows each its own colour, one that a single view sees keeps s. Only
    the Gaussians some view sees are fitted; prune: the share of each pixel's weight its render operator may drop
    (ErpColorOperator). smooth: the change to the colours and to the degree-1 terms is then made one the views' renders
    hold (smooth_change); then, while a view's render reads below min_psnr (dB, against its target at height rows),
    another round (up to max_rounds in all): `iters` more steps over the Gaussians those views see alone, from the
    smoothed colours, the change smoothed again. progress: a bar (core.progress.bar) through each operator built, each
    step, the smoothing. Returns the Gaussians (SH degree max(sh_degree, g's)) and {"views", "height", "iters",
    "prune", "sh_degree", "fitted", "operators_gb" (what the render operators held), "rmse_before", "rmse_after" (per
    view), "rounds" (one list per further round: the views it was for)}; g itself and
    {"views", "skipped": why} when the operators built so far say all of them would hold more than max_bytes."""
    import cv2

    from panoworld.core.progress import bar as progress_bar
    from panoworld.render.erp_operator import ErpColorOperator
    from panoworld.render.splats import covariance_3d

    if sh_degree not in (0, 1):
        raise ValueError(f"sh_degree={sh_degree!r} but expected 0 or 1")
    targets = []
    for img, _ in views:
        img = np.asarray(img)
        y = img.astype(np.float32) / (255.0 if img.dtype == np.uint8 else 1.0)
        if y.shape[0] != height:
            y = cv2.resize(y, (2 * height, height), interpolation=cv2.INTER_AREA)
        targets.append(torch.from_numpy(np.ascontiguousarray(y)))
    cov = covariance_3d(torch.as_tensor(g.scales).float(), torch.as_tensor(g.quats).float())
    # Each view is held on the Gaussians it sees alone (ops[k] restricted to mine[k]; seen_k[k]: its compositing
    # weight of each of them), so what the fit holds grows with the views' pixels, not with views x Gaussians.
    ops, seen_k, mine = [], [], []
    seen_any = np.zeros(len(g), bool)
    held = 0
    bar = progress_bar(total=len(views) + iters + int(smooth), desc=f"capture fit at {height} rows: operators",
                       unit="step", on=progress, leave=False)
    for _, pose in views:
        op = ErpColorOperator(g, pose, height, 2 * height, supersample=supersample, cov=cov, tile=FIT_TILE, prune=prune)
        seen = np.zeros(len(g), bool)
        for f in op.faces:
            seen[f[2].indices] = True
        mine.append(np.flatnonzero(seen))
        seen_any |= seen
        ops.append(op.restricted(mine[-1]).read_rows())
        del op, seen
        release_free_memory()  # the build's temporaries, so what the fit holds is what stays resident
        held += operator_nbytes(ops[-1])
        if held / len(ops) * len(views) > max_bytes:
            bar.close()
            return g, {"views": len(views), "skipped": f"the render operators of the {len(views)} capture poses would "
                       f"hold about {held / len(ops) * len(views) / 1e9:.1f} GB, more than {max_bytes / 1e9:.1f} GB"}
        seen_k.append(ops[-1].adjoint(torch.ones(height, 2 * height, 3))[:, 0].clone())
        bar.update()
    del cov
    # The unknowns are those of the Gaussians some view sees (the others' gradient is 0: they keep their colours),
    # and each view's products run over the Gaussians it sees alone (cols[k], positions among the seen).
    fit = np.flatnonzero(seen_any)
    n, views_n = len(fit), len(ops)
    cols = [np.searchsorted(fit, m).astype(np.int64) for m in mine]
    del mine
    cols_t = [torch.from_numpy(c) for c in cols]

    def scatter(term, width):  # term(k): view k's (len(cols[k]), width) per Gaussian, summed over the views in order
        out = torch.zeros(n, width)
        for k in range(views_n):
            out.index_add_(0, cols_t[k], term(k))
        return out

    total = scatter(lambda k: seen_k[k][:, None], 1)
    weight = total if smooth else None  # each Gaussian's compositing weight over the views, smooth_change's divisor
    seen = total.clamp(min=1e-3)
    total = torch.where(total > 0, total, 1.0)  # the weighted means below, exact where the weights are small
    s0 = np.zeros((n, 3, 3), np.float32)
    s0[:, : min(3, g.sh_rest.shape[1])] = np.asarray(g.sh_rest, np.float32)[fit, :3]
    s0 = torch.from_numpy(s0)
    means = np.asarray(g.means)[fit]

    def b(k):  # view k's degree-1 basis of the Gaussians it sees
        return sh1_basis(means[cols[k]], np.asarray(views[k][1])[:3, 3])

    b_mean = scatter(lambda k: seen_k[k][:, None] * b(k), 3) / total
    c0 = torch.from_numpy(g.base_colors()[fit]) + torch.einsum("nj,njc->nc", b_mean, s0)
    if sh_degree:
        # the unknowns are s times rho, each Gaussian's RMS basis change over the views lifted by the damping
        # (a diagonal preconditioner: the data and the damping of each unknown then weigh about alike)
        rho = scatter(lambda k: seen_k[k][:, None] * (b(k) - b_mean[cols_t[k]]).square(), 3).sum(1, keepdim=True)
        rho = rho / total
        one_way = rho < 1e-6  # seen from one direction (one view): s does not reach the colours
        rho = (rho + sh_damping / PIXEL_WEIGHT).sqrt()
        basis = [torch.where(one_way[c], 0.0, b(k) - b_mean[c]) / rho[c] for k, c in enumerate(cols_t)]
        x0 = torch.cat([c0, (s0 * rho[:, :, None]).reshape(n, 9)], 1)
        lam = [damping * seen, sh_damping * seen / rho.square()]  # per Gaussian: of its colour, of its s
        del one_way, s0
    else:
        basis = [b(k) - b_mean[c] for k, c in enumerate(cols_t)]
        s0_k = [s0[c] for c in cols]
        x0, lam = c0, [damping * seen]
    seen_k.clear()
    # Jacobi: the unknowns are x / dsc, dsc^-2 about each one's normal-matrix diagonal (its data term and its damping
    # both grow with its compositing weight), so a Gaussian a few pixels wide converges as fast as a wall-sized one
    dsc = seen.rsqrt()
    x0 = x0 / dsc
    lam = [lam_i * dsc.square() for lam_i in lam]
    del total, seen
    means = None
    cols = cols_t

    def damp(t):  # t (n, 12 or 3) times each unknown's damping, in place
        t[:, :3].mul_(lam[0])
        if sh_degree:
            t[:, 3:].mul_(lam[1])
        return t

    def colors(k, x):  # the unknowns (n, 3 or 12) -> the colours view k sees (len(cols[k]), 3)
        if sh_degree:
            return torch.from_numpy(_view_colors(x.numpy(), cols[k].numpy(), basis[k].numpy()))
        return x[cols[k]] + torch.einsum("nj,njc->nc", basis[k], s0_k[k])

    def lin(k, p):  # view k's render of p (n, 12 or 3), colours and degree-1 terms (unknowns times dsc)
        return ops[k](colors(k, p) if sh_degree else p[cols[k]])

    def grad(r, out):  # the adjoint of the views' renders of the residuals r (per view (H, W, 3)), as the unknowns
        out.zero_()
        for k in range(views_n):
            gc = ops[k].adjoint(r[k])
            if sh_degree:
                _add_view_grad(out.numpy(), cols[k].numpy(), gc.numpy(), basis[k].numpy())
            else:
                out.index_add_(0, cols[k], gc)
        return out.mul_(dsc)

    # Conjugate gradients on the normal equations, the (n, 12) vectors updated in place (tmp: scratch)
    s, tmp = torch.empty_like(x0), torch.empty_like(x0)
    rmse0 = None

    def steps(start: torch.Tensor, only: torch.Tensor | None = None) -> torch.Tensor:
        """`iters` CG steps from the unknowns start, damped towards x0; only (n, 1): the unknowns that may change."""
        nonlocal rmse0
        x = start.clone() if start is x0 else start  # a further round's start is a temporary of its own
        r = [targets[k] - lin(k, x * dsc) for k in range(views_n)]
        if rmse0 is None:
            rmse0 = [float(rk.square().mean().sqrt()) for rk in r]
        grad(r, s).sub_(damp(torch.sub(x, x0, out=tmp)))
        if only is not None:
            s.mul_(only)
        p, gamma = s.clone(), float(torch.mul(s, s, out=tmp).sum())
        bar.set_description(f"capture fit at {height} rows: steps")
        for _ in range(iters):
            q = [lin(k, torch.mul(p, dsc, out=tmp)) for k in range(views_n)]
            damped = damp(torch.mul(p, p, out=tmp)).sum()
            alpha = gamma / max(float(sum(qk.square().sum() for qk in q) + damped), 1e-20)
            x.add_(torch.mul(p, alpha, out=tmp))
            r = [r[k] - alpha * q[k] for k in range(views_n)]
            grad(r, s).sub_(damp(torch.sub(x, x0, out=tmp)))
            if only is not None:
                s.mul_(only)
            gamma_new = float(torch.mul(s, s, out=tmp).sum())
            p.mul_(gamma_new / max(gamma, 1e-20)).add_(s)
            gamma = gamma_new
            bar.update()
        return x.mul_(dsc)

    def smoothed(x: torch.Tensor, start: torch.Tensor) -> torch.Tensor:  # x's change from start as the renders hold it
        x[:, :3] = start[:, :3] + smooth_change(x[:, :3] - start[:, :3], ops, cols, weight, covers)
        for j in range(3, x.shape[1], 3):  # each degree-1 term's change, as coefficients (x holds them times rho)
            x[:, j:j + 3] = start[:, j:j + 3] + smooth_change((x[:, j:j + 3] - start[:, j:j + 3]) / rho, ops, cols,
                                                              weight, covers) * rho
        return x

    x = steps(x0)
    rounds: list[list[int]] = []
    if smooth:
        bar.set_description(f"capture fit at {height} rows: smoothing")
        covers = coverages(ops, cols)
        start = x0 * dsc
        start[:, :3] = c0
        x = smoothed(x, start)
        bar.update()
        while len(rounds) + 1 < max_rounds:
            low = [k for k in range(views_n)
                   if psnr(ops[k](colors(k, x)).clamp(0.0, 1.0).numpy(), targets[k].numpy(), data_range=1.0) < min_psnr]
            if not low:
                break
            rounds.append(low)
            only = torch.zeros(n, 1)
            for k in low:
                only[cols_t[k]] = 1.0
            bar.total += iters + 1
            start = x
            x = smoothed(torch.where(only > 0, steps(start / dsc, only), start), start)  # the rest exactly as was
            bar.update()
        covers = start = None
    bar.close()
    x[:, :3] = x[:, :3].clamp(0.0, 1.0)
    s = tmp = x0 = None  # steps' scratch and anchor, freed before the final renders
    c0 = weight = None
    lam.clear()
    rmse1 = [float((targets[k] - ops[k](colors(k, x))).square().mean().sqrt()) for k in range(views_n)]
    for held_list in (ops, basis, targets):
        held_list.clear()
    coef = x[:, 3:].reshape(n, 3, 3) / rho[:, :, None] if sh_degree else s0
    dc = np.array(g.sh_dc, np.float32)  # only the Gaussians some view sees change
    dc[fit] = rgb_to_sh_dc((x[:, :3] - torch.einsum("nj,njc->nc", b_mean, coef)).numpy())
    rest = np.zeros((len(g), max(3 if sh_degree else 0, g.sh_rest.shape[1]), 3), np.float32)
    rest[:, : g.sh_rest.shape[1]] = g.sh_rest
    if sh_degree:
        rest[fit, :3] = coef.numpy()
    out = Gaussians(g.means, g.scales, g.quats, g.opacities, dc, rest)
    return out, {"views": views_n, "height": height, "prune": prune, "iters": iters, "sh_degree": sh_degree, "fitted": n,
                 "operators_gb": held / 1e9, "rmse_before": rmse0, "rmse_after": rmse1, "rounds": rounds}


def smooth_change(change: torch.Tensor, ops: list, cols: list[torch.Tensor], weight: torch.Tensor,
                  covers: list[torch.Tensor]) -> torch.Tensor:
    """The change (n, 3) of the fitted Gaussians' colours (or of one of their degree-1 terms) as the views hold it:
    rendered through each view's operator ops[k] (over the Gaussians cols[k] it sees), divided by that view's coverage
    (covers[k]: coverages), and read back, each Gaussian the weighted mean
    of the pixels it covers over the views that see it (weight (n, 1): its compositing weight summed over the views, the
    adjoint of a white image; unchanged where it is 0). The least-squares change also varies from Gaussian to Gaussian
    finer than the views' pixels (the solution picks it by where each Gaussian's centre falls between them), which
    renders as moire rings on plain walls from anywhere else."""
    num = torch.zeros_like(change)
    for op, c, cover in zip(ops, cols, covers):
        num.index_add_(0, c, op.adjoint(op(change[c].contiguous()) / cover))
    return torch.where(weight > 1e-6, num / weight.clamp(min=1e-6), change)


def coverages(ops: list, cols: list[torch.Tensor]) -> list[torch.Tensor]:
    """Each view's render of white Gaussians (H, W, 3), at least 1e-3: smooth_change's divisors."""
    return [op(torch.ones(len(c), 3)).clamp(min=1e-3) for op, c in zip(ops, cols)]


@njit(cache=True, nogil=True)
def _view_colors(x, cols, basis):
    """(len(cols), 3) float32: x[cols, :3] + sum_j basis[:, j] x[cols, 3 + 3 j:6 + 3 j] (x (n, 12): colour and
    degree-1 terms), summed in j order as torch's einsum("nj,njc->nc") of the same arrays."""
    out = np.empty((cols.shape[0], 3), np.float32)
    for i in range(cols.shape[0]):
        r = cols[i]
        for c in range(3):
            acc = basis[i, 0] * x[r, 3 + c]
            acc += basis[i, 1] * x[r, 6 + c]
            acc += basis[i, 2] * x[r, 9 + c]
            out[i, c] = x[r, c] + acc
    return out


@njit(cache=True, nogil=True)
def _add_view_grad(out, cols, g, basis):
    """out[cols, :3] += g and out[cols, 3 + 3 j:6 + 3 j] += basis[:, j] g (g (len(cols), 3): one view's adjoint of
    its colours; cols unique), in place: _view_colors' adjoint."""
    for i in range(cols.shape[0]):
        r = cols[i]
        for c in range(3):
            out[r, c] += g[i, c]
        for j in range(3):
            b = basis[i, j]
            for c in range(3):
                out[r, 3 + 3 * j + c] += b * g[i, c]


def operator_nbytes(op) -> int:
    """Bytes an ErpColorOperator holds (its faces' sample indices and sparse sampling and weight matrices)."""
    return sum(index.nbytes + sum(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes for m in (S, A))
               for index, S, A in op.faces)
