"""Panoramic video from the warped conditions: holes filled (warp-inpaint, frame-inpaint or wan-shortcut), optionally
also written x2 upscaled (an output; later stages read the frames at the generation size)."""

from __future__ import annotations

import enum
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from panoworld.core import registry as backends
from panoworld.core.params import options, param
from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.io.rgb_image import RgbFormat
from panoworld.models.wan_config import WanShortcutConfig
from panoworld.video.backends import Job
from panoworld.video.backends.warp_inpaint import WarpOptions

NAME = "video"
VERSION = "2"
ARTIFACT = "video"
INPUTS = {
    "conditions": Input("conditions", help="conditions artifact (warped rgb, mask, depth per pose)"),
    "trajectory": Input("trajectory", help="trajectory artifact (the poses the conditions were rendered at, fps)"),
    "mesh": Input("mesh", optional=True, help="mesh artifact of the source view (required by warp-inpaint)"),
}
DEFAULT_FPS = 16.0


class Upscale(enum.StrEnum):
    NONE = "none"
    LANCZOS = "lanczos"
    REALESRGAN = "realesrgan"


@dataclass(kw_only=True)
class Params:
    backend: str = param("warp-inpaint", choices=backends.names(NAME))
    """How disoccluded pixels are filled: warp-inpaint, frame-inpaint or wan-shortcut (panoworld/video/backends/)."""
    upscale: Upscale = Upscale.NONE
    """Also write the frames x2 upscaled into upscaled/ (an output for viewing; frames/, which later stages read, stay
    at the generation size): none, lanczos (seam-aware) or realesrgan (needs --upscale-weights, the paper's)."""
    upscale_weights: str | None = None
    """RealESRGAN_x2plus.pth for --upscale realesrgan (weights are never downloaded)."""
    upscale_tile: int = param(0, ge=0)
    """Real-ESRGAN tile size in source pixels (0 = whole frames); bounds memory on big frames."""
    fps: float | None = param(None, gt=0)
    """Frame rate of the preview and MCAP timestamps; None = the trajectory's fps (16 if it has none)."""
    inpaint_radius: float = param(3.0, ge=0)
    """Telea inpainting radius in pixels (background layer colours, 2D fills)."""
    preview: bool = True
    """Write preview.mp4 (H.264, yuv420p): video.mcap's H.264 frame stream itself when it has one (mcap_codec h264)
    and the frames fit preview_max_width, else an encode of its own (x264 CRF 23)."""
    preview_max_width: int = param(1920, ge=16)
    """Width cap of preview.mp4 (frames are downscaled to fit)."""
    mcap: bool = True
    """Write video.mcap (Foxglove: frames, conditions, depth, camera poses)."""
    frame_format: RgbFormat = RgbFormat.JPEG
    """Format of frames/ (what poses and gaussians read): jpeg (of frame_quality, about 4x smaller) or png (lossless)."""
    frame_quality: int = param(93, ge=1, le=100)
    """JPEG quality of frames/ (4:4:4 chroma; 93: ~43 dB PSNR to the lossless frame, 95: ~44 dB for 1.2x the bytes, 90:
    ~41 dB for 0.8x; bench/bench_artifact_size.py)."""
    mcap_codec: str = param("h264", choices=("h264", "jpeg"))
    """How video.mcap holds the frames and conditions (a log for viewing; frames/ hold what later stages read): h264
    (two foxglove.CompressedVideo streams, a keyframe at least every 2 s) or jpeg (foxglove.CompressedImage per frame)."""
    mcap_crf: int = param(28, ge=0, le=51)
    """x264's constant rate factor of the MCAP's H.264 streams (preset MCAP_X264_PRESET; 28: about 35 dB PSNR to frames/
    on the demo, 26 35.5 dB for 1.3x the bytes)."""
    mcap_jpeg_quality: int = param(80, ge=0, le=100)
    """JPEG quality of the frames and conditions in video.mcap with mcap_codec jpeg; 0 = the files' own bytes (with PNG
    frames about 3x the size)."""
    device: str = "auto"
    """Device of realesrgan: auto = cuda when available, else cpu (wan-shortcut: wan.device)."""
    warp: WarpOptions = options(WarpOptions, "warp-inpaint")
    """warp-inpaint's options."""
    wan: WanShortcutConfig = options(WanShortcutConfig, "wan-shortcut")
    """wan-shortcut's options."""

    RENAMED: ClassVar[dict[str, str]] = {
        "max_band_deg": "warp.max_band_deg",
        **{k: f"wan.{k}" for k in ("weights", "lora", "extra_weights", "prompt_embeds", "prompt", "sampler", "steps",
                                   "guidance", "dtype", "cpu_offload", "vae_tiling", "seed")},
    }


def _device(name: str) -> str:
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from panoworld.core.progress import bar
    from panoworld.io.conditions import load_conditions
    from panoworld.io.trajectory import load_clips, load_trajectory, read_trajectory_doc
    from panoworld.io.video_writer import VideoWriter
    from panoworld.video.upscale import FrameUpscaler

    if params.upscale == Upscale.REALESRGAN and not (params.upscale_weights and Path(params.upscale_weights).is_file()):
        raise StageInputError(
            f"--upscale realesrgan needs --upscale-weights FILE (RealESRGAN_x2plus.pth; got {params.upscale_weights}); "
            "or pass --upscale lanczos"
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
    fps = params.fps or float(read_trajectory_doc(traj_dir, missing_ok=True).get("fps") or DEFAULT_FPS)

    info: dict = {"backend": str(params.backend), "upscale": str(params.upscale)}
    t0 = time.perf_counter()
    backend = backends.get(NAME, params.backend)
    try:
        clips = load_clips(traj_dir, len(poses))
    except ValueError as e:
        raise StageInputError(str(e)) from None
    job = Job(cond=cond, poses=poses, mesh_dir=inputs.get("mesh"), options=backend.options_of(params),
              inpaint_radius=params.inpaint_radius, clips=clips)
    produce, backend_info = backend.impl(job)
    info.update(backend_info)

    up = FrameUpscaler(params.upscale.value, weights=params.upscale_weights, tile=params.upscale_tile,
                       device=_device(params.device) if params.upscale == Upscale.REALESRGAN else "cpu")
    has_depth = backend.traits["has_depth"]
    writer = VideoWriter(out_dir, height=cond.height, width=cond.width, fps=fps, has_depth=has_depth,
                         preview=params.preview, preview_max_width=params.preview_max_width, mcap=params.mcap,
                         mcap_codec=params.mcap_codec, mcap_crf=params.mcap_crf,
                         mcap_jpeg_quality=params.mcap_jpeg_quality, frame_format=params.frame_format,
                         frame_quality=params.frame_quality,
                         upscale=up.scale)
    holes = filled_3d = filled_2d = 0
    t_fill = t_up = t_write = 0.0
    t1 = time.perf_counter()
    for k, (rgb, depth, filled) in enumerate(bar(produce, total=len(cond), desc="video", unit="frame")):
        t2 = time.perf_counter()
        t_fill += t2 - t1
        if filled is not None:
            n3, n2 = np.count_nonzero(filled.filled_3d), np.count_nonzero(filled.filled_2d)
            holes += n3 + n2
            filled_3d += n3
            filled_2d += n2
        big = up.rgb(rgb) if up.scale > 1 else None
        t3 = time.perf_counter()
        t_up += t3 - t2
        source = filled.source if filled is not None else None  # the condition as the backend decoded it
        writer.add(rgb, depth if has_depth else None, poses[k], upscaled=big, cond_rgb=source,
                   cond_rgb_png=None if source is not None and params.mcap_codec == "h264"
                   else (cond.root / cond.rgb.paths[k]).read_bytes(),
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
        hole_fraction=holes / n_px if has_depth else None,
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
