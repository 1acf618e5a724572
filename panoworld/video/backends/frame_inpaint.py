"""frame-inpaint: the baseline, seam-aware Telea inpainting of each frame on its own (no temporal consistency)."""

from __future__ import annotations

from panoworld.core.registry import register


def fill(job) -> tuple:
    from panoworld.video import inpaint

    cond = job.cond

    def frames():
        for k in range(len(cond)):
            f = inpaint.frame_inpaint(cond.rgb[k], cond.mask[k], None if cond.depth is None else cond.depth[k],
                                      radius=job.inpaint_radius)
            yield f.rgb, f.depth, f

    return frames(), {}


register("video", "frame-inpaint", fill, has_depth=True, renders_plan=True)
