"""Depth Anything V2 (transformers DepthAnythingForDepthEstimation) as a perspective depth predictor loaded from local weights."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from panoworld.core.errors import InputError
from panoworld.core.shapes import check_shape
from panoworld.io.depth import DepthKind

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")
EXPECTED = "config.json + model.safetensors (a Hugging Face Depth-Anything-V2-*-hf folder, e.g. Depth-Anything-V2-Small-hf)"


def _transformers():
    try:
        import torch
        from transformers import DepthAnythingForDepthEstimation
    except ImportError as e:
        raise ImportError(f"Depth Anything needs torch and transformers ({e}); pip install '.[models]'") from e
    return torch, DepthAnythingForDepthEstimation


class DepthAnything:
    """Wraps a DepthAnythingForDepthEstimation: `predictor(image (s, s, 3) uint8) -> (s, s) float32`.

    Relative checkpoints (config.depth_estimation_type == "relative", the V2 default) predict affine-invariant
    inverse depth; metric ones predict z-depth in metres (see panoworld.io.depth.DepthKind).
    """

    def __init__(self, model, *, input_size: int = 518, mean=IMAGENET_MEAN, std=IMAGENET_STD, device: str = "cpu"):
        torch, _ = _transformers()
        patch = int(getattr(model.config.backbone_config, "patch_size", 14))
        if input_size % patch:
            raise ValueError(f"{input_size=} must be a multiple of the backbone patch size {patch}")
        self.model = model.to(device).eval()
        self.input_size = input_size
        self.device = device
        self.mean = torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1)
        self.std = torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1)

    @property
    def kind(self) -> DepthKind:
        t = getattr(self.model.config, "depth_estimation_type", "relative")
        return DepthKind.METRIC if t == "metric" else DepthKind.RELATIVE

    @classmethod
    def from_pretrained(cls, weights: Path | str | None, *, input_size: int = 518, device: str = "cpu") -> DepthAnything:
        """Load from a local directory (never a hub download); InputError naming --weights if it is unusable."""
        if weights is None or str(weights) == "":
            raise InputError(f"depth-anything backend needs --weights DIR: a local folder with {EXPECTED}")
        path = Path(weights)
        if not (path / "config.json").is_file() or not any((path / f).is_file() for f in WEIGHT_FILES):
            raise InputError(f"--weights {path}: expected {EXPECTED} in that folder; found none")
        _, model_cls = _transformers()
        model = model_cls.from_pretrained(str(path), local_files_only=True)
        mean, std = IMAGENET_MEAN, IMAGENET_STD
        proc = path / "preprocessor_config.json"
        if proc.is_file():
            cfg = json.loads(proc.read_text())
            mean, std = tuple(cfg.get("image_mean", mean)), tuple(cfg.get("image_std", std))
        return cls(model, input_size=input_size, mean=mean, std=std, device=device)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """image (h, w, 3) uint8 RGB -> prediction (h, w) float32 (bicubic resize to input_size and back)."""
        torch, _ = _transformers()
        check_shape("image", image, "h w 3", dtype=np.uint8)
        h, w = image.shape[:2]
        x = cv2.resize(image, (self.input_size, self.input_size), interpolation=cv2.INTER_CUBIC)
        t = torch.from_numpy(x).permute(2, 0, 1)[None].float() / 255.0
        t = ((t - self.mean) / self.std).to(self.device)
        with torch.inference_mode():
            out = self.model(pixel_values=t).predicted_depth
        pred = out[0].float().cpu().numpy()
        return cv2.resize(pred, (w, h), interpolation=cv2.INTER_LINEAR)
