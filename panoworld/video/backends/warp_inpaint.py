"""warp-inpaint: a background layer behind every depth edge of the source view, meshed once and ray cast at each pose,
so a surface gets the same colour in every frame (no weights); per-frame depth included."""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from panoworld.core.errors import InputError
from panoworld.core.params import param
from panoworld.core.registry import register


@dataclass(kw_only=True)
class WarpOptions:
    max_band_deg: float = param(45.0, gt=0, le=180)
    """Widest background band (degrees) synthesized behind a foreground edge."""
    reuse: bool = False
    """Holes the background layer does not fill are filled from the farther side (depth-aware 2D fill, with depth)
    and committed as 3D points that later frames reuse (panoworld.video.inpaint.CommittedPoints); else a per-frame 2D fill
    without depth."""
    side_depth_m: float = param(0.0, ge=0)
    """Occluders' hidden sides: each foreground silhouette of the source view continues straight back along the
    source's rays by this many metres (up to the background), in the foreground's colour
    (panoworld.video.background_layer.occluder_sides), so a camera moving around furniture sees a side rather than wall colour;
    0 = off (the background layer alone)."""
    edge_depth_ratio: float = param(0.75, gt=0, le=1)
    """A depth edge of the source view grows a background layer only where its foreground is nearer than this
    fraction of the background's depth; smaller steps (shelves in front of books, furniture against a wall) are left
    to the far side's 2D fill (panoworld.video.background_layer.build_background_layer)."""
    layout_planes: bool = False
    """The background layer's depth never lies beyond the floor and ceiling planes fitted to the source depth
    (panoworld.room.floor.fit_planes): the hidden floor behind furniture and the ceiling behind a lamp stay on
    the room's planes (panoworld.video.background_layer.build_background_layer)."""
    wall_layout: bool = False
    """The room's shell from the source view: one wall per column, interpolated across the columns tall objects hide
    (panoworld.room.layout_columns), with the floor and ceiling planes; background layer pixels grown from an edge on the
    shell take its depth, and on a wall the wall's colour seen at the same height beside the occluder
    (panoworld.video.background_layer.wall_layer) instead of the inpainted colour."""
    color_sigma_px: float = param(0.0, ge=0)
    """> 0: the background layer's colour is the Gaussian-weighted mean (this sigma, source grid pixels) of the
    visible background around it (panoworld.video.background_layer.layer_mean_color) instead of Telea inpainting, which streaks
    across wide bands; 0 = Telea."""
    shadow_ambient: float = param(1.0, gt=0, le=1)
    """< 1: the background layer is relit for the ceiling lights found in the source view (bright patches on the
    fitted ceiling; panoworld.room.fill_shadows): where an occluder hides those lights from a hidden surface more than
    from the visible pixels its colour came from, it is darker (panoworld.video.background_layer.relight_layer), with ambient light
    this share of a fully lit surface's; points beyond the room's walls are left as they are; 1 = off."""
    plane_colors: bool = True
    """Hidden points on the floor plane beyond the room's walls (the next room through a doorway) take their colour
    from a top-down map of the floor seen beyond them (panoworld.room.plane_colors: push-pull filled, blending back into
    the inpainted colour far from any floor seen), not from the source pixels at the doorway's edge; false = off."""
    next_room_colors: bool = False
    """Hidden points beyond the room's walls between the floor and the ceiling take the median colour of the next
    room's walls seen through the doorway (panoworld.room.plane_colors), not the doorway edge's colour; where none is seen
    they keep theirs (a hidden piece of furniture there gets the wall's colour too); false = off."""
    depth_fill: bool = True
    """Without reuse: holes the background layer does not fill take the depth and colour of their farther side
    (panoworld.video.inpaint.background_fill), so the Gaussians stage places them; false = a colour-only 2D fill (no depth:
    no Gaussians there)."""


READ_AHEAD = 4
"""Conditions frames decoded ahead of the fill (~8 MB each at 720x1440)."""
FILL_AHEAD = 2
"""Frames filled at once (threads; without reuse)."""


def fill(job) -> tuple:
    from panoworld.geometry.erp_mesh import load_erp_mesh
    from panoworld.io.home import read_home_sources
    from panoworld.io.jsonio import read_json
    from panoworld.video import background_layer, inpaint
    from panoworld.video.home import home_background_layer

    if job.mesh_dir is None:
        raise InputError("warp-inpaint needs --mesh DIR (the mesh artifact the conditions were rendered from)")
    t0 = time.perf_counter()
    cond = job.cond
    # Decoding the first frames overlaps the layer's build (which leaves the second core mostly idle).
    cond_frames = cond.iter_frames(ahead=READ_AHEAD)
    mesh_dir = Path(job.mesh_dir)
    try:
        mesh = load_erp_mesh(mesh_dir)
        ratio = float(read_json(mesh_dir / "manifest.json", default={}).get("params", {}).get("max_edge_ratio", 12.0))
        opts = dict(max_band_deg=job.options.max_band_deg, inpaint_radius=job.inpaint_radius, max_edge_ratio=ratio,
                    side_depth_m=job.options.side_depth_m, edge_depth_ratio=job.options.edge_depth_ratio,
                    layout_planes=job.options.layout_planes, color_sigma_px=job.options.color_sigma_px,
                    wall_layout=job.options.wall_layout, shadow_ambient=job.options.shadow_ambient,
                    plane_colors=job.options.plane_colors, next_room_colors=job.options.next_room_colors)
        sources = read_home_sources(mesh_dir)
        if sources is not None:  # a home: one layer per source panorama (panoworld/video/home.py)
            layer = home_background_layer(mesh, sources, job.poses, **opts)
        else:
            layer = background_layer.build_background_layer(mesh, inpaint.max_translation(job.poses), ray_caster=True,
                                                           **opts)
    except (OSError, ValueError, KeyError) as e:
        raise InputError(f"{mesh_dir}/mesh.ply: {e}; rerun the mesh stage") from None
    info = dict(layer_faces=int(layer.layer_faces), layer_pixels=int(layer.synthesized.sum()),
                layer_s=round(time.perf_counter() - t0, 3))
    filler = inpaint.WarpInpainter(layer, inpaint_radius=job.inpaint_radius, reuse=job.options.reuse,
                                    depth_fill=job.options.depth_fill)

    def frames():
        if job.options.reuse:  # a frame reuses what the frames before it committed: one at a time, in order
            for k, (rgb, mask, depth) in enumerate(cond_frames):
                f = filler.fill(rgb, mask, depth, job.poses[k])
                yield f.rgb, f.depth, f
            return
        # Each frame's fill is independent of the others': FILL_AHEAD frames in flight on a pool's threads (the ray
        # casts, blurs and distance transforms release the GIL), yielded in order.
        with ThreadPoolExecutor(max_workers=FILL_AHEAD) as pool:
            pending: deque = deque()
            for k, (rgb, mask, depth) in enumerate(cond_frames):
                pending.append(pool.submit(filler.fill, rgb, mask, depth, job.poses[k]))
                if len(pending) >= FILL_AHEAD:
                    f = pending.popleft().result()
                    yield f.rgb, f.depth, f
            while pending:
                f = pending.popleft().result()
                yield f.rgb, f.depth, f

    return frames(), info


register("video", "warp-inpaint", fill, options=WarpOptions, key="warp", has_depth=True, renders_plan=True)
