"""voxel-fusion: no weights; the source view as one Gaussian per pixel, the other frames voxel-fused where it is blind."""

from __future__ import annotations

from dataclasses import dataclass

from panoworld.core.errors import InputError
from panoworld.core.params import param
from panoworld.core.registry import register
from panoworld.gaussians.fusion_params import FusionParams


@dataclass(kw_only=True)
class VoxelFusionOptions(FusionParams):
    source_pixels: bool = True
    """The source view (video frame 0; a home: every anchored panorama) becomes one Gaussian per pixel (its full
    detail at the capture point); the other frames are voxel-fused only where they see what the source does not."""
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
    fit_iters: int = param(10, ge=0)
    """With source_pixels: conjugate-gradient steps of a colour fit at the capture point (0 = none): for the fixed
    geometry the ERP render there is linear in the Gaussians' colours, which are refitted (least squares, damped
    towards their fused values) so it reproduces the source frame, undoing the blur of overlapping splats
    (the manifest's color_fit holds the RMSE before and after). Not applied to a home's panoramas."""
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
    Gaussian seen from few directions keeps about one colour."""
    fit_views_sh_only: bool = False
    """With fit_sh_degree 1: the views fit the degree-1 coefficients only; the colours seen from the capture point
    are its own fit's (fit_views 0's), so the capture point renders exactly as without the views."""
    back_sides: bool = True
    """With source_pixels and a navmesh input: upright source surfaces whose other side is in the line of sight of the
    walkable floor (within back_side_reach; what the source saw blocks the sight, unseen space does not) get a second
    layer of Gaussians back_side_thickness behind them, hidden from the capture point: a thin wall seen from the next
    room shows a back, not the source side's colour (panoworld/room/back_sides.py). The capture point's render is
    unchanged: the front covers its copy."""
    back_side_thickness: float = param(0.12, gt=0)
    """Metres behind the front surface (a wall's thickness; the synthetic walls are 0.15 m)."""
    back_side_reach: float = param(4.0, gt=0)
    """Metres of sight from the NavMesh to a wall's back."""
    back_side_shell: bool = True
    """Only surfaces on the room's shell get a back (panoworld.room.back_sides.on_shell: walls that meet the ceiling or
    floor in sight); off: the fronts of furniture too, whose unseen sides let the sight reach behind them."""
    back_side_edge_clear: bool = False
    """A back must lie behind the source depth within its thickness across its ray (back_sides.edge_clear), not
    only within 3 pixels: not seen past a doorway's jamb from views at 45 degrees. Stricter: it also drops the backs
    of walls the capture point sees at a grazing angle."""
    back_side_plane_clear: bool = False
    """A back must stay hidden when moved up to its thickness along its wall's plane (back_sides.plane_clear): not
    seen past a doorway's jamb, yet kept on walls the capture point sees at a grazing angle."""
    back_side_color: str = param("next_room", choices=("next_room", "front"))
    """next_room: the next room's wall colour the doorway shows (plane_colors.floor_beyond's; the front's where
    none is seen); front: the front's colour."""


def fuse(job):
    from panoworld.gaussians.fusion import voxel_fusion
    from panoworld.gaussians.pixel import source_anchored_fusion
    from panoworld.io.home import capture_poses

    o: VoxelFusionOptions = job.options
    if not o.source_pixels:
        return voxel_fusion(job.frames, o, progress=job.progress)
    captures = capture_poses(job.register)
    if len(captures) < 2:
        return source_anchored_fusion(job.frames, o, source_height=o.source_height, tol=o.source_tol,
                                      source_scale=o.source_scale, unseen_voxel_size=o.unseen_voxel_size,
                                      fit_iters=o.fit_iters, fit_height=o.fit_height, fit_views=o.fit_views,
                                      fit_view_height=o.fit_view_height, fit_view_reach=o.fit_view_reach,
                                      fit_view_weight=o.fit_view_weight, fit_sh_degree=o.fit_sh_degree,
                                      fit_sh_damping=o.fit_sh_damping, fit_views_sh_only=o.fit_views_sh_only,
                                      back_sides=back_side_hook(job),
                                      progress=job.progress)
    from panoworld.gaussians.home import home_anchored_fusion
    from panoworld.io.home import home_depth_dirs, load_sources

    dirs = home_depth_dirs(job.depth) if job.depth else None
    if dirs is None:
        raise InputError(f"{job.register}: the register artifact places several panoramas: give --depth, the home's "
                         "depth artifact (its panoramas are anchored)")
    names, rgbs, depths = load_sources(dirs, captures)
    return home_anchored_fusion(job.frames, {n: (rgbs[n], depths[n], captures[n]) for n in names}, o,
                                source_height=o.source_height, tol=o.source_tol, source_scale=o.source_scale,
                                unseen_voxel_size=o.unseen_voxel_size, progress=job.progress)


def back_side_hook(job):
    """source_anchored_fusion's back_sides callable for the job's options (None when off or without a NavMesh)."""
    o: VoxelFusionOptions = job.options
    if not o.back_sides or job.navmesh is None:
        return None
    from functools import partial

    from panoworld.geometry.navmesh import load_navmesh
    from panoworld.room.back_sides import back_side_layer

    return partial(back_side_layer, nav=load_navmesh(job.navmesh), thickness=o.back_side_thickness,
                   reach=o.back_side_reach, color=o.back_side_color, shell=o.back_side_shell,
                   edge=o.back_side_edge_clear, plane=o.back_side_plane_clear)


register("gaussians", "voxel-fusion", fuse, options=VoxelFusionOptions, key="voxel_fusion", weights=False)
