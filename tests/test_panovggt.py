import json

import numpy as np
import pytest
import torch

from panoworld.models.panovggt import PanoVGGT
from panoworld.models.panovggt_config import PanoVGGTConfig
from panoworld.models.panovggt_layers import ErpCorrelation, erp_coordinate_features, erp_resize, quat_wxyz_to_rotmat
from panoworld.models.weights import MissingWeightsError

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def no_grad():
    with torch.no_grad():
        yield


def tiny_config(**kw) -> PanoVGGTConfig:
    base = dict(
        patch_size=8, embed_dim=32, depth=4, num_heads=2, num_register_tokens=2, coord_frequencies=4,
        camera_trunk_depth=1, camera_iterations=2, dpt_layers=(0, 1, 2, 3), dpt_features=16,
        dpt_out_channels=(8, 16, 32, 32), image_height=32,
    )
    base.update(kw)
    return PanoVGGTConfig(**base)


def tiny_model(seed: int = 0) -> PanoVGGT:
    torch.manual_seed(seed)
    return PanoVGGT(tiny_config()).eval()


def frames(s: int = 3, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(1, s, 3, 32, 64, generator=g)


def test_output_shapes_and_ranges():
    out = tiny_model()(frames(3))
    assert out["world_from_cam"].shape == (1, 3, 4, 4) and out["world_from_cam"].dtype == torch.float64
    assert out["pose_enc"].shape == (1, 3, 7)
    assert out["depth"].shape == (1, 3, 32, 64) and out["depth_conf"].shape == (1, 3, 32, 64)
    assert (out["depth"] > 0).all() and (out["depth_conf"] >= 1).all()
    R = out["world_from_cam"][0, :, :3, :3]
    np.testing.assert_allclose((R.transpose(1, 2) @ R).numpy(), np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-9)
    np.testing.assert_allclose(out["world_from_cam"][0, :, 3].numpy(), [[0, 0, 0, 1]] * 3)


def test_frame0_is_identity_by_construction_and_others_are_relative_to_it():
    out = tiny_model()(frames(4))
    T = out["world_from_cam"][0]
    assert torch.equal(T[0], torch.eye(4, dtype=torch.float64))
    assert not torch.allclose(T[1], torch.eye(4, dtype=torch.float64), atol=1e-4)  # random weights: a real pose
    # world_from_cam_i = P_0^-1 P_i with P_i the raw per-frame poses of the camera head.
    enc = out["pose_enc"][0].double()
    P = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    P[:, :3, :3] = quat_wxyz_to_rotmat(enc[:, 3:])
    P[:, :3, 3] = enc[:, :3]
    np.testing.assert_allclose(T[1:].numpy(), (torch.linalg.inv(P[0]) @ P[1:]).numpy(), atol=1e-12)


def test_deterministic_and_batch_consistent():
    m = tiny_model()
    x = frames(3)
    a, b = m(x), m(x)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert torch.equal(tiny_model(0).state_dict()["coord_embed.weight"], tiny_model(0).state_dict()["coord_embed.weight"])
    both = m(torch.cat([x, frames(3, seed=5)]))
    torch.testing.assert_close(both["depth"][:1], a["depth"], rtol=1e-4, atol=1e-5)


def test_non_reference_frames_are_permutation_equivariant():
    # Swapping frames 1 and 2 swaps their outputs; frame 0 is special (its own camera/register tokens).
    m = tiny_model()
    x = frames(3)
    out = m(x)
    out_sw = m(x[:, [0, 2, 1]])
    torch.testing.assert_close(out_sw["world_from_cam"][0, 1], out["world_from_cam"][0, 2], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out_sw["depth"][0, 2], out["depth"][0, 1], rtol=1e-4, atol=1e-5)


def test_save_load_round_trip(tmp_path):
    m = tiny_model(3)
    m.save_pretrained(tmp_path / "w")
    assert json.loads((tmp_path / "w" / "config.json").read_text())["embed_dim"] == 32
    m2 = PanoVGGT.from_pretrained(tmp_path / "w")
    x = frames(2)
    a, b = m(x), m2(x)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    pred = m2.predict((x[0].permute(0, 2, 3, 1).numpy() * 255).astype(np.uint8))
    assert pred["world_from_cam"].shape == (2, 4, 4) and pred["depth"].shape == (2, 32, 64)


def test_missing_or_mismatched_weights_name_the_flag(tmp_path):
    with pytest.raises(MissingWeightsError, match="pass --weights DIR holding config.json, model.safetensors"):
        PanoVGGT.from_pretrained(None)
    (tmp_path / "w").mkdir()
    with pytest.raises(MissingWeightsError, match="--weights .* lacks config.json, model.safetensors"):
        PanoVGGT.from_pretrained(tmp_path / "w")
    tiny_model().save_pretrained(tmp_path / "w")
    cfg = json.loads((tmp_path / "w" / "config.json").read_text())
    cfg["depth"] = 5
    (tmp_path / "w" / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(MissingWeightsError, match="does not match config.json: missing"):
        PanoVGGT.from_pretrained(tmp_path / "w")
    cfg["depth"], cfg["embed_dim"] = 4, 48
    (tmp_path / "w" / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(MissingWeightsError, match="does not match config.json: .*size mismatch"):
        PanoVGGT.from_pretrained(tmp_path / "w")


def test_coordinate_encoding_wraps_across_the_erp_seam():
    hp, wp, f = 4, 16, 5
    enc = erp_coordinate_features(hp, wp, f)
    assert enc.shape == (hp, wp, 4 * f)
    # Shifting longitude by whole patches equals rolling the grid (horizontal-wrap equivariance).
    for m in (1, 3, wp - 1, wp):
        shifted = erp_coordinate_features(hp, wp, f, lon_offset=2 * np.pi * m / wp)
        np.testing.assert_allclose(shifted, np.roll(enc, -m, axis=1), atol=1e-5)
    # Continuous at the seam: the last and first columns are as close as any two neighbours.
    step = np.linalg.norm(enc[:, 1] - enc[:, 0], axis=-1)
    seam = np.linalg.norm(enc[:, 0] - enc[:, -1], axis=-1)
    np.testing.assert_allclose(seam, step, rtol=1e-5)
    # Distinct patches get distinct codes.
    flat = enc.reshape(-1, 4 * f)
    d = np.linalg.norm(flat[:, None] - flat[None], axis=-1) + np.eye(len(flat))
    assert d.min() > 1e-3


def test_erp_resize_wraps_and_matches_plain_interpolation_inside():
    x = torch.rand(1, 2, 4, 8)
    up = erp_resize(x, (16, 32))
    plain = torch.nn.functional.interpolate(x, size=(16, 32), mode="bilinear", align_corners=False)
    torch.testing.assert_close(up[..., 4:-4], plain[..., 4:-4])
    rolled = erp_resize(torch.roll(x, 1, dims=-1), (16, 32))
    torch.testing.assert_close(rolled, torch.roll(up, 4, dims=-1))


def test_rejects_non_erp_or_misaligned_input():
    m = tiny_model()
    with pytest.raises(ValueError, match="expected \\(B, S, 3, H, W\\)"):
        m(torch.rand(3, 3, 32, 64))
    with pytest.raises(ValueError, match="W = 2H with H a multiple of 8"):
        m(torch.rand(1, 2, 3, 36, 72))
    with pytest.raises(ValueError, match="dpt_layers"):
        tiny_config(dpt_layers=(0, 1, 2, 9))


HEAD = {
    "embed_dim": 16, "num_heads": 2, "global_layers": 1, "feature_dim": 8, "voxel_size": 0.2, "knn_k": 4,
    "knn_layers": 1, "knn_heads": 2, "token_dim": 16, "pe_freqs": 2, "mlp_hidden": 16,
}


def head_model(seed: int = 0, **head) -> PanoVGGT:
    torch.manual_seed(seed)
    return PanoVGGT(tiny_config(gaussian_head={**HEAD, **head})).eval()


def test_paper_sizes_fit_392x784():
    cfg = PanoVGGTConfig(gaussian_head={})
    assert cfg.image_height % cfg.patch_size == 0 and (2 * cfg.image_height) % cfg.patch_size == 0
    assert cfg.to_json()["gaussian_head"]["voxel_size"] == 0.02
    with pytest.raises(ValueError, match="backbone_layer"):
        tiny_config(gaussian_head={**HEAD, "backbone_layer": 4})


def test_gaussian_head_shares_the_backbone_tokens():
    m = head_model()
    x = frames(2)
    out = m(x, with_tokens=True)
    assert out["tokens"].shape == (1, 2, 4 * 8, 64)  # (B, S, patches, 2 * embed_dim)
    plain = tiny_model()(x)  # the same seed builds the same backbone, camera and depth heads
    gauss_free = {k: v for k, v in out.items() if k != "tokens"}
    for k in plain:
        torch.testing.assert_close(gauss_free[k], plain[k], msg=k)
    with torch.enable_grad():
        g = m.gaussians(x[0])
        g["gaussians"].sh_dc.square().mean().backward()
    grads = {k: [p.grad for p in v] for k, v in m.heads().items()}
    assert all(gr is None for k in ("backbone", "camera", "depth") for gr in grads[k])  # frozen in stage 2
    assert any(gr is not None and gr.abs().sum() > 0 for gr in grads["gaussian"])
    # Geometry given (a poses artifact's) replaces the predicted one; the centres follow the given depth.
    depth = torch.full((2, 32, 64), 2.0)
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    centres = m.gaussians(x[0], depth, poses)["centres"]
    r = centres.norm(dim=1)
    assert float(r.min()) > 2.0 - 0.2 * 1.8 and float(r.max()) < 2.0 + 0.2 * 1.8


def test_decode_context_frames_and_round_trip(tmp_path):
    from panoworld.io.gaussian_set import ContextFrames

    m = head_model(2)
    m.save_pretrained(tmp_path / "w")
    m2 = PanoVGGT.from_pretrained(tmp_path / "w")
    assert m2.cfg == m.cfg and m2.gaussian_head is not None
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (2, 64, 128, 3), dtype=np.uint8)  # stored at twice the model's size: resized
    depth = np.full((2, 64, 128), 1.5, np.float32)
    depth[0, :4] = np.nan
    cf = ContextFrames(rgb, depth, np.eye(4)[None].repeat(2, 0), [0, 5], "video")
    a, b = m.decode(cf), m2.decode(cf)
    assert a.backend == "decoder" and a.voxel_size == 0.2 and len(a.gaussians) == 2 * a.num_voxels
    assert np.array_equal(a.gaussians.means, b.gaussians.means) and np.array_equal(a.gaussians.sh_dc, b.gaussians.sh_dc)
    assert isinstance(a.gaussians.means, np.ndarray)


def test_weights_without_a_gaussian_head_name_stage_2(tmp_path):
    from panoworld.io.gaussian_set import ContextFrames

    tiny_model().save_pretrained(tmp_path / "w")
    m = PanoVGGT.from_pretrained(tmp_path / "w")
    cf = ContextFrames(np.zeros((1, 32, 64, 3), np.uint8), np.ones((1, 32, 64), np.float32), np.eye(4)[None], [0], "v")
    with pytest.raises(MissingWeightsError, match="no Gaussian head.*--stage 2"):
        m.decode(cf)
    with pytest.raises(ValueError, match="needs a model with a Gaussian head"):
        m(frames(1), with_tokens=True)


def test_gradient_checkpointing_gives_the_same_gradients():
    x = frames(2)
    grads = []
    for ckpt in (False, True):
        m = tiny_model().train()
        m.gradient_checkpointing = ckpt
        with torch.enable_grad():
            out = m(x)
            (out["depth"].mean() + out["pose_enc"].square().sum()).backward()
        grads.append(m.frame_blocks[0].attn.qkv.weight.grad.clone())
    torch.testing.assert_close(grads[0], grads[1])


def test_gaussians_stage_decoder_backend_loads_the_export(tmp_path):
    from panoworld.framework.stage import StageInputError, execute_stage, load_stage
    from stages.gaussians import DecoderOptions, Params
    from tests.test_gaussians import room as room_fixture
    from tests.test_gaussians import write_inputs

    video, poses = write_inputs(tmp_path, room_fixture.__wrapped__())
    head_model(4).save_pretrained(tmp_path / "w")
    digests = {"video": "0" * 64, "poses": "1" * 64}
    info = execute_stage(load_stage("gaussians"), {"video": video, "poses": poses},
                         Params(backend="decoder", decoder=DecoderOptions(weights=str(tmp_path / "w")), eval_views=1,
                                eval_height=32),
                         tmp_path / "out", input_digests=digests)["info"]
    assert info["backend"] == "decoder" and info["voxel_size"] == 0.2 and info["num_gaussians"] > 10
    tiny_model().save_pretrained(tmp_path / "nohead")
    with pytest.raises(StageInputError, match="no Gaussian head"):
        execute_stage(load_stage("gaussians"), {"video": video, "poses": poses},
                      Params(backend="decoder", decoder=DecoderOptions(weights=str(tmp_path / "nohead"))), tmp_path / "out2",
                      input_digests=digests)


def test_pose_correlation_finds_a_whole_patch_turn_and_runs_at_any_grid():
    torch.manual_seed(0)
    yaw = ErpCorrelation(16, 8, 8)
    with torch.no_grad():
        yaw.log_temperature.fill_(5.0)  # a sharp softmax: the expected roll angle is the peak's
    hp, wp = 3, 8
    f0 = torch.randn(1, 1, hp, wp, 16)
    for m in range(wp):
        # Frame 1 = frame 0 turned by m patches (its columns rolled by m): the cue reads angle 2 pi m / wp.
        tokens = torch.cat([f0, f0.roll(m, dims=3)], 1).reshape(1, 2, hp * wp, 16)
        cue = yaw.cue(tokens, (hp, wp), torch.ones(1, 2, 6, 16))[0]
        a = 2 * np.pi * m / wp
        # A pure turn moves every column alike and matches each perfectly: no translation cue (entries 4-7).
        np.testing.assert_allclose(cue[1, [0, 1, 2, 4, 5, 6, 7]].numpy(), [np.cos(a), np.sin(a), 1, 0, 0, 0, 0],
                                   atol=1e-3)
        np.testing.assert_allclose(cue[0, [0, 1, 2, 4, 5, 6, 7]].numpy(), [1, 0, 1, 0, 0, 0, 0], atol=1e-3)
    # Columns that move differently (a translation's parallax) give a first-harmonic shift cue.
    moved = f0.clone()
    moved[..., 1:4, :] = f0[..., 0:3, :]  # columns 1-3 show what column 0-2 showed: shifted by one patch
    cue = yaw.cue(torch.cat([f0, moved], 1).reshape(1, 2, hp * wp, 16), (hp, wp), torch.ones(1, 2, 6, 16))[0, 1]
    assert float(cue[4:6].norm()) > 0.05
    # Depth: frame 1 nearer by 0.5 m towards longitude phi0 (d0 - d1 = 0.5 cos(lon - phi0)): the harmonic reads it.
    lon = (torch.arange(16) + 0.5) * 2 * np.pi / 16
    phi0 = 1.0
    d0 = torch.full((6, 16), 3.0)
    d1 = d0 - 0.5 * torch.cos(lon - phi0)
    tokens = torch.cat([f0, f0], 1).reshape(1, 2, hp * wp, 16)
    cue = yaw.cue(tokens, (hp, wp), torch.stack([d0, d1])[None])[0, 1]
    np.testing.assert_allclose(cue[8:].numpy(), [0.0, 0.5 * np.cos(phi0), 0.5 * np.sin(phi0)], atol=1e-3)
    # ... and turned back by the roll: frame 1 also turned by 2 patches (its depth columns rolled by 4 pixels).
    tokens = torch.cat([f0, f0.roll(2, dims=3)], 1).reshape(1, 2, hp * wp, 16)
    cue = yaw.cue(tokens, (hp, wp), torch.stack([d0, d1.roll(4, dims=-1)])[None])[0, 1]
    np.testing.assert_allclose(cue[8:].numpy(), [0.0, 0.5 * np.cos(phi0), 0.5 * np.sin(phi0)], atol=1e-3)
    # (B, S, out_dim) for any grid: the same weights run at another input size.
    assert yaw(torch.randn(2, 3, 4 * 16, 16), (4, 16), torch.ones(2, 3, 32, 64)).shape == (2, 3, 8)


def test_camera_head_with_the_correlation_cues_runs_saves_and_loads(tmp_path):
    torch.manual_seed(0)
    m = PanoVGGT(tiny_config(pose_correlation=8)).eval()
    x = frames(3)
    out = m(x)
    assert out["world_from_cam"].shape == (1, 3, 4, 4)
    m.save_pretrained(tmp_path / "w")
    m2 = PanoVGGT.from_pretrained(tmp_path / "w")
    assert m2.camera_head.correlation is not None and torch.equal(m2(x)["world_from_cam"], out["world_from_cam"])
    # A config written before the cue existed (no key) loads as VGGT's head.
    assert PanoVGGTConfig.from_json({k: v for k, v in tiny_config().to_json().items() if k != "pose_correlation"}
                                    ).pose_correlation == 0


def test_predict_refines_the_head_poses_on_its_own_depth_when_configured(tmp_path):
    from panoworld.models.pose_refine import refine_sequence

    m = tiny_model()
    x = frames(3)
    rgb = (x[0].permute(0, 2, 3, 1) * 255).round().to(torch.uint8).numpy()
    head = m.predict(rgb)
    np.testing.assert_array_equal(head["world_from_cam"], m(torch.from_numpy(rgb).permute(0, 3, 1, 2)[None].float()
                                                            .div(255.0))["world_from_cam"][0].numpy())
    m.cfg.pose_refine_iters = 3
    refined = m.predict(rgb)
    expect = refine_sequence(torch.from_numpy(head["world_from_cam"]), torch.from_numpy(head["depth"]), iterations=3)
    np.testing.assert_allclose(refined["world_from_cam"], expect.numpy(), atol=1e-9)
    assert not np.allclose(refined["world_from_cam"][1:], head["world_from_cam"][1:], atol=1e-4)
    np.testing.assert_array_equal(refined["depth"], head["depth"])
    # saved with the model; configs written before the option load with it off
    m.save_pretrained(tmp_path / "w")
    assert PanoVGGT.from_pretrained(tmp_path / "w").cfg.pose_refine_iters == 3
    assert PanoVGGTConfig.from_json({k: v for k, v in tiny_config().to_json().items() if k != "pose_refine_iters"}
                                    ).pose_refine_iters == 0
    with pytest.raises(ValueError, match="pose_refine_iters=-1"):
        tiny_config(pose_refine_iters=-1)
