"""I3D video features for FVD: the Kinetics-400 I3D of the FVD paper as a TorchScript file (StyleGAN-V layout)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.core.shapes import check_shape
from panoworld.models.weights import MissingWeightsError, require_weights_file

I3D_WEIGHTS = "i3d_torchscript.pt"
I3D_WEIGHTS_TEXT = (f"{I3D_WEIGHTS}, the TF-Hub Kinetics-400 I3D of Unterthiner et al.'s FVD exported to TorchScript "
                    "(the file StyleGAN-V and most FVD codebases load)")
FEATURE_DIM = 400
CLIP_SIZE = 224


class I3DFeatures:
    """Calls the TorchScript I3D as the FVD reference does: clips (B, 3, T, 224, 224) in [-1, 1],
    `rescale=False, resize=False, return_features=True` -> (B, 400) logits-layer features."""

    def __init__(self, module):
        self.module = module

    @classmethod
    def from_file(cls, path: Path | str | None, flag: str = "--fvd-weights") -> I3DFeatures:
        import torch

        path = require_weights_file(path, model="FVD I3D", flag=flag, expected=I3D_WEIGHTS_TEXT)
        try:
            module = torch.jit.load(str(path), map_location="cpu")
        except Exception as e:  # any unreadable file gets the same actionable message
            raise MissingWeightsError(f"FVD I3D: cannot load {path} as TorchScript ({e}); it must be {I3D_WEIGHTS_TEXT}") from None
        return cls(module.eval())

    def features_uint8(self, videos: np.ndarray) -> np.ndarray:
        """(N, D) float64 features of uint8 RGB clips (N, T, H, W, 3); frames are resized to 224 x 224 (area)."""
        import cv2
        import torch

        videos = np.asarray(videos)
        check_shape("videos", videos, "N T H W 3", dtype=np.uint8)
        out = []
        with torch.no_grad():
            for clip in videos:
                frames = np.stack([cv2.resize(f, (CLIP_SIZE, CLIP_SIZE), interpolation=cv2.INTER_AREA) for f in clip])
                x = torch.from_numpy(frames).permute(3, 0, 1, 2)[None].float() / 127.5 - 1.0
                feats = self.module(x, rescale=False, resize=False, return_features=True)
                out.append(feats.double().reshape(1, -1).numpy())
        return np.concatenate(out) if out else np.zeros((0, FEATURE_DIM))
