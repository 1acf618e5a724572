"""colmap: COLMAP panorama SfM (pycolmap), Sim(3)-aligned to the planned trajectory for metric scale and canonical frame
(its options, ColmapOptions, live in panoworld/choices.py: light to import, shared with panoworld.poses)."""

from __future__ import annotations

from panoworld.backends import register
from panoworld.choices import ColmapOptions


def estimate(job):
    from panoworld.poses import colmap_estimate

    o: ColmapOptions = job.options
    return colmap_estimate(job.video.rgb, job.planned, render_type=o.render_type, matcher=o.matcher, sfm=o,
                           alignment=job.align)


register("poses", "colmap", estimate, options=ColmapOptions, key="colmap", needs_plan=True, needs_baseline=True,
         recovers=True)
