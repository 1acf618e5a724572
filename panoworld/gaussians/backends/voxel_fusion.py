"""voxel-fusion: no weights; the source view as one Gaussian per pixel, the other frames voxel-fused where it is blind."""

from __future__ import annotations

from dataclasses import dataclass

from panoworld.core.errors import InputError
from panoworld.core.params import param
from panoworld.core.registry import register
from panoworld.gaussians.fusion_params import SourcePixelParams


@dataclass(kw_only=True)
class VoxelFusionOptions(SourcePixelParams):
    source_pixels: bool = True
    """The source view (video frame 0; a home: every anchored panorama) becomes one Gaussian per pixel (its full
    detail at the capture point); the other frames are voxel-fused only where they see what the source does not."""
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
        return source_anchored_fusion(job.frames, o, back_sides=back_side_hook(job), progress=job.progress)
    from panoworld.gaussians.home import home_anchored_fusion
    from panoworld.io.home import home_depth_dirs
    from panoworld.room.home_sources import home_sources

    dirs = home_depth_dirs(job.depth) if job.depth else None
    if dirs is None:
        raise InputError(f"{job.register}: the register artifact places several panoramas: give --depth, the home's "
                         "depth artifact (its panoramas are anchored)")
    names, rgbs, depths, _ = home_sources(dirs, captures)  # as the fused mesh has them, its doorways not opened
    return home_anchored_fusion(job.frames, {n: (rgbs[n], depths[n], captures[n]) for n in names}, o,
                                progress=job.progress)


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
