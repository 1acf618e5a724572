"""Prints how well warp-inpaint fills the disoccluded pixels of a synthetic scene's video, against the ground truth.

    python bench/bench_warp_fill.py SCENE [--paths 0 2 4 6] [--height 180]

SCENE: a synthetic scene (runner.py synth; tune on validation seeds only) run to `conditions` at least. Every frame
of the chosen paths is filled in path order (as the video stage does) with the default fill and with
`video.warp.reuse`, and its hole pixels (conditions mask 0) are scored against the anti-aliased ground truth at
the same pose: PSNR, the share of hole pixels given depth (those become Gaussians) and the fill time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld import inpaint
from panoworld.conditions import load_conditions
from panoworld.eval.groundtruth import GroundTruth
from panoworld.mesh import load_erp_mesh
from panoworld.trajectory import load_clips, load_trajectory


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--paths", type=int, nargs="*", default=[0, 2, 4, 6], help="which paths (clips) to fill")
    ap.add_argument("--height", type=int, default=180, help="rows the frames are scored at (area-downsampled)")
    a = ap.parse_args()
    art = a.scene / "artifacts"
    cond = load_conditions(art / "conditions")
    poses = load_trajectory(art / "trajectory")
    clips = load_clips(art / "trajectory", len(poses))
    layer = inpaint.build_background_layer(load_erp_mesh(art / "mesh"), inpaint.max_translation(poses))
    gt = GroundTruth(a.scene / "gt", supersample=2)
    h, w = a.height, 2 * a.height
    print(f"{a.scene}: paths {a.paths} of {len(clips)}, scored at {h}x{w}")
    print("| fill | hole PSNR vs ground truth | hole pixels with depth | fill s |\n|---|---|---|---|")
    for reuse in (False, True):
        filler = inpaint.WarpInpainter(layer, reuse=reuse)
        se, n, with_depth, holes, seconds = 0.0, 0, 0, 0, 0.0
        for clip in (clips[k] for k in a.paths if k < len(clips)):
            for i in clip[1:]:
                t0 = time.perf_counter()
                f = filler.fill(cond.rgb[i], cond.mask[i], cond.depth[i], poses[i])
                seconds += time.perf_counter() - t0
                hole = ~cond.mask[i]
                holes += int(hole.sum())
                with_depth += int((f.depth[hole] > 0).sum())
                small = cv2.resize(f.rgb, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)
                hs = cv2.resize(hole.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
                err = ((small - gt.render(poses[i], h, w)[0]) ** 2).mean(-1)[hs]
                se, n = se + err.sum(), n + err.size
        psnr = 10 * np.log10(255.0**2 / max(se / max(n, 1), 1e-12))
        print(f"| {'warp.reuse=true' if reuse else 'default'} | {psnr:.2f} dB | {with_depth / max(holes, 1):.3f} | "
              f"{seconds:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
