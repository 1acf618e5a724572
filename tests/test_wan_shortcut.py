"""wan-shortcut on tiny random Wan2.2-like components: conditioning, zero-init, samplers, NFE, weight IO, losses."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

pytest.importorskip("diffusers")
pytest.importorskip("peft")

from diffusers import AutoencoderKLWan, WanTransformer3DModel

from panoworld.models import wan_layers as wl
from panoworld.models import wan_training as wt
from panoworld.models.wan_shortcut import (
    DEFAULT_PROMPT,
    Sampler,
    WanShortcutConfig,
    WanShortcutGenerator,
    euler_sample,
    save_prompt_embeds,
    shortcut_schedule,
)
from panoworld.models.weights import MissingWeightsError

Z = 4
TEXT_DIM = 16
T, H, W = 5, 64, 128  # -> latents (Z, 2, 4, 8), 2 x 2 x 4 tokens after the 2x2 patch


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def tiny_vae() -> AutoencoderKLWan:
    torch.manual_seed(0)
    return AutoencoderKLWan(
        base_dim=8, z_dim=Z, dim_mult=[1, 1, 1, 1], num_res_blocks=1, temperal_downsample=[False, True, True],
        latents_mean=[0.1, -0.2, 0.0, 0.3], latents_std=[1.5, 0.8, 1.0, 2.0], is_residual=True,
        in_channels=12, out_channels=12, patch_size=2, scale_factor_temporal=4, scale_factor_spatial=16,
    ).eval()


def tiny_transformer(seed: int = 0) -> WanTransformer3DModel:
    torch.manual_seed(seed)
    return WanTransformer3DModel(
        patch_size=(1, 2, 2), num_attention_heads=2, attention_head_dim=8, in_channels=Z, out_channels=Z,
        text_dim=TEXT_DIM, freq_dim=32, ffn_dim=32, num_layers=2, rope_max_seq_len=32,
    ).eval()


def cfg(**kw) -> WanShortcutConfig:
    return WanShortcutConfig(device="cpu", dtype="float32", vae_tiling=False, cpu_offload=False, **kw)


def embeds() -> torch.Tensor:
    return torch.randn(1, 7, TEXT_DIM, generator=torch.Generator().manual_seed(3))


def inputs(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (T, H, W, 3), dtype=np.uint8)
    mask = np.ones((T, H, W), bool)
    mask[1:, :, 40:70] = False
    return rgb, mask


def perturb(module: torch.nn.Module, seed: int, names: tuple[str, ...]) -> None:
    """Stand-in for training: random values in the given (zero-initialised) parameters."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for n, p in module.named_parameters():
            if any(s in n for s in names):
                p.copy_(torch.randn(p.shape, generator=g) * 0.1)


def test_generate_shapes_determinism_and_nfe():
    gen = WanShortcutGenerator.from_components(tiny_transformer(), tiny_vae(), cfg(seed=1), embeds())
    rgb, mask = inputs()
    video, info = gen.generate(rgb, mask)
    assert video.shape == (T, H, W, 3) and video.dtype == np.uint8
    assert video.std() > 0
    assert info["nfe"] == 4 and info["sampler"] == "shortcut" and info["steps"] == 4 and info["seconds"] > 0
    assert info["latent_shape"] == [Z, 2, 4, 8] and info["anchored_first_frame"]
    again, _ = gen.generate(rgb, mask)
    np.testing.assert_array_equal(video, again)
    gen.cfg = dataclasses.replace(gen.cfg, seed=2)
    assert not np.array_equal(gen.generate(rgb, mask)[0], video)

    flow = WanShortcutGenerator.from_components(
        tiny_transformer(), tiny_vae(), cfg(sampler=Sampler.FLOW, steps=10, guidance=5.0), embeds()
    )
    video, info = flow.generate(rgb, mask)
    assert info["nfe"] == 20 and info["sampler"] == "flow" and video.shape == (T, H, W, 3)


def test_odd_sizes_are_fitted_and_restored():
    gen = WanShortcutGenerator.from_components(tiny_transformer(), tiny_vae(), cfg(steps=1), embeds())
    rgb = np.random.default_rng(0).integers(0, 256, (3, 48, 96, 3), dtype=np.uint8)
    video, info = gen.generate(rgb, np.ones((3, 48, 96), bool))
    assert video.shape == (3, 48, 96, 3)
    assert info["model_shape"] == [5, 64, 96]  # T -> 4k+1, H 48 -> 64, W 96 already a multiple of 32
    with pytest.raises(ValueError, match="power of two"):
        WanShortcutGenerator.from_components(tiny_transformer(), tiny_vae(), cfg(steps=3), embeds())
    with pytest.raises(ValueError, match=r"mask.shape="):
        gen.generate(rgb, np.ones((3, 48, 95), bool))


def test_euler_sample_counts_forwards_and_integrates_exactly():
    x0 = torch.randn(2, 3)
    noise = torch.randn(2, 3)
    calls = []

    def straight(x, sigma, dt, positive):  # the exact velocity of the straight path noise -> x0
        calls.append((sigma, dt, positive))
        return noise - x0

    out, nfe = euler_sample(straight, noise, *shortcut_schedule(4), progress=False)
    assert nfe == 4 and [c[1] for c in calls] == [0.25] * 4
    torch.testing.assert_close(out, x0)
    calls.clear()
    _, nfe = euler_sample(straight, noise, *shortcut_schedule(8), guidance=3.0, progress=False)
    assert nfe == 16 and sum(not c[2] for c in calls) == 8


def test_mask_to_latent_follows_first_frame_rule():
    mask = torch.zeros(1, 1, 9, 32, 64)
    mask[:, :, 0] = 1
    mask[:, :, 6, :16, :32] = 1  # frame 6 = latent frame 2 ((6-1)//4 + 1), channel (6-1) % 4 = 1
    small = wl.mask_to_latent(mask, 4, 16)
    assert small.shape == (1, 4, 3, 2, 4)
    assert torch.all(small[0, :, 0] == 1)
    assert small[0, :, 1].sum() == 0
    assert small[0, 1, 2, 0, :2].tolist() == [1.0, 1.0] and small[0, :, 2].sum() == 2


def test_condition_encoding_uses_masked_rgb():
    vae = tiny_vae()
    rgb = torch.rand(1, 3, T, H, W) * 2 - 1
    mask = torch.ones(1, 1, T, H, W)
    mask[:, :, 1:, :, :64] = 0
    with torch.no_grad():
        cond = wl.encode_condition(vae, rgb, mask)
        changed = rgb.clone()
        changed[:, :, 1:, :, :64] = 0.7  # only under the hole: must not change the condition
        torch.testing.assert_close(wl.encode_condition(vae, changed, mask), cond)
    assert cond.shape == (1, Z + 4, 2, 4, 8)
    assert wl.condition_channels(vae) == Z + 4


def test_widened_and_step_embedded_model_equals_base_at_init():
    base = tiny_transformer()
    widened = tiny_transformer()
    wl.prepare_transformer(widened, Z + 4)
    assert widened.config.in_channels == 2 * Z + 4 and widened.patch_embedding.in_channels == 2 * Z + 4
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, Z, 2, 4, 8, generator=g)
    cond = torch.randn(2, Z + 4, 2, 4, 8, generator=g)
    text = torch.randn(2, 7, TEXT_DIM, generator=g)
    sigma = torch.tensor([0.3, 0.9])
    with torch.no_grad():
        ref = base(hidden_states=x, timestep=sigma * 1000, encoder_hidden_states=text, return_dict=False)[0]
        for dt in (0.0, 0.25, 1.0):
            out = wl.velocity(widened, x, sigma, torch.full((2,), dt), cond, text)
            torch.testing.assert_close(out, ref, rtol=0, atol=1e-6)
        # once trained, the condition and the step size do change the output
        perturb(widened, 1, ("patch_embedding", "step_embedder.embedder.linear_2"))
        a = wl.velocity(widened, x, sigma, torch.full((2,), 0.25), cond, text)
        b = wl.velocity(widened, x, sigma, torch.full((2,), 0.5), cond, text)
        c = wl.velocity(widened, x, sigma, torch.full((2,), 0.25), cond * 0, text)
    assert (a - b).abs().max() > 1e-3 and (a - c).abs().max() > 1e-3


def test_anchor_sets_first_frame_timestep_to_zero():
    tr = tiny_transformer()
    wl.prepare_transformer(tr, Z + 4)
    seen = []
    tr.condition_embedder.time_embedder.register_forward_pre_hook(lambda m, a: seen.append(a[0].shape))
    x = torch.randn(1, Z, 2, 4, 8)
    anchor = torch.randn(1, Z, 1, 4, 8)
    cond = torch.randn(1, Z + 4, 2, 4, 8)
    text = torch.randn(1, 7, TEXT_DIM)
    with torch.no_grad():
        v1 = wl.velocity(tr, x, torch.tensor([0.5]), torch.tensor([0.25]), cond, text, anchor)
        x2 = x.clone()
        x2[:, :, 0] += 5.0  # the noisy first frame is replaced by the anchor
        v2 = wl.velocity(tr, x2, torch.tensor([0.5]), torch.tensor([0.25]), cond, text, anchor)
    torch.testing.assert_close(v1, v2)
    assert seen[0] == (1, 16, 32)  # per-token timesteps: 2 latent frames x 2 x 4 tokens


@pytest.fixture
def wan_dir(tmp_path):
    """A tiny 'Wan2.2-TI2V-5B-Diffusers' directory plus trained (LoRA + extra) weights and prompt embeddings."""
    root = tmp_path / "wan"
    tiny_transformer(seed=5).save_pretrained(root / "transformer")
    tiny_vae().save_pretrained(root / "vae")
    save_prompt_embeds(tmp_path / "prompt.safetensors", embeds(), torch.zeros(1, 7, TEXT_DIM))
    trained = WanTransformer3DModel.from_pretrained(root, subfolder="transformer", local_files_only=True)
    params = wt.prepare_for_training(trained, Z + 4, rank=4, alpha=8)
    assert trained.peft_config[wl.ADAPTER_NAME].lora_alpha == 8
    assert params and all(p.requires_grad for p in params)
    perturb(trained, 7, ("lora_B", "patch_embedding", "step_embedder"))
    lora, extra = tmp_path / "out" / "lora.safetensors", tmp_path / "out" / "extra.safetensors"
    lora.parent.mkdir()
    wl.save_trained_weights(trained, lora, extra)
    return {"root": root, "lora": lora, "extra": extra, "prompt": tmp_path / "prompt.safetensors", "trained": trained}


def test_trained_weights_round_trip(wan_dir):
    lora, root = wan_dir["lora"], wan_dir["root"]
    size = int.from_bytes(lora.read_bytes()[:8], "little")
    header = json.loads(lora.read_bytes()[8 : 8 + size])
    assert all(k.startswith("transformer.") for k in header if k != "__metadata__")

    rgb, mask = inputs(1)
    in_memory = WanShortcutGenerator.from_components(wan_dir["trained"], tiny_vae(), cfg(seed=4), embeds())
    expected, _ = in_memory.generate(rgb, mask)
    loaded = WanShortcutGenerator.from_pretrained(
        cfg(weights=root, lora=lora, extra_weights=wan_dir["extra"], prompt_embeds=wan_dir["prompt"], seed=4)
    )
    assert loaded.transformer.peft_config[wl.ADAPTER_NAME].lora_alpha == 8
    video, info = loaded.generate(rgb, mask)
    np.testing.assert_array_equal(video, expected)
    assert info["prompt"] == "embeddings prompt.safetensors"
    # the trained weights matter: without the LoRA, or without both, the video differs
    extra_only = WanShortcutGenerator.from_components(
        WanTransformer3DModel.from_pretrained(root, subfolder="transformer", local_files_only=True),
        tiny_vae(), cfg(seed=4, extra_weights=wan_dir["extra"]), embeds(),
    )
    assert not np.array_equal(extra_only.generate(rgb, mask)[0], expected)
    plain = WanShortcutGenerator.from_components(
        WanTransformer3DModel.from_pretrained(root, subfolder="transformer", local_files_only=True),
        tiny_vae(), cfg(seed=4), embeds(),
    )
    assert not np.array_equal(plain.generate(rgb, mask)[0], expected)


def test_prompt_through_local_text_encoder(wan_dir):
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, UMT5Config, UMT5EncoderModel

    root = wan_dir["root"]
    words = "a panoramic video walking through an indoor scene kitchen".split()
    vocab = {"<pad>": 0, "</s>": 1, "<unk>": 2, **{w: i + 3 for i, w in enumerate(words)}}
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, pad_token="<pad>", eos_token="</s>", unk_token="<unk>")
    fast.save_pretrained(root / "tokenizer")
    torch.manual_seed(0)
    config = UMT5Config(vocab_size=len(vocab), d_model=TEXT_DIM, d_kv=4, d_ff=32, num_layers=1, num_heads=2)
    UMT5EncoderModel(config).save_pretrained(root / "text_encoder")
    base = cfg(weights=root, lora=wan_dir["lora"], extra_weights=wan_dir["extra"], steps=2)
    gen = WanShortcutGenerator.from_pretrained(base)
    pos = gen.prompt_embeds
    assert pos.shape == (1, 512, TEXT_DIM)  # Wan pads prompts to 512 tokens with zeros
    assert pos[0, :8].abs().sum(-1).min() > 0 and pos[0, 8:].abs().sum() == 0  # 8 words of the default prompt
    other = WanShortcutGenerator.from_pretrained(dataclasses.replace(base, prompt="a kitchen"))
    assert not torch.equal(other.prompt_embeds, pos)
    rgb, mask = inputs()
    video, info = gen.generate(rgb, mask)
    assert info["prompt"] == DEFAULT_PROMPT
    assert not np.array_equal(video, other.generate(rgb, mask)[0])


def test_cpu_offload_hooks_give_the_same_video():
    rgb, mask = inputs()
    ref, _ = WanShortcutGenerator.from_components(tiny_transformer(), tiny_vae(), cfg(), embeds()).generate(rgb, mask)
    offload = WanShortcutConfig(device="cpu", dtype="float32", cpu_offload=True, vae_tiling=True)
    gen = WanShortcutGenerator.from_components(tiny_transformer(), tiny_vae(), offload, embeds())
    assert hasattr(gen.transformer, "_hf_hook") and gen.vae.use_tiling
    np.testing.assert_array_equal(gen.generate(rgb, mask)[0], ref)


def test_missing_weights_name_files_and_flags(tmp_path):
    with pytest.raises(MissingWeightsError, match="--weights DIR"):
        WanShortcutGenerator.from_pretrained(cfg())
    (tmp_path / "transformer").mkdir()
    (tmp_path / "transformer" / "config.json").write_text("{}")
    with pytest.raises(MissingWeightsError) as e:
        WanShortcutGenerator.from_pretrained(cfg(weights=tmp_path))
    msg = str(e.value)
    assert "transformer/diffusion_pytorch_model*.safetensors" in msg and "vae/config.json" in msg
    assert "transformer/config.json," not in msg.split("lacks")[1].split(";")[0]
    for sub in ("transformer", "vae"):
        (tmp_path / sub).mkdir(exist_ok=True)
        (tmp_path / sub / "config.json").write_text("{}")
        (tmp_path / sub / "diffusion_pytorch_model.safetensors").write_bytes(b"")
    with pytest.raises(MissingWeightsError, match="--lora FILE"):
        WanShortcutGenerator.from_pretrained(cfg(weights=tmp_path))
    (tmp_path / "lora.safetensors").write_bytes(b"")
    with pytest.raises(MissingWeightsError, match="--extra-weights"):
        WanShortcutGenerator.from_pretrained(cfg(weights=tmp_path, lora=tmp_path / "lora.safetensors"))
    (tmp_path / "extra.safetensors").write_bytes(b"")
    with pytest.raises(MissingWeightsError, match="--prompt-embeds FILE"):
        WanShortcutGenerator.from_pretrained(
            cfg(weights=tmp_path, lora=tmp_path / "lora.safetensors", extra_weights=tmp_path / "extra.safetensors")
        )


def _training_batch(b: int):
    """A tiny VAE + widened transformer with LoRA, and a batch of b clips: (tr, params, x0, cond, text, generator)."""
    vae, tr = tiny_vae(), tiny_transformer()
    params = wt.prepare_for_training(tr, wl.condition_channels(vae), rank=4, alpha=4)
    g = torch.Generator().manual_seed(0)
    video = torch.rand(b, 3, T, H, W, generator=g) * 2 - 1
    mask = (torch.rand(b, 1, T, H, W, generator=g) > 0.3).float()
    with torch.no_grad():
        x0 = wl.encode_video(vae, video)
        cond = wl.encode_condition(vae, video, mask)
    return tr, params, x0, cond, torch.randn(b, 7, TEXT_DIM, generator=g), g


def test_training_step_lowers_the_mixed_objective():
    tr, params, x0, cond, text, g = _training_batch(2)

    def eval_loss() -> float:
        eg = torch.Generator().manual_seed(123)
        with torch.no_grad():
            return sum(
                wt.flow_matching_loss(tr, x0, cond, text, generator=eg).item()
                + wt.self_consistency_loss(tr, x0, cond, text, generator=eg).item()
                for _ in range(4)
            )

    before = eval_loss()
    opt = torch.optim.AdamW(params, lr=3e-3)
    branches = set()
    tr.train()
    for _ in range(40):
        loss, branch = wt.shortcut_objective(tr, x0, cond, text, generator=g)
        branches.add(branch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert branches == {"fm", "sc"}
    assert eval_loss() < 0.8 * before
    frozen = [n for n, p in tr.named_parameters() if p.requires_grad and "lora_" not in n]
    assert frozen and all(n.startswith(("patch_embedding.", "step_embedder.")) for n in frozen)


def test_frozen_teacher_is_unchanged_by_a_training_step_and_gives_the_targets():
    vae, tr = tiny_vae(), tiny_transformer()
    params = wt.prepare_for_training(tr, wl.condition_channels(vae), rank=4, alpha=4)
    perturb(tr, 3, ("lora_B", "step_embedder.embedder.linear_2"))
    teacher = wt.EmaTeacher(tr, decay=0.99)
    before = {n: t.clone() for n, t in teacher.shadow.items()}
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(2, Z, 2, 4, 8, generator=g)
    cond = torch.randn(2, Z + 4, 2, 4, 8, generator=g)
    text = torch.randn(2, 7, TEXT_DIM, generator=g)
    opt = torch.optim.AdamW(params, lr=1e-2)
    student_before = [p.detach().clone() for p in params]
    loss = wt.self_consistency_loss(tr, x0, cond, text, generator=torch.Generator().manual_seed(1), teacher=teacher)
    opt.zero_grad()
    loss.backward()
    opt.step()
    assert all(not t.requires_grad for t in teacher.shadow.values())
    for n, t in teacher.shadow.items():  # the optimiser step moved the student, not the teacher
        torch.testing.assert_close(t, before[n], rtol=0, atol=0)
    assert any((p - q).abs().max() > 0 for p, q in zip(params, student_before))
    # the teacher's targets are its own weights': equal to a student holding the shadow weights
    with teacher.swapped():
        v_t = wl.velocity(tr, x0, torch.full((2,), 0.5), torch.full((2,), 0.25), cond, text)
    v_s = wl.velocity(tr, x0, torch.full((2,), 0.5), torch.full((2,), 0.25), cond, text)
    assert (v_t - v_s).abs().max() > 0 and all(p.requires_grad for p in params)
    teacher.update()  # only update() moves it: shadow <- 0.99 shadow + 0.01 student
    n0, p0 = next(iter(teacher.params.items()))
    torch.testing.assert_close(teacher.shadow[n0], 0.99 * before[n0] + 0.01 * p0.detach())
    state = teacher.state_dict()
    other = wt.EmaTeacher(tr, decay=0.5)
    other.load_state_dict(state)
    assert other.decay == 0.99 and all(torch.equal(other.shadow[n], teacher.shadow[n]) for n in state["shadow"])


def test_discrete_sigma_is_t_over_n():
    s = wt.sample_sigma(4000, 8, torch.Generator().manual_seed(0))
    assert set((s * 8).round().int().tolist()) == set(range(1, 9))
    torch.testing.assert_close(s * 8, (s * 8).round())
    c = wt.sample_sigma(1000, 0, torch.Generator().manual_seed(0))
    assert len(set(c.tolist())) == 1000 and 0 <= c.min() and c.max() < 1


def test_self_consistency_target_is_the_mean_of_the_teachers_two_half_steps_on_the_grid(monkeypatch):
    vae, tr = tiny_vae(), tiny_transformer()
    wt.prepare_for_training(tr, wl.condition_channels(vae), rank=4, alpha=4)
    perturb(tr, 3, ("lora_B", "step_embedder.embedder.linear_2"))
    teacher = wt.EmaTeacher(tr, decay=0.99)
    perturb(tr, 4, ("lora_B", "step_embedder.embedder.linear_2"))  # the student now differs from its teacher
    name, param = next(iter(teacher.params.items()))
    calls, real = [], wl.velocity

    def spy(model, x_t, sigma, dt, condition, prompt_embeds, anchor=None):
        out = real(model, x_t, sigma, dt, condition, prompt_embeds, anchor)
        calls.append({"x": x_t.detach().clone(), "sigma": sigma.clone(), "dt": dt.clone(), "v": out.detach().clone(),
                      "teacher": param.data.data_ptr() == teacher.shadow[name].data_ptr()})
        return out

    monkeypatch.setattr(wl, "velocity", spy)
    b, max_steps = 48, 8
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(b, Z, 2, 4, 8, generator=g)
    cond = torch.randn(b, Z + 4, 2, 4, 8, generator=g)
    text = torch.randn(b, 7, TEXT_DIM, generator=g)
    loss = wt.self_consistency_loss(tr, x0, cond, text, generator=torch.Generator().manual_seed(1),
                                    max_steps=max_steps, teacher=teacher)
    assert [c["teacher"] for c in calls] == [True, True, False]
    first, second, student = calls
    dt, sigma = student["dt"].double(), student["sigma"].double()
    # the grid: dt in {1, 1/2, ..., 2/max_steps}, sigma = j dt with j in 1..1/dt; every level is drawn
    assert set(dt.tolist()) == {1.0, 0.5, 0.25}
    j = sigma / dt
    torch.testing.assert_close(j, j.round(), rtol=0, atol=1e-6)
    assert bool((j >= 1).all()) and bool((j <= 1 / dt + 1e-9).all())
    # the teacher: two half steps of dt/2 from (x_t, sigma), the finest half step is the plain flow (dt 0)
    half = dt / 2
    teacher_dt = torch.where(half <= 1 / max_steps, torch.zeros_like(half), half)
    torch.testing.assert_close(first["dt"].double(), teacher_dt)
    torch.testing.assert_close(second["dt"].double(), teacher_dt)
    torch.testing.assert_close(first["sigma"], student["sigma"])
    torch.testing.assert_close(second["sigma"].double(), sigma - half)
    torch.testing.assert_close(first["x"], student["x"])
    torch.testing.assert_close(second["x"], first["x"] - half.float().view(-1, 1, 1, 1, 1) * first["v"])
    # recomputed independently with the teacher's weights, the target is the mean of its two velocities
    monkeypatch.setattr(wl, "velocity", real)
    with teacher.swapped():
        v1 = real(tr, first["x"], first["sigma"], first["dt"], cond, text)
        v2 = real(tr, first["x"] - half.float().view(-1, 1, 1, 1, 1) * v1, second["sigma"], second["dt"], cond, text)
    torch.testing.assert_close(v1, first["v"])
    target = (v1 + v2) / 2
    torch.testing.assert_close(loss.detach(), ((student["v"] - target) ** 2).mean())
    # and it is not the student's own two half steps (the teacher's weights differ)
    s1 = real(tr, first["x"], first["sigma"], first["dt"], cond, text).detach()
    assert (s1 - v1).abs().max() > 1e-4


def test_one_clip_per_path_frames_back_in_pose_order():
    """wan-shortcut generates each path of a multi-path trajectory as its own clip (source view first) and puts the
    frames back in pose order: each path's frames equal that path generated alone."""
    from panoworld.video.backends.wan_shortcut import generate_clips

    gen = WanShortcutGenerator.from_components(tiny_transformer(), tiny_vae(), cfg(seed=2), embeds())
    rgb, mask = inputs(4)
    clips = [[0, 1, 2], [0, 3, 4]]
    frames, info = generate_clips(gen, rgb, mask, clips)
    assert info["clips"] == 2 and info["clip_frames"] == [3, 3] and len(frames) == T
    for idx in clips:
        alone, _ = gen.generate(rgb[idx], mask[idx])
        for i, f in zip(idx[1:], alone[1:]):
            np.testing.assert_array_equal(frames[i], f)
    first, _ = gen.generate(rgb[clips[0]], mask[clips[0]])
    np.testing.assert_array_equal(frames[0], first[0])
    whole, _ = gen.generate(rgb, mask)  # one sequence across both paths differs: path 2 would continue path 1
    assert not np.array_equal(np.stack(frames[3:]), whole[3:])
    with pytest.raises(ValueError, match="without a frame"):
        generate_clips(gen, rgb, mask, [[0, 1, 2]])


def test_batch_split_gives_a_quarter_of_every_batch_to_self_consistency():
    """split='batch' (Frans et al.): the first round((1 - rho) B) samples take L_SC, the rest L_FM, and the loss is
    the per-sample mean; split='iteration' (the paper) sends the whole batch to one loss."""
    torch.set_num_threads(1)
    tr, _, x0, cond, text, _ = _training_batch(4)
    perturb(tr, 5, ("lora_B", "step_embedder.embedder.linear_2"))
    with torch.no_grad():
        loss, branch = wt.shortcut_objective(tr, x0, cond, text, rho=0.75, split="batch",
                                             generator=torch.Generator().manual_seed(7))
        eg = torch.Generator().manual_seed(7)
        sc = wt.self_consistency_loss(tr, x0[:1], cond[:1], text[:1], generator=eg)
        fm = wt.flow_matching_loss(tr, x0[1:], cond[1:], text[1:], generator=eg)
        fm_all, fm_branch = wt.shortcut_objective(tr, x0, cond, text, rho=1.0, split="batch",
                                                  generator=torch.Generator().manual_seed(7))
    assert branch == "mixed" and fm_branch == "fm"
    assert float(sc) != pytest.approx(float(fm), rel=0.05)  # the weighting below is visible
    assert float(loss) == pytest.approx((1 * float(sc) + 3 * float(fm)) / 4, rel=1e-5)
    with pytest.raises(ValueError, match="split='half'"):
        wt.shortcut_objective(tr, x0, cond, text, split="half")
    assert torch.isfinite(fm_all)
