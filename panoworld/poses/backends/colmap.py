"""colmap: COLMAP panorama SfM (pycolmap), Sim(3)-aligned to the planned trajectory for metric scale and canonical frame
(its options, ColmapOptions, live in panoworld/poses/options.py: light to import, shared with panoworld.poses.estimate)."""

from __future__ import annotations

from panoworld.core.registry import register
from panoworld.poses.options import ColmapOptions


def estimate(job):
    from panoworld.poses.estimate import colmap_estimate

    o: ColmapOptions = job.options
    return colmap_estimate(job.video.rgb, job.planned, o, alignment=job.align)


register("poses", "colmap", estimate, options=ColmapOptions, key="colmap", needs_plan=True, needs_baseline=True,
         recovers=True)
