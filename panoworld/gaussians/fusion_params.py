"""Settings of the voxel-fusion backend, importable without torch (stage modules build their CLI from them)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from panoworld.core.params import param


class Confidence(enum.StrEnum):
    """Non-learned per-pixel confidence w of the voxel-fusion backend."""

    UNIFORM = "uniform"
    """w = 1: every pixel one vote (views closer to a surface sample it more densely and so dominate)."""
    AREA = "area"
    """w = footprint area of the pixel on the surface: surface-area-weighted moments, every view counts equally."""
    RESOLUTION = "resolution"
    """w = cos(grazing angle) / depth^2: frontal, close (sharper) observations dominate."""


@dataclass(kw_only=True)
class FusionParams:
    """Settings of the non-learned voxel-fusion backend."""

    voxel_size: float = param(0.02, gt=0)
    """Voxel edge length in metres (the paper's epsilon)."""
    per_voxel: int = param(1, ge=1)
    """Gaussians per occupied voxel, K in {1, 2, 4, 8}: the voxel's samples are split in two along each of its
    log2(K) principal axes and every non-empty part becomes one Gaussian."""
    confidence: Confidence = Confidence.RESOLUTION
    """Per-pixel confidence weight used in the fusion."""
    min_points: int = param(1, ge=1)
    """Prune voxels (and sub-voxel parts) observed by fewer pixels than this."""
    scale_factor: float = param(1.6, gt=0)
    """Gaussian standard deviation = scale_factor * sqrt(eigenvalue of the fused covariance)."""
    min_scale: float = param(0.05, gt=0)
    """Lower clamp of every Gaussian scale, as a fraction of voxel_size (keeps surfels from being degenerate)."""
    max_scale: float = param(1.0, gt=0)
    """Upper clamp of every Gaussian scale, as a multiple of voxel_size."""
    opacity: float = param(0.98, gt=0, le=1)
    """Opacity of every emitted Gaussian."""
    min_cos: float = param(0.08, ge=0, le=1)
    """Drop pixels seen at grazing angles with |cos| below this (depth discontinuities, flying pixels)."""
    max_depth: float = param(0.0, ge=0)
    """Drop pixels with depth beyond this many metres (0 = keep all)."""

    def check(self) -> None:
        if not self.voxel_size > 0:
            raise ValueError(f"voxel_size={self.voxel_size} but expected > 0")
        if self.per_voxel not in (1, 2, 4, 8):
            raise ValueError(f"per_voxel={self.per_voxel} but expected one of 1, 2, 4, 8")
        if self.min_points < 1:
            raise ValueError(f"min_points={self.min_points} but expected >= 1")
        if not 0 < self.min_scale <= self.max_scale:
            raise ValueError(f"min_scale={self.min_scale}, max_scale={self.max_scale} but expected 0 < min <= max")
        if not 0 < self.opacity < 1:
            raise ValueError(f"opacity={self.opacity} but expected in (0, 1)")


@dataclass(kw_only=True)
class SourcePixelParams(FusionParams):
    """Settings of source-anchored fusion (gaussians.pixel, gaussians.home): the source view as one Gaussian per
    pixel, the other frames voxel-fused where it is blind, the colours fitted at the capture point."""

    source_height: int = param(640, ge=0)
    """ERP height of the source view's per-pixel Gaussians (0 = that of the other frames); rows near the poles keep
    every k-th pixel so kept pixels are about square on the sphere. More rows keep more of the input's detail for
    views from aside, at the cost of more Gaussians (quadratic in the rows)."""
    source_scale: float = param(2.1, gt=0)
    """Footprint scale of the source's per-pixel Gaussians (scale_factor of the voxel Gaussians otherwise): large
    enough that neighbours leave no see-through cracks between them (the renderer's 2x pole faces show cracks a
    smaller footprint leaves), small enough to keep the input's detail."""
    unseen_voxel_size: float = param(0.04, ge=0)
    """With source_pixels: voxel edge (metres) of what the other frames see that the source does not (0 =
    voxel_size). That is the generated (disoccluded) content, softer than the input: 4 cm voxels hold it with fewer,
    larger Gaussians and fewer see-through gaps than 2 cm."""
    source_tol: float = param(0.03, gt=0)
    """Observations of the other frames within this relative depth of the source's surface (or in front of it) count
    as seen by the source and are not fused."""
    source_complete: bool = False
    """A home: a panorama's pixels without depth (implausible layout masked, a doorway line through another capture
    point dropped) take the depth of the nearest surface the other panoramas see along their ray
    (gaussians.home.complete_from_others), so the panorama's own colours stand there where it sees that surface
    nearest; without it the generated frames fill them. Off: with layout-only depth the nearest surface the others
    see along such a ray can lie behind a wall the panorama's own depth lacks (measured in docs/multi.md)."""
    source_carve_tol: float = param(0.0, ge=0)
    """A home: a panorama's pixel whose surface lies nearer than another panorama's depth along that panorama's ray by
    more than this (log range; the nearest of its 3 x 3 depths) is dropped: the other saw through it (a layout
    annotation's wall across a doorway, seen from the next room). 0 = not checked (the default: where two rooms'
    layout polygons disagree by a wall's thickness it drops real walls; measured in docs/multi.md)."""
    source_fill: bool = True
    """A home: a panorama's pixels without depth (implausible layout masked, a doorway line through another capture
    point dropped) get its own per-pixel Gaussians (gaussians.home.add_own_fill), placed in front of whatever else
    its capture point sees along their rays (at most the median of its own depth), only where no other panorama's
    depth explains them (on or in front of a surface another measured) and where they stand in front of no other
    panorama's fill seen from its capture point; the frames' voxel Gaussians in front of them are dropped. Which
    panorama keeps a surface stays decided by the measured depths alone; the capture fit then colours the
    panorama's own pixels where the frames' coarser Gaussians or another panorama's stood in (docs/multi.md)."""
    source_fill_height: int = param(640, ge=8)
    """ERP height of that fill (its render and per-pixel Gaussians; at most source_height). 640, source_height's: the
    fill is as sharp as the panorama's measured pixels beside it; halving it trades the capture views of panoramas
    with much depth missing for fewer Gaussians (measured in docs/multi.md)."""
    fit_iters: int = param(10, ge=0)
    """With source_pixels: conjugate-gradient steps of a colour fit at the capture point (0 = none): for the fixed
    geometry the ERP render there is linear in the Gaussians' colours, which are refitted (least squares, damped
    towards their fused values) so it reproduces the source frame, undoing the blur of overlapping splats
    (the manifest's color_fit holds the RMSE before and after). A home's colours: capture_fit_iters."""
    fit_height: int = param(512, ge=0)
    """ERP height of that fit's render and target (0 = source_height). 512: its cube faces are those of a 256-row
    render supersampled 2x (the roam protocol's), so the fit resolves what the eval's render shows."""
    fit_views: int = param(0, ge=0)
    """With fit_iters: that many other frames, spread over the path (farthest-point from the capture point), join the
    colour fit where they see what the source saw, so the source's colours are fitted from aside too (0 = the capture
    point only). Improves the seen part from aside; each view adds about a third of the colour fit's cost (its
    operator over every Gaussian the view sees). Off by default (docs/evaluation.md, options off by default)."""
    fit_view_height: int = param(256, ge=8)
    """ERP height of those frames' renders and targets in the fit."""
    fit_view_reach: float = param(2.0, ge=0)
    """Those frames are picked among the ones within this distance (metres) of the capture point (0 = any): where a
    user roams, not at the room's far walls."""
    fit_view_weight: float = param(1.0, ge=0)
    """Weight of each of those frames' pixels in the fit against 1 for the capture point's."""
    fit_sh_degree: int = param(0, ge=0, le=1)
    """With fit_views: 1 fits view-dependent colours too (degree-1 SH, written as f_rest_*), so the colours seen from
    those frames need not be the capture point's (0 = one colour per Gaussian). The joint fit may move the colours
    seen from the capture point; fit_views_sh_only keeps them."""
    fit_sh_damping: float = param(0.001, ge=0)
    """Damping of those degree-1 coefficients towards 0 per unit of compositing weight (the colours' is 0.01): a
    Gaussian seen from few directions keeps about one colour. A home's capture fit damps its own the same: more trades
    its capture poses for its novel views (measured in docs/multi.md)."""
    fit_views_sh_only: bool = False
    """With fit_sh_degree 1: the views fit the degree-1 coefficients only; the colours seen from the capture point
    are its own fit's (fit_views 0's), so the capture point renders exactly as without the views."""
    capture_fit_iters: int = param(5, ge=0)
    """A home: conjugate-gradient steps of a colour fit at every capture point (gaussians.capture_fit; 0 = none).
    For the fixed geometry the ERP render at each capture pose is linear in the colours, which are refitted by
    least squares over all capture poses at once (damped towards their fused values) so that each reproduces its
    panorama: where several panoramas see a surface, a panorama's Gaussians seen from another capture point show
    the texture where its own layout depth put it, and where a panorama has no depth the frames' coarser Gaussians
    stand in. The manifest's color_fit holds each panorama's RMSE before and after. The steps are preconditioned
    (Jacobi), so a few reach what plain steps reach in many; more fit the capture poses closer and the views between
    them no better (measured in docs/multi.md)."""
    capture_fit_damping: float = param(0.05, ge=0)
    """Damping of that fit's colours towards their fused values, per unit of each Gaussian's compositing weight. More
    keeps the colours nearer the fused ones, further from each capture pose's panorama (measured in
    docs/multi.md)."""
    capture_fit_smooth: bool = True
    """That fit's change to the colours and to their degree-1 terms is made one the capture poses' renders hold
    (capture_fit.smooth_change: rendered at each capture pose and read back, each Gaussian the mean of the pixels it
    covers). The least-squares change varies from Gaussian to Gaussian finer than the capture poses' pixels (most where
    two capture poses see a surface differently: each Gaussian leans towards either by how each pose's pixels happen to
    sample it), which shows as moire rings on plain walls in every other view. Smoothed, the views between the capture
    poses are sharper and the capture poses further from their panoramas (capture_fit_min_psnr bounds that; measured
    in docs/multi.md)."""
    capture_fit_min_psnr: float = param(29.0, ge=0)
    """With capture_fit_smooth: while a capture pose's render reads below this (dB, at capture_fit_height rows against
    its panorama) after the smoothing, the fit goes on for the Gaussians those poses see (capture_fit_iters more steps
    from the smoothed colours, the change smoothed again), up to capture_fit_max_rounds rounds in all; 0 = never."""
    capture_fit_max_rounds: int = param(3, ge=1, le=8)
    """The most rounds of that fit and its smoothing (1 = one)."""
    capture_fit_height: int = param(512, ge=8)
    """ERP height of that fit's renders and targets (the panoramas area-downsampled). 512: the cube faces of a
    256-row render supersampled 2x, so the fit resolves what a 256-row render shows (memory: capture_fit_max_gb)."""
    capture_fit_max_gb: float = param(6.0, gt=0)
    """The fit holds one render operator per capture pose at once: when the ones built so far say all of them would
    take more than this (GB), the fit prunes harder (capture_fit_prune_fallback), then runs at half the height (down
    to 64 rows), else it is skipped (colours as fused); the manifest's color_fit says what was refused and why. An
    operator at 512 rows with capture_fit_prune 0.002 holds about 0.17 GB per capture pose, so 6 GB holds about 36
    capture poses at 512 rows (about 48 at the fallback's pruning; docs/multi.md, Scale)."""
    capture_fit_prune: float = param(0.002, ge=0, lt=1)
    """Each face pixel of that fit's render operators drops its smallest compositing weights while their sum stays
    within this share of the pixel's total (render.erp_operator.prune_weights): a render through an operator is off by
    at most this share of the brightest colour. 0.002 drops about a third of the weights (the far tails of Gaussians
    and those nearly hidden); 0 keeps them all (measured in docs/multi.md)."""
    capture_fit_prune_fallback: float = param(0.01, ge=0, lt=1)
    """Where the operators at capture_fit_prune would exceed capture_fit_max_gb, the fit tries this share at the same
    height before it halves the height (not when it is no larger than capture_fit_prune): pruning harder costs the
    capture poses less than half the rows (measured in docs/multi.md)."""
    capture_fit_supersample: int = param(1, ge=1, le=4)
    """Supersampling of those renders (render.erp.ERP_SUPERSAMPLE's meaning; 1: pixel centres only)."""
    capture_fit_sh_degree: int = param(1, ge=0, le=1)
    """1: view-dependent colours (degree-1 SH, written as f_rest_*) so each capture point sees its own colour of a
    surface that several see; they tell the capture points apart only (a Gaussian seen from one keeps one colour,
    damped by fit_sh_damping). 0: one colour per Gaussian, the views' least-squares compromise."""
