"""Tests of the depth stage: depth files, hole filling, floor-based metric scale, seamless cube-view merging, models."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from panoworld.core.conventions import erp_dirs
from panoworld.depth import depth_map as dep
from panoworld.depth.depth_map import Rescale
from panoworld.framework.stage import StageInputError, execute_stage, load_stage
from panoworld.framework.stage_params import params_from_dict
from panoworld.geometry.cube_views import cube_views, merge_view_predictions, render_view
from panoworld.io.depth import DepthKind, read_depth, read_panorama
from panoworld.room.floor import estimate_floor
from tests.test_mesh import CAMERA_HEIGHT, BoxRoom


@pytest.fixture(scope="module")
def room():
    scene = BoxRoom()
    rgb, depth = scene.render(np.eye(4), 64, 128)
    return scene, rgb, depth


def run_depth_stage(tmp_path, panorama, depth=None, **params):
    spec = load_stage("depth")
    out = tmp_path / "out"
    manifest = execute_stage(spec, {"panorama": panorama, "depth": depth}, params_from_dict(spec.params_cls, params), out)
    return manifest, out


def write_png(path, rgb):
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


# ---------------------------------------------------------------- files


def test_read_depth_formats(room, tmp_path):
    _, _, depth = room
    np.save(tmp_path / "d.npy", depth)
    np.testing.assert_array_equal(read_depth(tmp_path / "d.npy"), depth)
    cv2.imwrite(str(tmp_path / "d.png"), np.rint(depth / 0.00025).astype(np.uint16))
    np.testing.assert_allclose(read_depth(tmp_path / "d.png", png_scale=0.00025), depth, atol=0.000126)
    cv2.imwrite(str(tmp_path / "d8.png"), np.rint(depth * 10).astype(np.uint8))
    with pytest.raises(StageInputError, match="8-bit PNG cannot hold depth"):
        read_depth(tmp_path / "d8.png")
    (tmp_path / "bad.npy").write_bytes(b"not numpy at all")
    with pytest.raises(StageInputError, match="bad.npy: cannot read"):
        read_depth(tmp_path / "bad.npy")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(StageInputError, match="bad.png: depth PNG is corrupt or not an image"):
        read_depth(tmp_path / "bad.png")
    depth.tofile(tmp_path / "d.raw")
    with pytest.raises(StageInputError, match="unsupported depth format"):
        read_depth(tmp_path / "d.raw")


def test_read_exr(room, tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR", reason="OpenCV here lacks OpenEXR; EXR needs the OpenEXR package")
    _, _, depth = room
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"Z": depth.astype(np.float32)}) as f:
        f.write(str(tmp_path / "d.exr"))
    np.testing.assert_array_equal(read_depth(tmp_path / "d.exr"), depth)
    (tmp_path / "bad.exr").write_bytes(b"v/1\x01 not an exr")
    with pytest.raises(StageInputError, match="bad.exr: cannot read"):
        read_depth(tmp_path / "bad.exr")


def test_panorama_checks(room, tmp_path):
    _, rgb, _ = room
    write_png(tmp_path / "wide.png", np.zeros((64, 100, 3), np.uint8))
    with pytest.raises(StageInputError, match=r"wide.png: panorama is 100x64 .* must be 2:1"):
        read_panorama(tmp_path / "wide.png")
    (tmp_path / "broken.jpg").write_bytes(b"\xff\xd8\xff garbage")
    with pytest.raises(StageInputError, match="broken.jpg: panorama is corrupt or not an image"):
        read_panorama(tmp_path / "broken.jpg")
    np.testing.assert_array_equal(read_panorama(write_png(tmp_path / "p.png", rgb)), rgb)


def test_conform_depth(room):
    scene, _, depth = room
    _, small = scene.render(np.eye(4), 128, 256)
    _, full = scene.render(np.eye(4), 256, 512)
    up, note = dep.conform_depth(small, 256, 512)
    assert note == "depth resized from 256x128 to 512x256 (bilinear on smooth surfaces, nearest at depth edges)"
    # The room's walls, floor and ceiling are smooth: bilinear lands far nearer the depth rendered at 256 rows than
    # nearest sampling, and neighbouring rows hardly repeat (a nearest 2x enlargement repeats every row: a terrace).
    nearest = cv2.resize(small, (512, 256), interpolation=cv2.INTER_NEAREST_EXACT)
    err, err_nearest = (np.median(np.abs(a - full) / full) for a in (up, nearest))
    assert err < 0.1 * err_nearest, (err, err_nearest)
    assert np.mean(up[1:] == up[:-1]) < 0.05 < 0.45 < np.mean(nearest[1:] == nearest[:-1])
    # A depth edge stays an edge and invalid depth never blends in: only the source values, 0 where none.
    step = np.where(np.arange(64) < 32, 1.0, 3.0)[None, :].repeat(32, 0).astype(np.float32)
    step[:4] = np.nan
    up, _ = dep.conform_depth(step, 64, 128)
    assert set(np.unique(up)) == {0.0, 1.0, 3.0} and (up[:8] == 0).all() and (up[8:] > 0).all()
    # Depth stored as float16 (ZInD's layout depth) keeps that precision, whose rounding step the plane tests read.
    up16, _ = dep.conform_depth(small.astype(np.float16).astype(np.float32), 256, 512)
    assert (up16.astype(np.float16).astype(np.float32) == up16).all() and np.mean(up16[1:] == up16[:-1]) < 0.3
    down, note = dep.conform_depth(full, 128, 256)
    assert note.endswith("(area-averaged on smooth surfaces, nearest at depth edges)")
    assert np.median(np.abs(down - small) / small) < 1e-3
    with pytest.raises(StageInputError, match="different aspect"):
        dep.conform_depth(depth[:, :100], 64, 128)


def test_fill_small_holes(room):
    _, _, depth = room
    valid = np.ones_like(depth, bool)
    valid[27:30, 40:43] = False  # 9 px on a wall
    valid[30:32, 0] = valid[30:32, -1] = False  # 4 px across the seam: one hole
    valid[40:60, 60:80] = False  # 400 px: a dropout
    filled, out_valid, n = dep.fill_small_holes(np.where(valid, depth, np.nan), valid, max_hole_px=16)
    assert n == 13
    assert out_valid[27:30, 40:43].all() and out_valid[30:32, [0, -1]].all() and not out_valid[40:60, 60:80].any()
    np.testing.assert_allclose(filled[27:30, 40:43], depth[27:30, 40:43], rtol=0.01)
    np.testing.assert_allclose(filled[30:32, [0, -1]], depth[30:32, [0, -1]], rtol=0.03)
    assert np.all(filled[40:60, 60:80] == 0) and np.array_equal(filled[valid], depth[valid])


def test_fill_scan_line_gaps():
    _, depth = BoxRoom().render(np.eye(4), 128, 256)
    valid = np.zeros_like(depth, bool)
    valid[:, 1::4] = True  # sparse LiDAR: every 4th column
    valid[:, 2::4] |= np.random.default_rng(0).random(valid[:, 2::4].shape) < 0.3
    valid[60:100, 20:80] = False  # a dropout wider than the gaps
    filled, out_valid, n = dep.fill_small_holes(np.where(valid, depth, 0), valid, max_hole_px=0, max_gap_px=3)
    assert out_valid[:, 0].all()  # the gap across the seam (columns 254, 255, 0) is interpolated too
    assert not out_valid[60:100, 24:76].any() and n == out_valid.sum() - valid.sum()
    # Maximum principle: invalid neighbours (the dropout's rim) are no boundary values, they must not pull depth.
    assert depth[valid].min() <= filled[out_valid].min() and filled[out_valid].max() <= depth[valid].max()
    rel = np.abs(filled[out_valid] - depth[out_valid]) / depth[out_valid]
    assert np.median(rel) < 2e-3 and np.percentile(rel, 90) < 0.01  # the tail: interpolation across depth edges


# ---------------------------------------------------------------- metric scale


def test_floor_recovers_camera_height():
    rgb, depth = BoxRoom().render(np.eye(4), 96, 192)
    fit = estimate_floor(depth, np.ones_like(depth, bool))
    assert fit.camera_height == pytest.approx(CAMERA_HEIGHT, rel=1e-3)
    assert fit.support > 0.3
    raw = depth * 3.7  # unknown units
    scaled, info = dep.metric_rescale(raw, np.ones_like(depth, bool), relative=False, rescale=Rescale.ALWAYS,
                                      camera_height=CAMERA_HEIGHT)
    assert info["camera_height_estimated_before"] == pytest.approx(3.7 * CAMERA_HEIGHT, rel=1e-3)
    assert info["camera_height_estimated_after"] == pytest.approx(CAMERA_HEIGHT, rel=1e-6)
    np.testing.assert_allclose(scaled, depth, rtol=2e-3)
    with pytest.raises(StageInputError, match="depth units look wrong: the floor is 5.365 units below"):
        dep.metric_rescale(raw, np.ones_like(depth, bool), relative=False, rescale=Rescale.RELATIVE_ONLY,
                           camera_height=CAMERA_HEIGHT)
    kept, info = dep.metric_rescale(raw, np.ones_like(depth, bool), relative=False, rescale=Rescale.NEVER,
                                    camera_height=CAMERA_HEIGHT)
    assert np.array_equal(kept, raw) and info["scale_factor"] == 1.0 and not info["rescaled"]
    kept, info = dep.metric_rescale(depth, np.ones_like(depth, bool), relative=False, rescale=Rescale.RELATIVE_ONLY,
                                    camera_height=1.6)
    assert np.array_equal(kept, depth) and info["camera_height_estimated_after"] == pytest.approx(CAMERA_HEIGHT, 1e-3)


@pytest.mark.parametrize("unit,per_metre", [("millimetres", 1000), ("centimetres", 100), (None, 450), (None, 3.7)])
def test_provided_depth_in_millimetres_or_centimetres_keeps_the_captures_own_camera_height(unit, per_metre):
    """rescale auto converts depth in millimetres or centimetres to metres (the floor stays at the capture's own 1.45 m,
    not camera_height's 1.6); other units (raw sensor values) still put the floor at camera_height."""
    _, depth = BoxRoom().render(np.eye(4), 96, 192)
    scaled, info = dep.metric_rescale(depth * per_metre, np.ones_like(depth, bool), relative=False,
                                      rescale=Rescale.AUTO, camera_height=1.6)
    assert info["rescaled"] and info.get("units") == unit
    if unit is None:
        assert info["camera_height_estimated_after"] == pytest.approx(1.6, rel=1e-6)
        assert "unknown units, floor put at camera_height" in info["scale_note"]
    else:
        assert info["scale_factor"] == 1 / per_metre
        assert info["camera_height_estimated_after"] == pytest.approx(CAMERA_HEIGHT, rel=1e-3)
        np.testing.assert_allclose(scaled, depth, rtol=1e-6)
        assert info["scale_note"].startswith(f"floor {CAMERA_HEIGHT * per_metre:.4g} units below the camera: depth "
                                             f"in {unit}, converted to metres (floor 1.450 m)")


def test_depth_stage_says_which_unit_it_converted_in_its_validated_manifest(tmp_path, room):
    _, rgb, depth = room
    np.save(tmp_path / "depth_mm.npy", depth * 1000)
    manifest, out = run_depth_stage(tmp_path, write_png(tmp_path / "panorama.png", rgb), tmp_path / "depth_mm.npy")
    info = manifest["info"]  # the manifest passed artifacts_schema/depth.schema.json when written
    assert info["units"] == "millimetres" and info["camera_height_estimated_after"] == pytest.approx(CAMERA_HEIGHT, 1e-3)
    assert any("depth in millimetres, converted to metres" in d for d in info["decisions"])


def test_floor_on_synth_scene(synth_scene, tmp_path):
    gt = json.loads((synth_scene / "gt" / "gt.json").read_text())
    manifest, _ = run_depth_stage(tmp_path, synth_scene / "panorama.png", synth_scene / "depth.npy")
    assert manifest["info"]["camera_height_estimated_before"] == pytest.approx(gt["camera_height_m"], rel=1e-3)


def test_no_floor_is_an_input_error(room):
    _, _, depth = room
    upper = np.zeros_like(depth, bool)
    upper[:30] = True
    assert estimate_floor(depth, upper) is None
    with pytest.raises(StageInputError, match="no horizontal floor"):
        dep.metric_rescale(depth, upper, relative=True, rescale=Rescale.RELATIVE_ONLY, camera_height=1.6)


# ---------------------------------------------------------------- cube views


def _view_truth(scene, views):
    """True perspective z-depth of each view (size, size)."""
    out = []
    for v in views:
        rays = v.rays()
        dist = scene.rc.cast(np.zeros((1, 3)), rays.reshape(-1, 3)).distance.reshape(rays.shape[:2])
        out.append(dist * (rays @ v.cam_from_view[:, 2]))
    return out


@pytest.mark.parametrize("kind", [DepthKind.RELATIVE, DepthKind.METRIC])
def test_merge_is_seamless(kind):
    scene = BoxRoom()
    _, gt = scene.render(np.eye(4), 96, 192)
    views = cube_views(110.0, 96)
    rng = np.random.default_rng(7)
    preds = []
    for z in _view_truth(scene, views):
        if kind == DepthKind.RELATIVE:
            preds.append(rng.uniform(0.3, 3.0) / z + rng.uniform(-0.3, 0.5))  # affine-invariant inverse depth
        else:
            preds.append(z * rng.uniform(0.8, 1.25))
    res = merge_view_predictions(preds, views, 96, 192, kind)
    assert res.valid.all()
    scale = np.median(gt / res.depth)
    rel = np.abs(res.depth * scale - gt) / gt
    assert np.median(rel) < 1e-3 and np.percentile(rel, 99) < 0.02  # the rest: bilinear resampling at depth edges
    # No seams: the error along view borders is no larger than inside the views.
    dirs = erp_dirs(96, 192, dtype=np.float64)
    n_cover = sum(np.isfinite(v.project(dirs)[0]) & (np.abs(v.project(dirs)[0] - 47.5) <= 47.5)
                  & (np.abs(v.project(dirs)[1] - 47.5) <= 47.5) for v in views)
    assert np.median(rel[n_cover > 1]) < 2e-3
    assert res.overlap_rel_rmse < 0.02
    if kind == DepthKind.METRIC:
        assert scale == pytest.approx(1.0, rel=0.25)


def test_render_view_matches_panorama():
    scene = BoxRoom()
    rgb, _ = scene.render(np.eye(4), 256, 512)
    view = cube_views(110.0, 64)[1]
    rays = view.rays()
    hit = scene.rc.cast(np.zeros((1, 3)), rays.reshape(-1, 3)).distance.reshape(64, 64)
    truth = scene.texture(rays * hit[..., None])
    assert np.abs(render_view(rgb, view).astype(float) - truth).mean() < 3.0


# ---------------------------------------------------------------- Depth Anything


def tiny_depth_anything(path):
    import torch
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    torch.manual_seed(0)
    backbone = Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, intermediate_size=64,
                            patch_size=14, image_size=56, out_features=["stage1", "stage2", "stage3", "stage4"],
                            reshape_hidden_states=False)
    config = DepthAnythingConfig(backbone_config=backbone, fusion_hidden_size=16, neck_hidden_sizes=[8, 16, 32, 32],
                                 reassemble_hidden_size=32, head_hidden_size=8, depth_estimation_type="relative")
    model = DepthAnythingForDepthEstimation(config)
    with torch.no_grad():  # a positive bias so the random head predicts positive inverse depth everywhere
        model.head.conv3.bias.fill_(1.0)
    model.save_pretrained(path)
    return path


def test_depth_anything_loads_from_local_weights(tmp_path, room):
    from panoworld.models.depth_anything import DepthAnything

    _, rgb, _ = room
    model = DepthAnything.from_pretrained(tiny_depth_anything(tmp_path / "w"), input_size=56)
    assert model.kind == DepthKind.RELATIVE
    view = render_view(rgb, cube_views(110.0, 70)[0])
    pred = model(view)
    assert pred.shape == (70, 70) and pred.dtype == np.float32 and np.isfinite(pred).all()
    with pytest.raises(StageInputError, match=r"--weights .*expected config.json \+ model.safetensors"):
        DepthAnything.from_pretrained(tmp_path / "missing")
    with pytest.raises(StageInputError, match="needs --weights DIR"):
        DepthAnything.from_pretrained(None)


def test_depth_stage_depth_anything(tmp_path, room, monkeypatch):
    _, rgb, _ = room
    weights = tiny_depth_anything(tmp_path / "w")
    pano = write_png(tmp_path / "panorama.png", rgb)
    manifest, out = run_depth_stage(tmp_path, pano, weights=str(weights), view_size=56, rescale="never")
    info = manifest["info"]
    assert info["backend"] == "depth-anything" and info["model_kind"] == "relative"
    depth = np.load(out / "depth.npy")
    valid = cv2.imread(str(out / "valid.png"), cv2.IMREAD_GRAYSCALE) == 255
    assert depth.shape == (64, 128) and valid.any() and np.all(depth[valid] > 0) and np.all(depth[~valid] == 0)
    # RGB only, no weights: one line naming both fixes.
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-hf-cache"))
    with pytest.raises(StageInputError, match=r"no depth model on disk; run `python runner.py weights fetch "
                                              r"depth-anything-v2-small` \(or put a metric depth") as e:
        run_depth_stage(tmp_path, pano)
    assert "\n" not in str(e.value)


def test_a_home_with_one_panorama_lacking_depth_is_refused_before_any_panorama_is_worked_on(tmp_path, room,
                                                                                           monkeypatch):
    """A home whose last panorama has no depth file (and no depth model on disk) fails at once, naming that panorama
    and where its depth goes, before the panoramas that have depth are cleaned (minutes on a real tour)."""
    import stages.depth as depth_stage

    _, rgb, depth = room
    home = tmp_path / "home"
    (home / "panoramas").mkdir(parents=True)
    (home / "depths").mkdir()
    for name in ("hall", "kitchen", "study"):
        write_png(home / "panoramas" / f"{name}.png", rgb)
    for name in ("hall", "kitchen"):
        np.save(home / "depths" / f"{name}.npy", depth)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-hf-cache"))
    worked = []
    real = depth_stage.depth_of_panorama
    monkeypatch.setattr(depth_stage, "depth_of_panorama", lambda inputs, *a, **k: worked.append(inputs) or real(
        inputs, *a, **k))
    spec = load_stage("depth")
    with pytest.raises(StageInputError, match=r"study.png: no depth file in the scene and no depth model on disk") as e:
        execute_stage(spec, {"panoramas": home / "panoramas", "depths": home / "depths"},
                      params_from_dict(spec.params_cls, {}), tmp_path / "out")
    assert worked == []
    assert f"give its metric depth as {home / 'depths' / 'study'}.npy|exr|png" in str(e.value)
    assert "\n" not in str(e.value) and not (tmp_path / "out").exists()
    with pytest.raises(StageInputError, match=r"study.png: backend provided needs its depth file; give its metric "
                                              r"depth as .*study.npy\|exr\|png"):
        execute_stage(spec, {"panoramas": home / "panoramas", "depths": home / "depths"},
                      params_from_dict(spec.params_cls, {"backend": "provided"}), tmp_path / "out")
    assert worked == [] and not (tmp_path / "out").exists()


# ---------------------------------------------------------------- provided depth through the stage


def test_depth_stage_provided_masks_bad_values(tmp_path, room):
    _, rgb, depth = room
    pano = write_png(tmp_path / "panorama.png", rgb)
    bad = (depth * 1000).astype(np.float32)  # millimetres in a PNG
    bad[5:7, 10:12] = 0  # small dropout: filled
    bad[40:60, 60:90] = 0  # sensor dropout: masked (and, by default, completed afterwards: see below)
    cv2.imwrite(str(tmp_path / "depth.png"), bad[::2, ::2].astype(np.uint16))  # half resolution
    manifest, out = run_depth_stage(tmp_path, pano, tmp_path / "depth.png", max_hole_px=8, complete_dropouts=False)
    info = manifest["info"]
    assert info["backend"] == "provided" and "resized from 64x32 to 128x64" in info["resized"]
    assert info["camera_height_estimated_before"] == pytest.approx(CAMERA_HEIGHT, rel=0.02)
    assert not info["rescaled"]
    depth_out = np.load(out / "depth.npy")
    valid = cv2.imread(str(out / "valid.png"), cv2.IMREAD_GRAYSCALE) == 255
    assert not valid[40:60, 60:90].any() and np.all(depth_out[40:60, 60:90] == 0)
    assert valid[4:8, 10:12].all()
    assert valid.mean() == pytest.approx(1 - 600 / depth.size, abs=0.01)
    np.testing.assert_array_equal(cv2.cvtColor(cv2.imread(str(out / "panorama.png")), cv2.COLOR_BGR2RGB), rgb)
    assert json.loads((out / "manifest.json").read_text())["schema"] == "depth"
    # with dropout completion (the default) the masked dropout is filled from its rim and recorded
    manifest, out = run_depth_stage(tmp_path / "completed", pano, tmp_path / "depth.png", max_hole_px=8)
    done = manifest["info"]["dropout_completion"]
    assert done["dropouts"] >= 1 and done["completed_fraction"] == pytest.approx(600 / depth.size, abs=0.01)
    filled = np.load(out / "depth.npy")[40:60, 60:90]
    assert np.all(filled > 0) and np.median(np.abs(filled - depth[40:60, 60:90]) / depth[40:60, 60:90]) < 0.1


def test_depth_stage_rescales_unknown_units(tmp_path, room):
    _, rgb, depth = room
    pano = write_png(tmp_path / "panorama.png", rgb)
    np.save(tmp_path / "depth.npy", depth * 450.0)  # raw sensor units
    manifest, out = run_depth_stage(tmp_path, pano, tmp_path / "depth.npy", rescale="always", camera_height=1.5)
    assert manifest["info"]["camera_height_estimated_before"] == pytest.approx(450 * CAMERA_HEIGHT, rel=0.01)
    np.testing.assert_allclose(np.load(out / "depth.npy"), depth * 1.5 / CAMERA_HEIGHT, rtol=0.01)


@pytest.mark.parametrize("what", ["nan", "aspect", "no_depth"])
def test_depth_stage_bad_input(tmp_path, room, what):
    _, rgb, depth = room
    pano = write_png(tmp_path / "panorama.png", rgb)
    if what == "nan":
        np.save(tmp_path / "depth.npy", np.full_like(depth, np.nan))
        match = "no valid depth"
    elif what == "aspect":
        np.save(tmp_path / "depth.npy", depth[:, :100])
        match = "different aspect"
    else:
        match = r"panorama.png: backend provided needs its depth file; put a metric depth.npy\|exr\|png next to the panorama"
    with pytest.raises(StageInputError, match=match):
        run_depth_stage(tmp_path, pano, tmp_path / "depth.npy" if what != "no_depth" else None,
                        backend="provided")
    assert not (tmp_path / "out").exists()
