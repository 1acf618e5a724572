"""Prints the PNG encode / decode time and size of a video artifact's frames and depth under OpenCV's filter settings.

    python bench/bench_png.py VIDEO_DIR [--frames 10]

VIDEO_DIR: a video artifact (artifacts/video). Every setting is checked lossless (decoded == the input); `encode_png`
and `encode_depth_png` are the ones the video writer uses for frames and depth; `level 1, adaptive` is libpng's per-row trial of all five filters, for
comparison.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.core.conventions import depth_to_mm
from panoworld.io.depth_png import encode_depth_png
from panoworld.io.png import encode_png
from panoworld.io.video import load_video

C, F, S = cv2.IMWRITE_PNG_COMPRESSION, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_STRATEGY
SETTINGS = {
    "level 1, adaptive": [C, 1],
    "level 1, Sub, RLE": [C, 1, F, cv2.IMWRITE_PNG_FILTER_SUB, S, cv2.IMWRITE_PNG_STRATEGY_RLE],
    "level 1, Sub": [C, 1, F, cv2.IMWRITE_PNG_FILTER_SUB],
    "level 1, Up": [C, 1, F, cv2.IMWRITE_PNG_FILTER_UP],
    "level 1, Up, RLE": [C, 1, F, cv2.IMWRITE_PNG_FILTER_UP, S, cv2.IMWRITE_PNG_STRATEGY_RLE],
    **{f"level {n}, Up": [C, n, F, cv2.IMWRITE_PNG_FILTER_UP] for n in (3, 4, 6)},
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("video", type=Path)
    ap.add_argument("--frames", type=int, default=10, help="frames taken evenly along the video")
    a = ap.parse_args(argv)
    video = load_video(a.video)
    pick = np.linspace(0, len(video.frames) - 1, min(a.frames, len(video.frames))).round().astype(int)
    kinds = {"rgb": [video.frames[k] for k in pick]}
    if video.depth is not None:
        kinds["depth"] = [depth_to_mm(video.depth[k]) for k in pick]
    print(f"{'setting':22s} {'image':6s} {'encode ms':>9s} {'decode ms':>9s} {'KB':>7s}")
    for kind, images in kinds.items():
        bgr = [cv2.cvtColor(x, cv2.COLOR_RGB2BGR) if x.ndim == 3 else x for x in images]
        encoders = {name: (lambda x, p=p: cv2.imencode(".png", x, p)[1].tobytes()) for name, p in SETTINGS.items()}
        writer = ("encode_depth_png", encode_depth_png) if kind == "depth" else ("encode_png", encode_png)
        encoders[writer[0]] = None
        for name, enc in encoders.items():
            t0 = time.perf_counter()
            data = [writer[1](x) for x in images] if enc is None else [enc(x) for x in bgr]
            t1 = time.perf_counter()
            back = [cv2.imdecode(np.frombuffer(d, np.uint8), cv2.IMREAD_UNCHANGED) for d in data]
            t2 = time.perf_counter()
            if not all(np.array_equal(x, y) for x, y in zip(back, bgr)):
                raise SystemExit(f"{name}: not lossless")
            n = len(data)
            print(f"{name:22s} {kind:6s} {(t1 - t0) / n * 1e3:9.1f} {(t2 - t1) / n * 1e3:9.1f} "
                  f"{sum(map(len, data)) / n / 1024:7.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
