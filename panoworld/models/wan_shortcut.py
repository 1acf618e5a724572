"""The paper's generator: Wan2.2-TI2V-5B + LoRA conditioned on warped ERP video + masks, 4-step shortcut sampling."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch

from panoworld.core.progress import bar
from panoworld.core.shapes import check_shape
from panoworld.models import wan_layers as wl
from panoworld.models.wan_config import (  # noqa: F401  (re-exported)
    DEFAULT_PROMPT,
    Sampler,
    WanShortcutConfig,
    resolve_device,
)
from panoworld.models.weights import MissingWeightsError, require_weights_dir, require_weights_file

MAX_SEQUENCE_LENGTH = 512  # Wan2.2 pads/truncates UMT5 prompts to 512 tokens
BASE_FILES = (
    "transformer/config.json",
    "transformer/diffusion_pytorch_model*.safetensors",
    "vae/config.json",
    "vae/diffusion_pytorch_model.safetensors",
)
TEXT_FILES = ("text_encoder/config.json", "text_encoder/model*.safetensors", "tokenizer/tokenizer_config.json")
FLAGS = "--weights DIR --lora FILE --extra-weights FILE [--prompt-embeds FILE]"


def shortcut_schedule(steps: int) -> tuple[list[float], list[float]]:
    """Uniform sigmas 1 -> 0 in `steps` steps and the step size given to the model (1/steps) at each."""
    if steps < 1 or steps & (steps - 1) or steps > 128:
        raise ValueError(f"{steps=} but the shortcut sampler takes a power of two <= 128 (trained on dyadic steps)")
    return [1.0 - i / steps for i in range(steps + 1)], [1.0 / steps] * steps


def flow_schedule(steps: int, shift: float) -> tuple[list[float], list[float]]:
    """Wan's shifted flow-matching sigmas (diffusers FlowMatchEulerDiscreteScheduler) with step size 0 (plain flow)."""
    if steps < 1:
        raise ValueError(f"{steps=} but expected >= 1")
    from diffusers import FlowMatchEulerDiscreteScheduler

    scheduler = FlowMatchEulerDiscreteScheduler(num_train_timesteps=1000, shift=shift)
    scheduler.set_timesteps(steps)
    return [float(s) for s in scheduler.sigmas], [0.0] * steps


def euler_sample(
    velocity_fn: Callable[[torch.Tensor, float, float, bool], torch.Tensor],
    noise: torch.Tensor,
    sigmas: list[float],
    step_sizes: list[float],
    *,
    guidance: float = 1.0,
    progress: bool = True,
) -> tuple[torch.Tensor, int]:
    """Integrate dx/dsigma = v from sigma = sigmas[0] to sigmas[-1]; returns (x, number of model forwards).

    velocity_fn(x, sigma, dt, positive) evaluates the model with the prompt (positive) or the negative prompt;
    guidance != 1 mixes both (classifier-free guidance) at two forwards per step.
    """
    x, nfe = noise, 0
    for i in bar(range(len(step_sizes)), desc="denoise", leave=False, on=progress):
        sigma, dt = sigmas[i], step_sizes[i]
        v = velocity_fn(x, sigma, dt, True)
        nfe += 1
        if guidance != 1.0:
            v_neg = velocity_fn(x, sigma, dt, False)
            nfe += 1
            v = v_neg + guidance * (v - v_neg)
        x = x + (sigmas[i + 1] - sigma) * v
    return x, nfe


def load_prompt_embeds(path: Path) -> dict[str, torch.Tensor]:
    """Read {'prompt_embeds': (1, L, D), optional 'negative_prompt_embeds'} from .safetensors or .pt."""
    path = require_weights_file(
        path, model="wan-shortcut", flag="--prompt-embeds",
        expected="a .safetensors/.pt holding 'prompt_embeds' (1, L, 4096) from Wan's UMT5 (see save_prompt_embeds)",
    )
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        data = load_file(str(path))
    else:
        data = torch.load(path, map_location="cpu", weights_only=True)
        data = data if isinstance(data, dict) else {"prompt_embeds": data}
    if "prompt_embeds" not in data or data["prompt_embeds"].ndim != 3:
        raise MissingWeightsError(f"wan-shortcut: {path} lacks a 3-D 'prompt_embeds' tensor (has {sorted(data)})")
    return data


def save_prompt_embeds(path: Path, prompt_embeds: torch.Tensor, negative_prompt_embeds: torch.Tensor | None = None):
    """Write prompt embeddings (1, L, D) for `--prompt-embeds` (safetensors)."""
    from safetensors.torch import save_file

    data = {"prompt_embeds": prompt_embeds.detach().cpu().contiguous()}
    if negative_prompt_embeds is not None:
        data["negative_prompt_embeds"] = negative_prompt_embeds.detach().cpu().contiguous()
    save_file(data, str(path))


def encode_prompts(
    weights: Path, prompt: str, negative_prompt: str = "", *, dtype: str = "bfloat16", device: str = "cpu"
) -> dict[str, torch.Tensor]:
    """Embed a prompt and negative prompt with the UMT5 text encoder in `weights` (Wan pipeline's encoding)."""
    wl.import_diffusers()
    from diffusers import WanPipeline
    from transformers import AutoTokenizer, UMT5EncoderModel

    root = require_weights_dir(weights, TEXT_FILES, model="wan-shortcut text encoder", flag="--weights")
    tokenizer = AutoTokenizer.from_pretrained(root, subfolder="tokenizer", local_files_only=True)
    text_encoder = UMT5EncoderModel.from_pretrained(
        root, subfolder="text_encoder", dtype=getattr(torch, dtype), local_files_only=True
    ).to(device)
    pipe = WanPipeline(tokenizer=tokenizer, text_encoder=text_encoder, vae=None, scheduler=None)
    with torch.no_grad():
        pos, neg = pipe.encode_prompt(
            prompt, negative_prompt, do_classifier_free_guidance=True, max_sequence_length=MAX_SEQUENCE_LENGTH,
            device=torch.device(device),
        )
    return {"prompt_embeds": pos.float().cpu(), "negative_prompt_embeds": neg.float().cpu()}


def _fit(n: int, q: int) -> int:
    return max(q, int(round(n / q)) * q)


class WanShortcutGenerator:
    """Warped ERP video + valid mask -> generated ERP video, with the paper's conditioning and samplers."""

    def __init__(self, transformer, vae, cfg: WanShortcutConfig, embeds: dict, pipe=None):
        cfg = dataclasses.replace(cfg, device=resolve_device(cfg.device))
        self.transformer, self.vae, self.cfg, self._pipe = transformer, vae, cfg, pipe
        self.device = torch.device(cfg.device)
        pos = embeds["prompt_embeds"]
        neg = embeds.get("negative_prompt_embeds")
        self.prompt_embeds = pos.to(self.device)
        self.negative_prompt_embeds = (torch.zeros_like(pos) if neg is None else neg).to(self.device)
        self.prompt_source = str(embeds.get("source", "given embeddings"))
        self.temporal = vae.config.scale_factor_temporal
        self.spatial = vae.config.scale_factor_spatial
        self.multiple = self.spatial * transformer.config.patch_size[1]

    @classmethod
    def from_components(
        cls, transformer, vae, cfg: WanShortcutConfig, prompt_embeds: torch.Tensor | dict | None = None
    ) -> WanShortcutGenerator:
        """Wrap loaded diffusers models: widen/extend the transformer (zero-init) unless done, load cfg.extra_weights
        and cfg.lora when given, and place the models (CPU offload or on cfg.device)."""
        wl.import_diffusers()
        cfg = dataclasses.replace(cfg, device=resolve_device(cfg.device))
        if cfg.sampler == Sampler.SHORTCUT:
            shortcut_schedule(cfg.steps)
        if cfg.extra_weights is not None:
            wl.load_extra_weights(transformer, cfg.extra_weights)
        wl.prepare_transformer(transformer, wl.condition_channels(vae))
        if cfg.lora is not None:
            wl.load_lora(transformer, cfg.lora)
        if prompt_embeds is None:
            if cfg.prompt_embeds is None:
                raise MissingWeightsError(f"wan-shortcut: no prompt embeddings; pass --prompt-embeds FILE ({FLAGS})")
            embeds = load_prompt_embeds(cfg.prompt_embeds)
            embeds["source"] = f"embeddings {Path(cfg.prompt_embeds).name}"
        else:
            embeds = dict(prompt_embeds) if isinstance(prompt_embeds, dict) else {"prompt_embeds": prompt_embeds}
        text_dim = transformer.config.text_dim
        if embeds["prompt_embeds"].shape[-1] != text_dim:
            raise ValueError(f"{embeds['prompt_embeds'].shape=} but the transformer expects (1, L, {text_dim})")
        transformer.eval().requires_grad_(False)
        vae.eval().requires_grad_(False)
        if cfg.vae_tiling:
            vae.enable_tiling()
        pipe = None
        if cfg.cpu_offload:
            from diffusers import FlowMatchEulerDiscreteScheduler, WanPipeline

            pipe = WanPipeline(
                tokenizer=None, text_encoder=None, vae=vae, scheduler=FlowMatchEulerDiscreteScheduler(),
                transformer=transformer,
            )
            pipe.enable_model_cpu_offload(device=cfg.device)
        else:
            transformer.to(cfg.device)
            vae.to(cfg.device)
        return cls(transformer, vae, cfg, embeds, pipe)

    @classmethod
    def from_pretrained(cls, cfg: WanShortcutConfig) -> WanShortcutGenerator:
        """Load Wan2.2-TI2V-5B from cfg.weights (local files only), the trained LoRA and extra weights, and the
        prompt embedding (cfg.prompt_embeds, else cfg.prompt through the local UMT5 text encoder)."""
        wl.import_diffusers()
        from diffusers import AutoencoderKLWan, WanTransformer3DModel

        model = "wan-shortcut (Wan2.2-TI2V-5B-Diffusers)"
        root = require_weights_dir(cfg.weights, BASE_FILES, model=model, flag="--weights")
        require_weights_file(cfg.lora, model="wan-shortcut", flag="--lora", expected="the trained LoRA safetensors")
        require_weights_file(
            cfg.extra_weights, model="wan-shortcut", flag="--extra-weights",
            expected="the trained patch/step-size embedding safetensors",
        )
        embeds = None  # from_components reads cfg.prompt_embeds
        if cfg.prompt_embeds is None:
            if not all(any(root.glob(p)) for p in TEXT_FILES):
                raise MissingWeightsError(
                    f"wan-shortcut: {root} has no text encoder ({', '.join(TEXT_FILES)}); "
                    "add it or pass --prompt-embeds FILE"
                )
            # before the transformer is loaded, so the 11 GB UMT5-XXL has the device to itself
            embeds = encode_prompts(root, cfg.prompt, cfg.negative_prompt, dtype=cfg.dtype, device=cfg.device)
            embeds["source"] = cfg.prompt
            if torch.cuda.is_available():
                torch.cuda.empty_cache()
        dtype = getattr(torch, cfg.dtype)
        transformer = WanTransformer3DModel.from_pretrained(
            root, subfolder="transformer", torch_dtype=dtype, local_files_only=True
        )
        vae = AutoencoderKLWan.from_pretrained(root, subfolder="vae", torch_dtype=torch.float32, local_files_only=True)
        return cls.from_components(transformer, vae, cfg, embeds)

    def model_shape(self, t: int, h: int, w: int) -> tuple[int, int, int]:
        """The (T, H, W) the model runs at for an input of (t, h, w): T = 4k+1 >= t, H, W rounded to multiples of 32."""
        frames = (t - 1 + self.temporal - 1) // self.temporal * self.temporal + 1
        return frames, _fit(h, self.multiple), _fit(w, self.multiple)

    def _velocity_fn(self, condition, anchor):
        def fn(x, sigma, dt, positive):
            embeds = self.prompt_embeds if positive else self.negative_prompt_embeds
            b = x.shape[0]
            s = torch.full((b,), sigma, device=x.device)
            d = torch.full((b,), dt, device=x.device)
            return wl.velocity(self.transformer, x, s, d, condition, embeds, anchor)

        return fn

    @torch.no_grad()
    def generate(self, cond_rgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, dict]:
        """Warped ERP frames (T, H, W, 3) uint8 and their valid mask (T, H, W) bool (True = warped pixel is valid,
        False = disoccluded hole) -> generated video (T, H, W, 3) uint8 and info (nfe, sampler, steps, seconds, ...).

        Frames are padded to 4k+1 (repeating the last) and resized to multiples of 32 when needed, then cropped
        and resized back.
        """
        dims = check_shape("cond_rgb", cond_rgb, "T H W 3", dtype=np.uint8)
        check_shape("mask", mask, "T H W", dtype=np.bool_, dims=dims)
        start = time.perf_counter()
        cfg = self.cfg
        t, h, w, _ = cond_rgb.shape
        tm, hm, wm = self.model_shape(t, h, w)
        frames, valid = cond_rgb, mask
        if (hm, wm) != (h, w):
            frames = np.stack([cv2.resize(f, (wm, hm), interpolation=cv2.INTER_AREA) for f in frames])
            small = [cv2.resize(m.astype(np.uint8), (wm, hm), interpolation=cv2.INTER_NEAREST) for m in valid]
            valid = np.stack(small) > 0
        if tm != t:
            frames = np.concatenate([frames, np.repeat(frames[-1:], tm - t, axis=0)])
            valid = np.concatenate([valid, np.repeat(valid[-1:], tm - t, axis=0)])
        cond = torch.from_numpy(frames).to(self.device).permute(3, 0, 1, 2)[None].float() / 127.5 - 1.0
        m = torch.from_numpy(valid).to(self.device)[None, None].float()

        condition = wl.encode_condition(self.vae, cond, m)
        z = self.vae.config.z_dim
        anchor = condition[:, :z, :1] if cfg.anchor_first_frame and wl.anchors_first_frame(valid[0]) else None
        generator = torch.Generator("cpu").manual_seed(cfg.seed)
        noise = torch.randn((1, z, *condition.shape[2:]), generator=generator).to(self.device)
        if cfg.sampler == Sampler.SHORTCUT:
            sigmas, step_sizes = shortcut_schedule(cfg.steps)
        else:
            sigmas, step_sizes = flow_schedule(cfg.steps, cfg.shift)
        latents, nfe = euler_sample(
            self._velocity_fn(condition, anchor), noise, sigmas, step_sizes, guidance=cfg.guidance
        )
        if anchor is not None:
            latents[:, :, :1] = anchor
        video = wl.decode_latents(self.vae, latents)[0, :, :t]
        out = ((video.clamp(-1, 1) + 1.0) * 127.5).round().to(torch.uint8).permute(1, 2, 3, 0).cpu().numpy()
        if (hm, wm) != (h, w):
            out = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_LANCZOS4) for f in out])
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        info = {
            "nfe": int(nfe),
            "sampler": str(cfg.sampler),
            "steps": int(cfg.steps),
            "guidance": float(cfg.guidance),
            "seed": int(cfg.seed),
            "seconds": round(time.perf_counter() - start, 3),
            "model_shape": [tm, hm, wm],
            "latent_shape": list(latents.shape[1:]),
            "anchored_first_frame": anchor is not None,
            "prompt": self.prompt_source,
        }
        return out, info

