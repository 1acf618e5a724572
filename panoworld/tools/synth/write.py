"""write_scene: render a SynthScene and write its scene directory (panorama, depth, gt/) atomically."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from panoworld.tools.synth.params import SynthParams
from panoworld.tools.synth.rig import RigKind, render_with_rig
from panoworld.tools.synth.scene import SynthScene


def write_scene(scene: SynthScene, out_dir: str | os.PathLike, params: SynthParams, *, progress: bool = True) -> Path:
    """Render and write a scene directory atomically (temporary sibling directory renamed into place); returns it."""
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out} already exists and is not an empty directory; refusing to overwrite it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        (tmp / "gt").mkdir(parents=True)
        rp = params.render
        h = rp.pano_height
        rgb, depth, rig_mask = render_with_rig(scene, rp.rig, h, supersample=rp.supersample)
        cv2.imwrite(str(tmp / "panorama.png"), rgb[..., ::-1])
        np.save(tmp / "depth.npy", depth)
        pano_rel = {"rgb": "../panorama.png", "depth": "../depth.npy", "height": h, "width": 2 * h,
                    "track": 0, "frame": 0, "supersample": rp.supersample, "rig": str(rp.rig)}
        if rp.rig != RigKind.NONE:
            clean_rgb, clean_depth = scene.render(scene.world_from_canonical, h, 2 * h, supersample=rp.supersample)
            cv2.imwrite(str(tmp / "gt" / "panorama_clean.png"), clean_rgb[..., ::-1])
            np.save(tmp / "gt" / "depth_clean.npy", clean_depth)
            cv2.imwrite(str(tmp / "gt" / "rig_mask.png"), rig_mask.astype(np.uint8) * 255)
            pano_rel.update(rgb_clean="panorama_clean.png", depth_clean="depth_clean.npy", rig_mask="rig_mask.png")
        frames_rel = None
        if rp.write_frames:
            frames_rel = []
            total = sum(len(t.world_from_cam) for t in scene.tracks)
            bar = tqdm(total=total, desc=f"render {out.name}", disable=not progress, leave=False)
            for k, tr in enumerate(scene.tracks):
                fdir = tmp / "gt" / "frames" / f"track_{k:02d}"
                (fdir / "rgb").mkdir(parents=True)
                (fdir / "depth").mkdir()
                for i in range(len(tr.world_from_cam)):
                    rgb_i, depth_i = scene.render_frame(k, i, rp.frame_height, supersample=rp.supersample)
                    cv2.imwrite(str(fdir / "rgb" / f"{i:06d}.png"), rgb_i[..., ::-1])
                    np.save(fdir / "depth" / f"{i:06d}.npy", depth_i)
                    bar.update()
                frames_rel.append({"rgb": f"frames/track_{k:02d}/rgb/{{:06d}}.png",
                                   "depth": f"frames/track_{k:02d}/depth/{{:06d}}.npy",
                                   "height": rp.frame_height, "width": 2 * rp.frame_height})
            bar.close()
        scene.save_gt(tmp / "gt", pano_rel=pano_rel, frames_rel=frames_rel)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
