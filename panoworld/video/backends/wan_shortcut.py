"""wan-shortcut: the paper's generator (Wan2.2-TI2V-5B + LoRA, 4-step shortcut sampling); needs local weights, no depth."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from panoworld.core.errors import InputError
from panoworld.core.registry import register
from panoworld.models.wan_config import WanShortcutConfig


def generate(job) -> tuple:
    cfg: WanShortcutConfig = job.options
    if not cfg.weights:
        raise InputError(
            "wan-shortcut: no weights directory given; pass --wan-weights DIR (Wan2.2-TI2V-5B-Diffusers), --wan-lora "
            "FILE and --wan-extra-weights FILE (weights are never downloaded), or use --backend warp-inpaint"
        )

    from panoworld.models.wan_shortcut import WanShortcutGenerator

    paths = {k: Path(v) for k in ("weights", "lora", "extra_weights", "prompt_embeds") if (v := getattr(cfg, k))}
    generator = WanShortcutGenerator.from_pretrained(dataclasses.replace(cfg, **paths))
    generated, info = generate_clips(generator, job.cond.rgb, job.cond.mask, job.clips or [list(range(len(job.cond)))])
    return ((frame, None, None) for frame in generated), info


def generate_clips(generator, rgb, mask, clips: list[list[int]]) -> tuple[list[np.ndarray], dict]:
    """One generated clip per path (the paper: each path is its own clip conditioned on its warped frames); the clips'
    frames are put back in pose order. A pose in several clips (pose 0, the source view every path leaves from) keeps
    the frame of the first. rgb (T, H, W, 3) / mask (T, H, W) index per frame. Returns (frames, info)."""
    out: list[np.ndarray | None] = [None] * len(rgb)
    info: dict = {}
    seconds = 0.0
    for idx in clips:
        video, gen_info = generator.generate(np.stack([rgb[i] for i in idx]), np.stack([np.asarray(mask[i], bool) for i in idx]))
        seconds += float(gen_info.get("seconds", 0.0))
        info = info or {k: v for k, v in gen_info.items() if isinstance(v, (int, float, str, bool))}
        for i, frame in zip(idx, video):
            if out[i] is None:
                out[i] = frame
    missing = [i for i, f in enumerate(out) if f is None]
    if missing:
        raise ValueError(f"clips leave poses {missing[:5]} without a frame")
    info.update(clips=len(clips), clip_frames=[len(c) for c in clips], seconds=round(seconds, 3))
    return out, info  # type: ignore[return-value]


register("video", "wan-shortcut", generate, options=WanShortcutConfig, key="wan", has_depth=False, renders_plan=False)
