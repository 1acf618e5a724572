"""Panoramic video from the warped conditions: holes filled (warp-inpaint, frame-inpaint or wan-shortcut), optionally
also written x2 upscaled (an output; later stages read the frames at the generation size)."""

from __future__ import annotations

import enum
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.stage import Input, StageInputError, stage_main

NAME = "video"
VERSION = "2"
ARTIFACT = "video"
INPUTS = {
    "conditions": Input("conditions", help="conditions artifact (warped rgb, mask, depth per pose)"),
    "trajectory": Input("trajectory", help="trajectory artifact (the poses the conditions were rendered at, fps)"),
    "mesh": Input("mesh", optional=True, help="mesh artifact of the source view (required by warp-inpaint)"),
}
DEFAULT_FPS = 16.0


class Backend(enum.StrEnum):
    WARP_INPAINT = "warp-inpaint"
    """No weights: a background layer behind every depth edge of the source view, meshed once and ray cast at each
    pose, so a surface gets the same colour in every frame; per-frame depth included."""
    FRAME_INPAINT = "frame-inpaint"
    """Baseline: seam-aware Telea inpainting of each frame on its own (no temporal consistency)."""
    WAN_SHORTCUT = "wan-shortcut"
    """The paper's generator (Wan2.2-TI2V-5B + LoRA, 4-step shortcut sampling); needs local weights, no depth."""


class Upscale(enum.StrEnum):
    NONE = "none"
    LANCZOS = "lanczos"
    REALESRGAN = "realesrgan"


class Sampler(enum.StrEnum):
    SHORTCUT = "shortcut"
    FLOW = "flow"


@dataclass(kw_only=True)
class Params:
    backend: Backend = Backend.WARP_INPAINT
    """How disoccluded pixels are filled: warp-inpaint, frame-inpaint or wan-shortcut."""
    upscale: Upscale = Upscale.NONE
    """Also write the frames x2 upscaled into upscaled/ (an output for viewing; frames/, which later stages read, stay
    at the generation size): none, lanczos (seam-aware) or realesrgan (needs --upscale-weights, the paper's)."""
    upscale_weights: str | None = None
    """RealESRGAN_x2plus.pth for --upscale realesrgan (weights are never downloaded)."""
    upscale_tile: int = 0
    """Real-ESRGAN tile size in source pixels (0 = whole frames); bounds memory on big frames."""
    fps: float | None = None
    """Frame rate of the preview and MCAP timestamps; None = the trajectory's fps (16 if it has none)."""
    max_band_deg: float = 45.0
    """warp-inpaint: widest background band (degrees) synthesized behind a foreground edge."""
    inpaint_radius: float = 3.0
    """Telea inpainting radius in pixels (background layer colours, 2D fills)."""
    preview: bool = True
    """Write preview.mp4 (H.264, yuv420p)."""
    preview_max_width: int = 1920
    """Width cap of preview.mp4 (frames are downscaled to fit)."""
    mcap: bool = True
    """Write video.mcap (Foxglove: frames, conditions, depth, camera poses)."""
    weights: str | None = None
    """wan-shortcut: local Wan2.2-TI2V-5B-Diffusers directory."""
    lora: str | None = None
    """wan-shortcut: trained LoRA safetensors."""
    extra_weights: str | None = None
    """wan-shortcut: trained patch/step-size embedding safetensors."""
    prompt_embeds: str | None = None
    """wan-shortcut: precomputed UMT5 prompt embeddings (needed when the weights have no text encoder)."""
    prompt: str = "a panoramic video walking through an indoor scene"
    """wan-shortcut: text prompt (ignored with --prompt-embeds)."""
    sampler: Sampler = Sampler.SHORTCUT
    """wan-shortcut: shortcut (few steps told their size, the paper) or flow (plain flow-matching Euler)."""
    steps: int = 4
    """wan-shortcut: denoising steps."""
    guidance: float = 1.0
    """wan-shortcut: classifier-free guidance scale (1 = guidance-free)."""
    device: str = "auto"
    """Device of the learned models (wan-shortcut, realesrgan): auto = cuda when available, else cpu."""
    dtype: str = "bfloat16"
    """wan-shortcut transformer dtype."""
    cpu_offload: bool = False
    """wan-shortcut: keep models on the CPU, move each to the device only while it runs."""
    vae_tiling: bool = True
    """wan-shortcut: VAE in spatial tiles (lower memory)."""
    seed: int = 0
    """wan-shortcut: seed of the initial noise."""


def _device(name: str) -> str:
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _generate_wan(params: Params, cond) -> tuple[np.ndarray, dict]:
    from panoworld.models.wan_shortcut import Sampler as WanSampler
    from panoworld.models.wan_shortcut import WanShortcutConfig, WanShortcutGenerator

    cfg = WanShortcutConfig(
        weights=params.weights and Path(params.weights), lora=params.lora and Path(params.lora),
        extra_weights=params.extra_weights and Path(params.extra_weights),
        prompt_embeds=params.prompt_embeds and Path(params.prompt_embeds), prompt=params.prompt,
        sampler=WanSampler(params.sampler.value), steps=params.steps, guidance=params.guidance,
        device=_device(params.device), dtype=params.dtype, cpu_offload=params.cpu_offload,
        vae_tiling=params.vae_tiling, seed=params.seed,
    )
    generator = WanShortcutGenerator.from_pretrained(cfg)
    return generator.generate(np.asarray(cond.rgb), np.asarray(cond.mask))


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from tqdm import tqdm

    from panoworld import inpaint
    from panoworld.conditions import load_conditions
    from panoworld.trajectory import load_trajectory
    from panoworld.upscale import FrameUpscaler
    from panoworld.video_io import VideoWriter

    if params.upscale == Upscale.REALESRGAN and not (params.upscale_weights and Path(params.upscale_weights).is_file()):
        raise StageInputError(
            f"--upscale realesrgan needs --upscale-weights FILE (RealESRGAN_x2plus.pth; got {params.upscale_weights}); "
            "or pass --upscale lanczos"
        )
    if params.backend == Backend.WAN_SHORTCUT and not params.weights:
        raise StageInputError(
            "wan-shortcut: no weights directory given; pass --weights DIR (Wan2.2-TI2V-5B-Diffusers), --lora FILE and "
            "--extra-weights FILE (weights are never downloaded), or use --backend warp-inpaint"
        )
    cond_dir = Path(inputs["conditions"])
    try:
        cond = load_conditions(cond_dir)
    except ValueError as e:
        raise StageInputError(str(e)) from None
    traj_dir = Path(inputs["trajectory"])
    try:
        poses = load_trajectory(traj_dir)
    except ValueError as e:
        raise StageInputError(f"{e}; rerun the trajectory stage") from None
    if poses.shape != cond.poses.shape or not np.allclose(poses, cond.poses, atol=1e-6):
        raise StageInputError(
            f"{cond_dir}/conditions.json: {len(cond.poses)} poses that differ from the {len(poses)} of "
            f"{traj_dir}/trajectory.json; rerun the conditions stage on this trajectory"
        )
    fps = params.fps or float(_read_json(traj_dir / "trajectory.json").get("fps") or DEFAULT_FPS)

    info: dict = {"backend": str(params.backend), "upscale": str(params.upscale)}
    t0 = time.perf_counter()
    if params.backend == Backend.WAN_SHORTCUT:
        generated, gen_info = _generate_wan(params, cond)
        info.update({k: v for k, v in gen_info.items() if isinstance(v, (int, float, str, bool))})
        produce = ((generated[k], None, None) for k in range(len(cond)))
    elif params.backend == Backend.WARP_INPAINT:
        if inputs.get("mesh") is None:
            raise StageInputError("warp-inpaint needs --mesh DIR (the mesh artifact the conditions were rendered from)")
        from panoworld.mesh import load_erp_mesh

        mesh_dir = Path(inputs["mesh"])
        try:
            mesh = load_erp_mesh(mesh_dir)
            ratio = float(_read_json(mesh_dir / "manifest.json").get("params", {}).get("max_edge_ratio", 12.0))
            layer = inpaint.build_background_layer(
                mesh, inpaint.max_translation(poses), max_band_deg=params.max_band_deg,
                inpaint_radius=params.inpaint_radius, max_edge_ratio=ratio,
            )
        except (OSError, ValueError, KeyError) as e:
            raise StageInputError(f"{mesh_dir}/mesh.ply: {e}; rerun the mesh stage") from None
        info.update(layer_faces=int(layer.layer_faces), layer_pixels=int(layer.synthesized.sum()),
                    layer_s=round(time.perf_counter() - t0, 3))
        filler = inpaint.WarpInpainter(layer, inpaint_radius=params.inpaint_radius)

        def produce_warp():
            for k in range(len(cond)):
                f = filler.fill(cond.rgb[k], cond.mask[k], None if cond.depth is None else cond.depth[k], poses[k])
                yield f.rgb, f.depth, f

        produce = produce_warp()
    else:

        def produce_frame():
            for k in range(len(cond)):
                f = inpaint.frame_inpaint(cond.rgb[k], cond.mask[k], None if cond.depth is None else cond.depth[k],
                                          radius=params.inpaint_radius)
                yield f.rgb, f.depth, f

        produce = produce_frame()

    up = FrameUpscaler(params.upscale.value, weights=params.upscale_weights, tile=params.upscale_tile,
                       device=_device(params.device) if params.upscale == Upscale.REALESRGAN else "cpu")
    has_depth = params.backend != Backend.WAN_SHORTCUT
    writer = VideoWriter(out_dir, height=cond.height, width=cond.width, fps=fps, has_depth=has_depth,
                         preview=params.preview, preview_max_width=params.preview_max_width, mcap=params.mcap,
                         upscale=up.scale)
    holes = filled_3d = filled_2d = 0
    t_fill = t_up = t_write = 0.0
    t1 = time.perf_counter()
    for k, (rgb, depth, filled) in enumerate(tqdm(produce, total=len(cond), desc="video", unit="frame", disable=None)):
        t2 = time.perf_counter()
        t_fill += t2 - t1
        if filled is not None:
            holes += int(filled.filled_3d.sum() + filled.filled_2d.sum())
            filled_3d += int(filled.filled_3d.sum())
            filled_2d += int(filled.filled_2d.sum())
        big = up.rgb(rgb) if up.scale > 1 else None
        t3 = time.perf_counter()
        t_up += t3 - t2
        writer.add(rgb, depth if has_depth else None, poses[k], upscaled=big,
                   cond_rgb_png=(cond.root / cond.rgb.paths[k]).read_bytes(),
                   cond_mask_png=(cond.root / cond.mask.paths[k]).read_bytes())
        t1 = time.perf_counter()
        t_write += t1 - t3
    t3 = time.perf_counter()
    writer.close({"backend": str(params.backend), "upscale": str(params.upscale)})
    t_write += time.perf_counter() - t3
    n_px = len(cond) * cond.height * cond.width
    info.update(
        num_frames=len(cond), height=cond.height, width=cond.width, fps=fps, has_depth=has_depth,
        upscaled_height=cond.height * up.scale if up.scale > 1 else None,
        upscaled_width=cond.width * up.scale if up.scale > 1 else None,
        hole_fraction=holes / n_px if params.backend != Backend.WAN_SHORTCUT else None,
        filled_3d_fraction=filled_3d / holes if holes else None,
        filled_2d_fraction=filled_2d / holes if holes else None,
        fill_s=round(t_fill, 3), upscale_s=round(t_up, 3), write_s=round(t_write, 3),
        total_s=round(time.perf_counter() - t0, 3),
    )
    return info


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
