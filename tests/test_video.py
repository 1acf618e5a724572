"""Video artifact: layout, load_video and MCAP round trips, upscaling seams, the stage CLI and its input errors."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import types
from pathlib import Path

import cv2
import imageio_ffmpeg
import numpy as np
import pytest

from panoworld.core.conventions import depth_to_mm, rotmat_from_quat_wxyz
from panoworld.framework.stage import StageSpec, execute_stage
from panoworld.io.png import decode_png, encode_png
from panoworld.io.video import VIDEO_FILE, load_video
from panoworld.io.video_mcap import (
    MCAP_FILE,
    TOPIC_COND_MASK,
    TOPIC_COND_RGB,
    TOPIC_DEPTH,
    TOPIC_POSE,
    TOPIC_RGB,
    TOPIC_TF,
    raw_image_array,
    read_mcap,
    world_from_cam_from_mcap,
)
from panoworld.io.video_writer import PREVIEW_FILE, write_video
from panoworld.render.metrics import psnr
from panoworld.video.upscale import lanczos_x2, nearest_x2
from stages import video as video_stage

REPO = Path(__file__).resolve().parent.parent


def random_video(t=4, h=16, w=32, seed=0):
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (t, h, w, 3), dtype=np.uint8)
    depth = rng.uniform(0.3, 8.0, (t, h, w)).astype(np.float32)
    depth[:, 0, :3] = 0.0  # unknown
    poses = np.tile(np.eye(4), (t, 1, 1))
    poses[:, :3, :3] = rotmat_from_quat_wxyz(rng.normal(size=(t, 4)))
    poses[:, :3, 3] = rng.normal(size=(t, 3))
    return frames, depth, poses


def decode_h264(messages, height: int, width: int) -> np.ndarray:
    """foxglove.CompressedVideo messages of one topic -> frames (N, H, W, 3) RGB, decoded by the ffmpeg program that
    imageio-ffmpeg ships (not the PyAV library that encoded them) from the messages' bytes laid end to end."""
    stream = b"".join(m.data for m in messages)
    out = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-f", "h264", "-i", "-",
                          "-f", "rawvideo", "-pix_fmt", "rgb24", "-"], input=stream, capture_output=True, check=True)
    return np.frombuffer(out.stdout, np.uint8).reshape(-1, height, width, 3)


def nal_types(access_unit: bytes) -> list[int]:
    """The NAL unit types of an Annex B access unit (5 IDR slice, 1 other slice, 7 SPS, 8 PPS, 6 SEI)."""
    starts = [i + 3 for i in range(len(access_unit) - 3) if access_unit[i:i + 3] == b"\x00\x00\x01"]
    return [access_unit[i] & 31 for i in starts]


def test_write_and_load_video_round_trip(tmp_path):
    frames, depth, poses = random_video()
    doc = write_video(tmp_path, frames, depth, poses, fps=12.0, meta={"backend": "test", "upscale": "none"})
    for name in (VIDEO_FILE, PREVIEW_FILE, MCAP_FILE, "frames/000000.png", "frames/000003.png", "depth/000003.png"):
        assert (tmp_path / name).is_file(), name
    on_disk = json.loads((tmp_path / VIDEO_FILE).read_text())
    assert on_disk == doc
    assert {k: on_disk[k] for k in ("height", "width", "num_frames", "fps", "has_depth", "depth_scale")} == {
        "height": 16, "width": 32, "num_frames": 4, "fps": 12.0, "has_depth": True, "depth_scale": 0.001}
    assert on_disk["frames"][2] == {"rgb": "frames/000002.png", "depth": "depth/000002.png"}
    v = load_video(tmp_path)
    np.testing.assert_array_equal(v.frames, frames)
    np.testing.assert_array_equal(v.poses, poses)
    assert v.depth.dtype == np.float32 and v.fps == 12.0
    assert np.abs(v.depth - depth).max() <= 0.0005 + 1e-6  # millimetre PNGs
    assert (v.depth[:, 0, :3] == 0).all()
    assert load_video(tmp_path, with_depth=False).depth is None


def test_video_without_depth(tmp_path):
    frames, _, poses = random_video(t=2)
    doc = write_video(tmp_path, frames, None, poses, fps=16.0, preview=False, mcap=False)
    assert doc["has_depth"] is False and doc["frames"][0]["depth"] is None
    assert not (tmp_path / "depth").exists() and not (tmp_path / PREVIEW_FILE).exists()
    assert load_video(tmp_path).depth is None


@pytest.mark.parametrize(("codec", "jpeg_quality"), [("jpeg", 0), ("jpeg", 80), ("h264", 80)])
def test_mcap_decodes_back_exactly(tmp_path, codec, jpeg_quality):
    from panoworld.io.video_writer import VideoWriter

    frames, depth, poses = random_video(t=3)
    frames = cv2.GaussianBlur(frames.reshape(-1, 32, 3), (5, 5), 2).reshape(frames.shape)  # photo-like: JPEG's domain
    writer = VideoWriter(tmp_path, height=16, width=32, fps=10.0, has_depth=True, preview=False,
                         mcap_codec=codec, mcap_jpeg_quality=jpeg_quality)
    cond_pngs = [encode_png(f[::2, ::2]) for f in frames]
    mask_pngs = [encode_png(((f[::2, ::2, 0] > 127) * 255).astype(np.uint8)) for f in frames]
    for k in range(3):
        writer.add(frames[k], depth[k], poses[k], cond_rgb_png=cond_pngs[k], cond_mask_png=mask_pngs[k])
    writer.close()
    msgs = read_mcap(tmp_path / MCAP_FILE)
    assert {t: len(m) for t, m in msgs.items()} == {t: 3 for t in (TOPIC_RGB, TOPIC_DEPTH, TOPIC_COND_RGB,
                                                                     TOPIC_COND_MASK, TOPIC_TF, TOPIC_POSE)}
    if codec == "h264":  # one access unit per message, the first an IDR, each IDR with its SPS and PPS (Foxglove's rules)
        assert [m.format for m in msgs[TOPIC_RGB] + msgs[TOPIC_COND_RGB]] == ["h264"] * 6
        types = [nal_types(m.data) for m in msgs[TOPIC_RGB] + msgs[TOPIC_COND_RGB]]
        assert 5 in types[0] and 5 in types[3] and all({7, 8} <= set(t) for t in types if 5 in t)
        video, cond_video = decode_h264(msgs[TOPIC_RGB], 16, 32), decode_h264(msgs[TOPIC_COND_RGB], 8, 16)
        assert len(video) == len(cond_video) == 3
    for k in range(3):
        rgb, cond = msgs[TOPIC_RGB][k], msgs[TOPIC_COND_RGB][k]
        assert rgb.frame_id == "camera" and msgs[TOPIC_COND_MASK][k].data == mask_pngs[k]
        if codec == "h264":  # for viewing: the decoded streams close to the frames and conditions
            assert psnr(video[k], frames[k]) > 25 and psnr(cond_video[k], decode_png(cond_pngs[k])) > 25
            assert psnr(video[k], frames[k]) > psnr(video[k], frames[(k + 1) % 3]) + 5  # the frames in order
        elif jpeg_quality == 0:  # lossless: the PNGs themselves
            assert rgb.format == cond.format == "png" and cond.data == cond_pngs[k]
            np.testing.assert_array_equal(decode_png(rgb.data), frames[k])
        else:  # for viewing: JPEG close to the frames and conditions
            assert rgb.format == cond.format == "jpeg"
            jpg = cv2.imdecode(np.frombuffer(rgb.data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
            assert psnr(jpg, frames[k]) > 25  # an unrelated image: about 12 dB
            c = cv2.imdecode(np.frombuffer(cond.data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
            assert psnr(c, decode_png(cond_pngs[k])) > 25
        d = msgs[TOPIC_DEPTH][k]  # one pixel in 4 x 4
        mm = depth_to_mm(depth[k])[::4, ::4].astype(int)  # to the nearest 2 cm, unknown kept
        assert (d.encoding, d.width, d.height) == ("16UC1", 8, 4) and (raw_image_array(d) % 20 == 0).all()
        np.testing.assert_array_equal(raw_image_array(d) == 0, mm == 0)
        assert np.abs(raw_image_array(d).astype(int) - mm).max() <= 10
        tf = msgs[TOPIC_TF][k]
        assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "camera")
        np.testing.assert_allclose(world_from_cam_from_mcap(tf), poses[k], atol=1e-12)
        np.testing.assert_allclose(world_from_cam_from_mcap(msgs[TOPIC_POSE][k]), poses[k], atol=1e-12)
        assert rgb.timestamp.ToNanoseconds() == round(k * 1e9 / 10.0)
    # The ROS world is z up: our up (-Y) must come out as +z.
    from panoworld.core.conventions import ros_world_from_cam

    np.testing.assert_allclose(ros_world_from_cam(np.eye(4))[:3, :3] @ np.array([0.0, -1.0, 0.0]), [0, 0, 1])


@pytest.mark.parametrize(("codec", "jpeg_quality"), [("h264", 80), ("jpeg", 80)])
def test_mcap_of_a_decoded_condition_is_that_of_its_bytes(tmp_path, codec, jpeg_quality):
    from panoworld.io.video_writer import VideoWriter

    frames, depth, poses = random_video(t=3)
    frames = cv2.GaussianBlur(frames.reshape(-1, 32, 3), (5, 5), 2).reshape(frames.shape)
    cond_pngs = [encode_png(f[::2, ::2]) for f in frames]
    data = {}
    for how in ("bytes", "decoded"):
        writer = VideoWriter(tmp_path / how, height=16, width=32, fps=10.0, has_depth=True, preview=False,
                             mcap_codec=codec, mcap_jpeg_quality=jpeg_quality)
        for k in range(3):
            if how == "bytes":
                writer.add(frames[k], depth[k], poses[k], cond_rgb_png=cond_pngs[k])
            else:
                writer.add(frames[k], depth[k], poses[k], cond_rgb=decode_png(cond_pngs[k]))
        writer.close()
        data[how] = [m.data for m in read_mcap(tmp_path / how / MCAP_FILE)[TOPIC_COND_RGB]]
    assert len(data["bytes"]) == 3 and data["decoded"] == data["bytes"]


def test_preview_is_the_mcaps_h264_frame_stream(tmp_path):
    frames, depth, poses = random_video(t=40, h=32, w=64)  # more frames than a keyframe interval (2 s at 8 fps)
    frames = cv2.GaussianBlur(frames.reshape(-1, 64, 3), (5, 5), 2).reshape(frames.shape)
    write_video(tmp_path, frames, depth, poses, fps=8.0)
    reader = imageio_ffmpeg.read_frames(str(tmp_path / PREVIEW_FILE))
    meta = next(reader)
    assert meta["codec"] == "h264" and meta["size"] == (64, 32) and meta["fps"] == 8.0
    assert meta["pix_fmt"].startswith("yuv420p")
    preview = np.stack([np.frombuffer(f, np.uint8).reshape(32, 64, 3) for f in reader])
    mcap = decode_h264(read_mcap(tmp_path / MCAP_FILE)[TOPIC_RGB], 32, 64)
    assert len(preview) == 40 and np.array_equal(preview, mcap)  # the same access units, not a second encode
    assert psnr(np.concatenate(preview), np.concatenate(frames)) > 25


def test_jpeg_frames_round_trip_and_go_into_the_mcap_as_they_are(tmp_path):
    from panoworld.io.rgb_image import decode_rgb, encode_rgb

    frames, depth, poses = random_video(t=2, h=32, w=64)
    frames = cv2.GaussianBlur(frames.reshape(-1, 64, 3), (5, 5), 2).reshape(frames.shape)
    write_video(tmp_path, frames, depth, poses, fps=5.0, preview=False, frame_format="jpeg", frame_quality=95,
                mcap_codec="jpeg", mcap_jpeg_quality=0)
    v = load_video(tmp_path)
    assert [e["rgb"] for e in v.meta["frames"]] == ["frames/000000.jpg", "frames/000001.jpg"]
    assert v.frames.shape == frames.shape and psnr(np.concatenate(v.frames), np.concatenate(frames)) > 30
    assert np.abs(v.depth - depth).max() <= 5.1e-4  # depth stays a PNG of millimetres
    data = (tmp_path / "frames" / "000001.jpg").read_bytes()
    assert np.array_equal(decode_rgb(data), v.frames[1]) and data == encode_rgb(frames[1], "jpeg", quality=95)
    msgs = read_mcap(tmp_path / MCAP_FILE)  # decoded with the foxglove.CompressedImage schema
    assert msgs[TOPIC_RGB][1].format == "jpeg" and msgs[TOPIC_RGB][1].data == data


def test_preview_is_h264_yuv420p_with_even_size(tmp_path):
    frames, _, poses = random_video(t=3, h=18, w=36)
    write_video(tmp_path, frames, None, poses, fps=8.0, mcap=False, preview_max_width=30)
    meta = next(imageio_ffmpeg.read_frames(str(tmp_path / PREVIEW_FILE)))
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert all(s % 2 == 0 for s in meta["size"]) and meta["size"][0] <= 30


def test_lanczos_upscale_is_seam_equivariant():
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (16, 32, 3), dtype=np.uint8)
    up = lanczos_x2(img)
    assert up.shape == (32, 64, 3)
    # Upscaling commutes with a rotation in longitude exactly: the seam is treated like any other column.
    np.testing.assert_array_equal(lanczos_x2(np.roll(img, 5, axis=1)), np.roll(up, 10, axis=1))
    d = rng.uniform(1, 2, (4, 8)).astype(np.float32)
    np.testing.assert_array_equal(nearest_x2(d)[::2, ::2], d)
    np.testing.assert_array_equal(nearest_x2(d)[1::2, 1::2], d)


# ---------------------------------------------------------------- the stage


@dataclasses.dataclass(kw_only=True)
class _NoParams:
    pass


def _artifact(kind: str, out: Path, write) -> Path:
    """A real upstream artifact (manifest, digests) whose files are written by `write(out_dir) -> info`."""
    spec = StageSpec(f"stub-{kind}", "0", kind, {}, _NoParams, types.SimpleNamespace(run=lambda i, p, o: write(o), __name__=__name__, __file__=__file__))
    execute_stage(spec, {}, _NoParams(), out)
    return out


@pytest.fixture(scope="module")
def upstream(tmp_path_factory):
    """mesh, trajectory and conditions artifacts of the box scene of test_inpaint (64x128, 5 poses)."""
    from panoworld.conditions.warp import render_conditions, write_conditions
    from panoworld.geometry.erp_mesh import erp_mesh_from_depth, save_erp_mesh
    from panoworld.io.trajectory import write_trajectory
    from tests.test_inpaint import BoxScene, sideways_poses

    root = tmp_path_factory.mktemp("upstream")
    rgb0, d0 = BoxScene().render(np.eye(4), 64, 128)
    mesh = erp_mesh_from_depth(d0, rgb0)
    poses = sideways_poses(5, 0.6)

    def write_mesh(o):
        save_erp_mesh(mesh, o / "mesh.ply")
        return {"num_vertices": len(mesh.vertices), "num_faces": len(mesh.faces),
                "num_faces_stretched": int((~mesh.face_valid).sum()), "stretched_kept_as_occluders": True,
                "grid": [64, 128]}

    def write_traj(o):
        write_trajectory(o, poses, np.full(len(poses), 1.0), fps=10.0)
        return {"source": "planned", "kind": "sector", "frames": len(poses), "step_m": 0.15, "min_clearance_m": 1.0,
                "agent_radius_m": 0.2, "invalid_poses": []}

    def write_cond(o):
        info = write_conditions(o, render_conditions(mesh, poses, 64, 128, backend="raycast"), poses)
        return {**info, "backend": "raycast"}

    return {"mesh": _artifact("mesh", root / "mesh", write_mesh),
            "trajectory": _artifact("trajectory", root / "trajectory", write_traj),
            "conditions": _artifact("conditions", root / "conditions", write_cond), "poses": poses}


def _cli(upstream, out: Path, *flags: str) -> list[str]:
    return ["--conditions", str(upstream["conditions"]), "--trajectory", str(upstream["trajectory"]),
            "--mesh", str(upstream["mesh"]), "--out", str(out), *flags]


def test_stage_warp_inpaint_end_to_end(upstream, tmp_path):
    out = tmp_path / "video"
    assert video_stage.main(_cli(upstream, out)) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    info = manifest["info"]
    assert info["backend"] == "warp-inpaint" and info["upscale"] == "none" and info["fps"] == 10.0
    assert info["layer_faces"] > 0 and info["filled_3d_fraction"] > 0.9
    assert min(info["fill_s"], info["write_s"]) > 0 and info["upscaled_height"] is None
    v = load_video(out)
    assert v.frames.shape == (5, 64, 128, 3) and v.depth.shape == (5, 64, 128)
    assert not (out / "upscaled").exists()
    np.testing.assert_allclose(v.poses, upstream["poses"])
    assert (v.depth > 0).mean() > 0.99  # conditions depth + layer depth
    msgs = read_mcap(out / MCAP_FILE)
    assert len(msgs[TOPIC_COND_RGB]) == 5 and msgs[TOPIC_COND_RGB][0].format == "h264"
    assert decode_h264(msgs[TOPIC_COND_RGB], 64, 128).shape == (5, 64, 128, 3)
    assert len(msgs[TOPIC_RGB]) == 5 and len(msgs[TOPIC_DEPTH]) == 5
    # frames/ are JPEG (quality 93) by default; the MCAP holds each frame once, in an H.264 stream.
    frame2 = (out / "frames" / "000002.jpg").read_bytes()
    video = decode_h264(msgs[TOPIC_RGB], 64, 128)
    assert psnr(video[2], cv2.imdecode(np.frombuffer(frame2, np.uint8), 1)[..., ::-1]) > 20  # 64x128: 4:2:0 chroma
    # Lossless PNG frames on request: the same fill within JPEG's error (4:2:0 chroma at 64x128); the MCAP holds JPEG.
    png_out = tmp_path / "video_png"
    assert video_stage.main(_cli(upstream, png_out, "--frame-format", "png", "--preview", "false")) == 0
    exact = load_video(png_out)
    assert psnr(np.concatenate(v.frames), np.concatenate(exact.frames)) > 25 and np.array_equal(v.depth, exact.depth)
    assert psnr(decode_h264(read_mcap(png_out / MCAP_FILE)[TOPIC_RGB], 64, 128)[2], exact.frames[2]) > 20


def test_warp_inpaint_frames_filled_on_threads_equal_one_at_a_time(upstream, tmp_path, monkeypatch):
    from panoworld.video.backends import warp_inpaint

    outs = {}
    for ahead in (1, 3):
        monkeypatch.setattr(warp_inpaint, "FILL_AHEAD", ahead)
        outs[ahead] = tmp_path / f"video{ahead}"
        assert video_stage.main(_cli(upstream, outs[ahead], "--preview", "false", "--mcap", "false")) == 0
    files = sorted(p.relative_to(outs[1]) for p in outs[1].rglob("*") if p.parent.name in ("frames", "depth"))
    assert len(files) == 10  # each frame's colour and depth, in order
    for f in files:
        assert (outs[1] / f).read_bytes() == (outs[3] / f).read_bytes(), f


def test_stage_lanczos_upscale_is_an_output_not_an_input_to_later_stages(upstream, tmp_path):
    out = tmp_path / "video"
    assert video_stage.main(_cli(upstream, out, "--upscale", "lanczos", "--preview", "false", "--frame-format", "png")) == 0
    v = load_video(out)
    assert v.frames.shape == (5, 64, 128, 3) and v.meta["upscaled_height"] == 128
    up = [decode_png((out / e["upscaled"]).read_bytes()) for e in v.meta["frames"]]
    np.testing.assert_array_equal(up[3], lanczos_x2(v.frames[3]))
    assert len(read_mcap(out / MCAP_FILE)[TOPIC_RGB]) == 5  # not stored twice


def test_stage_frame_inpaint_without_upscale(upstream, tmp_path):
    out = tmp_path / "video"
    assert video_stage.main(_cli(upstream, out, "--backend", "frame-inpaint", "--upscale", "none",
                                 "--mcap", "false", "--preview", "false")) == 0
    v = load_video(out)
    assert v.frames.shape == (5, 64, 128, 3) and v.meta["backend"] == "frame-inpaint"
    assert not (out / MCAP_FILE).exists()


def test_stage_input_errors(upstream, tmp_path, capsys):
    out = tmp_path / "video"
    assert video_stage.main(_cli(upstream, out, "--backend", "wan-shortcut")) == 2
    assert "--wan-weights DIR" in capsys.readouterr().err
    assert video_stage.main(_cli(upstream, out, "--upscale", "realesrgan")) == 2
    assert "--upscale-weights FILE" in capsys.readouterr().err
    # Conditions rendered for another trajectory.
    from panoworld.io.trajectory import write_trajectory

    other = _artifact("trajectory", tmp_path / "traj2", lambda o: (
        write_trajectory(o, upstream["poses"][:3], np.ones(3), fps=10.0),
        {"source": "planned", "kind": "sector", "frames": 3, "step_m": 0.1, "min_clearance_m": 1.0,
         "agent_radius_m": 0.2, "invalid_poses": []})[1])
    argv = _cli(upstream, out)
    argv[argv.index("--trajectory") + 1] = str(other)
    assert video_stage.main(argv) == 2
    assert "rerun the conditions stage" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_stage_wan_shortcut_names_missing_weight_files(upstream, tmp_path, capsys):
    assert video_stage.main(_cli(upstream, tmp_path / "v", "--backend", "wan-shortcut", "--weights", str(tmp_path))) == 2
    err = capsys.readouterr().err
    assert "--weights" in err and "transformer/config.json" in err


def test_cli_help():
    out = subprocess.run([sys.executable, "-m", "stages.video", "--help"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    for flag in ("--backend", "--upscale", "--upscale-weights", "--wan-weights", "--wan-lora", "--wan-extra-weights",
                 "--wan-steps", "--warp-max-band-deg"):
        assert flag in out.stdout


def test_stage_realesrgan_upscale_with_local_weights(upstream, tmp_path):
    """--upscale realesrgan loads an official-layout RRDBNet state dict (a tiny random one here) and doubles the size."""
    import torch

    from panoworld.models.rrdbnet import RRDBNet

    torch.manual_seed(0)
    weights = tmp_path / "RealESRGAN_x2plus.pth"
    torch.save({"params_ema": RRDBNet(scale=2, num_feat=8, num_block=1, num_grow_ch=4).state_dict()}, weights)
    out = tmp_path / "video"
    assert video_stage.main(_cli(upstream, out, "--upscale", "realesrgan", "--upscale-weights", str(weights),
                                 "--device", "cpu", "--preview", "false", "--mcap", "false")) == 0
    v = load_video(out)
    assert v.frames.shape == (5, 64, 128, 3) and v.depth.shape == (5, 64, 128)
    assert v.meta["upscale"] == "realesrgan"
    assert decode_png((out / v.meta["frames"][0]["upscaled"]).read_bytes()).shape == (128, 256, 3)


@pytest.mark.slow
def test_stage_wan_shortcut_on_tiny_local_weights(upstream, tmp_path):
    """The real loading path of the generator (tiny random Wan2.2-like weights saved to disk): NFE in the manifest,
    no depth, one frame per pose."""
    pytest.importorskip("diffusers")
    pytest.importorskip("peft")
    import torch

    from panoworld.models import wan_layers as wl
    from panoworld.models import wan_training as wt
    from panoworld.models.wan_shortcut import save_prompt_embeds
    from tests.test_wan_shortcut import TEXT_DIM, Z, embeds, tiny_transformer, tiny_vae

    torch.set_num_threads(1)
    root = tmp_path / "wan"
    tiny_transformer(seed=5).save_pretrained(root / "transformer")
    tiny_vae().save_pretrained(root / "vae")
    save_prompt_embeds(tmp_path / "prompt.safetensors", embeds(), torch.zeros(1, 7, TEXT_DIM))
    from diffusers import WanTransformer3DModel

    trained = WanTransformer3DModel.from_pretrained(root, subfolder="transformer", local_files_only=True)
    wt.prepare_for_training(trained, Z + 4, rank=4, alpha=8)
    wl.save_trained_weights(trained, tmp_path / "lora.safetensors", tmp_path / "extra.safetensors")
    out = tmp_path / "video"
    assert video_stage.main(_cli(
        upstream, out, "--backend", "wan-shortcut", "--weights", str(root), "--lora", str(tmp_path / "lora.safetensors"),
        "--extra-weights", str(tmp_path / "extra.safetensors"), "--prompt-embeds", str(tmp_path / "prompt.safetensors"),
        "--device", "cpu", "--dtype", "float32", "--vae-tiling", "false", "--upscale", "none", "--preview", "false",
    )) == 0
    info = json.loads((out / "manifest.json").read_text())["info"]
    assert info["nfe"] == 4 and info["sampler"] == "shortcut" and info["has_depth"] is False
    v = load_video(out)
    assert v.frames.shape == (5, 64, 128, 3) and v.depth is None
    assert TOPIC_DEPTH not in read_mcap(out / MCAP_FILE)
