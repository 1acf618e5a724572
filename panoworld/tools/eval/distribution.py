"""FID and FVD over a set of scenes: generated frames / videos against their references, with local feature networks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from panoworld.tools.eval.common import EvalParams, unavailable
from panoworld.tools.eval.groundtruth import NoReference

MIN_SAMPLES = 2
NO_FID = "pass --fid-weights pt_inception-2015-12-05-6726825d.pth (pytorch-fid's InceptionV3; `runner.py weights list`)"
NO_FVD = "pass --fvd-weights i3d_torchscript.pt (the FVD paper's Kinetics-400 I3D as TorchScript)"


def _unit_samples(scene: Path, variant: str | None, params: EvalParams, height: int) -> dict[str, Any]:
    """Generated frames (T, H, W, 3) of one scene's video and their references: the ground truth at the same poses
    when the scene has it (frames or a synthetic mesh), else the scene's input panorama (plan-only scenes)."""
    from panoworld.io.video import load_frames
    from panoworld.tools.eval.inputs import SceneInputs

    ev = SceneInputs(scene, params, progress=False, variant=variant)
    video = ev.video
    gen = load_frames(video.rgb, height)
    poses, _ = ev.reference_poses()
    try:
        ref = np.stack([ev.gt.render(p, height, 2 * height)[0] for p in poses])
        kind = "ground truth at the video's poses"
    except NoReference:
        pano = next(p for p in (scene / f"panorama.{e}" for e in ("png", "jpg", "jpeg")) if p.is_file())
        ref = load_frames([pano], height)
        kind = "the dataset's input panoramas"
    return {"gen": gen, "ref": ref, "ref_kind": kind}


def distribution_metrics(units: list[tuple[Path, str | None]], params: EvalParams, *, height: int = 256) -> dict:
    """{"fid": value | unavailable, "fvd": ..., "fid_reference": what the generated frames were compared with}.

    FID: InceptionV3 pool features of every generated frame vs every reference frame (pytorch-fid's network and
    Frechet distance). FVD: I3D features of each generated video vs each ground-truth video (scenes with a ground
    truth at every pose only). Frames are read at ERP height `height`.
    """
    from panoworld.render.metrics import frechet_feature_distance

    if not params.fid_weights and not params.fvd_weights:
        return {"fid": unavailable(NO_FID), "fvd": unavailable(NO_FVD)}
    samples, errors = [], []
    for scene, variant in units:
        try:
            samples.append(_unit_samples(Path(scene), variant, params, height))
        except Exception as e:  # a scene without a readable video is left out and named
            errors.append(f"{Path(scene).name}: {type(e).__name__}: {e}")
    out: dict[str, Any] = {"scenes_used": len(samples), "scenes_left_out": errors,
                           "fid_reference": sorted({s["ref_kind"] for s in samples})}
    if params.fid_weights:
        from panoworld.models.inception import FIDInceptionV3

        gen = np.concatenate([s["gen"] for s in samples]) if samples else np.zeros((0,))
        ref = np.concatenate([s["ref"] for s in samples]) if samples else np.zeros((0,))
        if len(gen) < MIN_SAMPLES or len(ref) < MIN_SAMPLES:
            out["fid"] = unavailable(f"{len(gen)} generated and {len(ref)} reference frames; FID needs >= {MIN_SAMPLES} each")
        else:
            net = FIDInceptionV3.from_file(params.fid_weights)
            out["fid"] = frechet_feature_distance(net.features_uint8(gen), net.features_uint8(ref))
            out["fid_frames"] = [int(len(gen)), int(len(ref))]
    else:
        out["fid"] = unavailable(NO_FID)
    if params.fvd_weights:
        from panoworld.models.i3d import I3DFeatures

        pairs = [s for s in samples if len(s["ref"]) == len(s["gen"])]
        if pairs:  # one clip length per FVD: the most common one
            lengths = [len(s["gen"]) for s in pairs]
            pairs = [s for s in pairs if len(s["gen"]) == max(set(lengths), key=lengths.count)]
        if len(pairs) < MIN_SAMPLES:
            out["fvd"] = unavailable(f"{len(pairs)} scenes with a ground-truth video; FVD needs >= {MIN_SAMPLES}")
        else:
            i3d = I3DFeatures.from_file(params.fvd_weights)
            fg = i3d.features_uint8(np.stack([s["gen"] for s in pairs]))
            fr = i3d.features_uint8(np.stack([s["ref"] for s in pairs]))
            out["fvd"] = frechet_feature_distance(fg, fr)
    else:
        out["fvd"] = unavailable(NO_FVD)
    return out
