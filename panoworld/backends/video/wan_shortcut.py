"""wan-shortcut: the paper's generator (Wan2.2-TI2V-5B + LoRA, 4-step shortcut sampling); needs local weights, no depth."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from panoworld.backends import register
from panoworld.errors import InputError
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
    generated, gen_info = generator.generate(np.asarray(job.cond.rgb), np.asarray(job.cond.mask))
    info = {k: v for k, v in gen_info.items() if isinstance(v, (int, float, str, bool))}
    return ((generated[k], None, None) for k in range(len(job.cond))), info


register("video", "wan-shortcut", generate, options=WanShortcutConfig, key="wan", has_depth=False)
