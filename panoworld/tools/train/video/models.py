"""The frozen base of the video trainer: Wan2.2-TI2V-5B from a local directory, or a tiny Wan-architecture stand-in."""

from __future__ import annotations

from pathlib import Path

import torch

from panoworld.models import wan_layers as wl
from panoworld.tools.train.video.config import VideoTrainConfig


def tiny_vae(cfg: VideoTrainConfig):
    """A tiny Wan2.2-style VAE (patchified, residual): 8x spatial, 4x temporal, cfg.tiny_z latent channels."""
    from diffusers import AutoencoderKLWan

    z = cfg.tiny_z
    return AutoencoderKLWan(
        base_dim=8, z_dim=z, dim_mult=[1, 2, 2], num_res_blocks=1, temperal_downsample=[True, True],
        latents_mean=[0.0] * z, latents_std=[1.0] * z, is_residual=True, in_channels=12, out_channels=12,
        patch_size=2, scale_factor_temporal=4, scale_factor_spatial=8,
    )


def tiny_transformer(cfg: VideoTrainConfig):
    """A tiny WanTransformer3DModel (cfg.tiny_layers blocks, head dim 16) on cfg.tiny_z latent channels."""
    from diffusers import WanTransformer3DModel

    return WanTransformer3DModel(
        patch_size=(1, 2, 2), num_attention_heads=cfg.tiny_heads, attention_head_dim=16, in_channels=cfg.tiny_z,
        out_channels=cfg.tiny_z, text_dim=cfg.tiny_text_dim, freq_dim=64, ffn_dim=4 * 16 * cfg.tiny_heads,
        num_layers=cfg.tiny_layers, rope_max_seq_len=256,
    )


def tiny_prompt_embeds(cfg: VideoTrainConfig) -> torch.Tensor:
    """The tiny base's fixed 'prompt': a seeded random (1, 8, text_dim) embedding (no text encoder at this size)."""
    return torch.randn(1, 8, cfg.tiny_text_dim, generator=torch.Generator().manual_seed(12345))


def load_wan(weights: Path, cfg: VideoTrainConfig, device):
    """(transformer, vae, prompt embeds) from a local Wan2.2-TI2V-5B-Diffusers directory (never downloads)."""
    wl.import_diffusers()
    from diffusers import AutoencoderKLWan, WanTransformer3DModel

    from panoworld.models.wan_shortcut import BASE_FILES, encode_prompts
    from panoworld.models.weights import require_weights_dir

    root = require_weights_dir(weights, BASE_FILES, model="train video (Wan2.2-TI2V-5B-Diffusers)", flag="--weights")
    embeds = None
    if (root / "text_encoder").is_dir():
        embeds = encode_prompts(root, cfg.prompt, dtype="bfloat16" if device.type == "cuda" else "float32",
                                device=str(device))["prompt_embeds"]
        if device.type == "cuda":
            torch.cuda.empty_cache()
    # the frozen backbone in bf16 on CUDA (10 GB instead of 20); trainable tensors are cast back to fp32 after LoRA
    dtype = torch.bfloat16 if device.type == "cuda" and cfg.mixed_precision != "no" else torch.float32
    transformer = WanTransformer3DModel.from_pretrained(root, subfolder="transformer", local_files_only=True,
                                                       torch_dtype=dtype)
    vae = AutoencoderKLWan.from_pretrained(root, subfolder="vae", local_files_only=True, torch_dtype=torch.float32)
    if embeds is None:
        if not (root / "prompt_embeds.safetensors").is_file():
            from panoworld.models.weights import MissingWeightsError

            raise MissingWeightsError(f"train video: {root} has neither text_encoder/ (UMT5 of Wan2.2-TI2V-5B) nor "
                                      "prompt_embeds.safetensors to embed the prompt; add one of them")
        embeds = _load_embeds(root / "prompt_embeds.safetensors")
    return transformer, vae, embeds


def _load_embeds(path: Path) -> torch.Tensor:
    from panoworld.models.wan_shortcut import load_prompt_embeds

    return load_prompt_embeds(path)["prompt_embeds"]


def load_base_dir_part(root: Path, part: str):
    """The `transformer` or `vae` saved by save_base in `root` (diffusers layout, local files only)."""
    from diffusers import AutoencoderKLWan, WanTransformer3DModel

    cls = {"transformer": WanTransformer3DModel, "vae": AutoencoderKLWan}[part]
    return cls.from_pretrained(root, subfolder=part, local_files_only=True)


def save_base(root: Path, transformer=None, vae=None, prompt_embeds: torch.Tensor | None = None) -> None:
    """Write the parts given in the diffusers layout the video stage loads (transformer/, vae/, prompt embeds)."""
    from panoworld.models.wan_shortcut import save_prompt_embeds

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if transformer is not None:
        transformer.save_pretrained(root / "transformer")
    if vae is not None:
        vae.save_pretrained(root / "vae")
    if prompt_embeds is not None:
        save_prompt_embeds(root / "prompt_embeds.safetensors", prompt_embeds, torch.zeros_like(prompt_embeds))


def vae_loss(vae, video: torch.Tensor, kl_weight: float = 1e-6) -> torch.Tensor:
    """Autoencoder loss of the tiny VAE on (B, 3, T, H, W) in [-1, 1]: L1 + MSE of the reconstruction + a small KL."""
    posterior = vae.encode(video).latent_dist
    rec = vae.decode(posterior.sample()).sample
    return (rec - video).abs().mean() + ((rec - video) ** 2).mean() + kl_weight * posterior.kl().mean()


@torch.no_grad()
def set_latent_stats(vae, videos: list[torch.Tensor]) -> None:
    """Per-channel mean/std of the VAE's latents over `videos` into its config (Wan normalises latents with them)."""
    lat = torch.cat([vae.encode(v[None]).latent_dist.mode().flatten(2) for v in videos], dim=2)[0]
    vae.register_to_config(latents_mean=lat.mean(1).tolist(), latents_std=lat.std(1).clamp_min(1e-3).tolist())


class Trainable:
    """state_dict()/load_state_dict() of a module's trainable tensors only (checkpoints stay small with a 5B base)."""

    def __init__(self, module: torch.nn.Module):
        self.module = module

    def state_dict(self) -> dict:
        return {n: p.detach().clone() for n, p in self.module.named_parameters() if p.requires_grad}

    def load_state_dict(self, state: dict) -> None:
        params = dict(self.module.named_parameters())
        missing = sorted(set(state) ^ {n for n, p in params.items() if p.requires_grad})
        if missing:
            raise ValueError(f"checkpoint does not match the model's trainable tensors ({missing[:4]})")
        with torch.no_grad():
            for n, t in state.items():
                params[n].copy_(t)
