"""Scene and dataset reports: built from a real ci-tiny pipeline run, opened in headless Chromium."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from panoworld.tools.report.cli import build_scene_report, main
from panoworld.tools.report.scene_data import ReportParams
from panoworld.tools.report.topdown import PlanView

SCENE_SECTIONS = ["stages", "depth", "plan", "frames", "poses", "gaussians", "eval", "roam"]


_BUILT: dict[str, object] = {}


@pytest.fixture(scope="session")
def pipeline_scene(synth_scene, tmp_path_factory):
    """A ci-tiny synthetic scene with every stage run, built once per session: test_viewer imports this fixture,
    which gives it a second session fixture definition, so the scene itself is cached in this module."""
    from panoworld.framework import pipeline as pl

    if "scene" not in _BUILT:
        scene = tmp_path_factory.mktemp("report") / "scene"
        shutil.copytree(synth_scene, scene)
        report = pl.run(scene, preset="ci-tiny", echo=False)
        assert report.ok, report.table()
        _BUILT["scene"] = scene
    return _BUILT["scene"]


@pytest.fixture(scope="module")
def scene_report(pipeline_scene):
    from panoworld.tools.eval.cli import EvalParams, evaluate
    from panoworld.tools.report.scene_data import ROAM_IMAGES

    # cheap stages (the page shows any saved eval) and the roam protocol at small sizes, with its pictures
    rep, errors = evaluate(pipeline_scene, EvalParams(roam_height=32, roam_pinhole=16),
                           stages=["trajectory", "poses", "roam"], roam_images=pipeline_scene / "artifacts" / ROAM_IMAGES)
    assert not errors
    (pipeline_scene / "artifacts" / "report").mkdir(parents=True, exist_ok=True)
    (pipeline_scene / "artifacts" / "report" / "eval.json").write_text(json.dumps(rep))
    timings: dict = {}
    out = build_scene_report(pipeline_scene, params=ReportParams(gs_views=2, preset="ci-tiny"), timings=timings)
    return out, timings


def _sections(text: str) -> dict[str, str]:
    return dict(re.findall(r'<section id="(\w+)" class="(\w+)"', text))


@pytest.mark.slow
def test_scene_report_has_every_section_and_is_self_contained(scene_report, pipeline_scene):
    out, _ = scene_report
    assert out == pipeline_scene / "artifacts" / "report" / "index.html"
    text = out.read_text()
    assert _sections(text) == {s: "present" for s in SCENE_SECTIONS}
    assert "could not draw" not in text
    assert "capture point: Gaussians, ERP" in text and "capture point: reference, pinhole" in text
    # nothing is fetched: every image is a data: URI and no script or style comes from elsewhere
    assert re.findall(r'<img[^>]+src="(?!data:image/)', text) == []
    assert not re.search(r'<(script|link)[^>]+(src|href)="(?!data:)', text)
    assert out.stat().st_size < 5e6
    # the stage table names every stage with its manifest's seconds, and links manifests and logs that exist
    for stage in ["depth", "mesh", "navmesh", "trajectory", "conditions", "video", "poses", "gaussians"]:
        m = json.loads((pipeline_scene / "artifacts" / stage / "manifest.json").read_text())
        assert f"<td>{stage}</td>" in text and f"{m['wall_s']:.2f}" in text
        assert f'href="../{stage}/manifest.json"' in text and f'href="../logs/{stage}.log"' in text
    # eval targets from the saved evaluation are shown with their verdicts
    assert "clear_fraction" in text and "rte" in text


@pytest.mark.slow
def test_scene_report_in_chromium(scene_report, tmp_path):
    from panoworld.tools.report.browser import browser_page, screenshot_array

    out, _ = scene_report
    with browser_page(1280, 900) as (page, console):
        page.goto(out.resolve().as_uri())
        page.wait_for_load_state("load")
        for sec in SCENE_SECTIONS:
            assert page.locator(f"section#{sec}").is_visible()
        img = screenshot_array(page, tmp_path / "report.png", full_page=True)
        label = page.locator('[data-text="frames:label"]')
        first_label = label.text_content()
        video = page.locator('img[data-slot="frames:video"]')
        first_src = video.get_attribute("src")
        slider = page.locator('input[data-slider="frames"]')
        data = json.loads(page.locator("#report-data").text_content())["frames"]["images"]["video"]
        assert data[0] == first_src and int(slider.get_attribute("max")) == len(data) - 1
        # a frame that looks different from frame 0 (a sector path keeps coming back to its start)
        i = next(k for k in range(len(data) - 1, 0, -1) if data[k] != data[0])
        slider.fill(str(i))  # dispatches input: the page swaps every frame column
        assert label.text_content() != first_label
        assert video.get_attribute("src") == data[i]
        assert console.errors == []
    assert img.shape[0] > 2000  # the whole page, every section
    assert img.std() > 30  # not blank
    # the top-down plan really shows the mesh from above (not a flat background)
    packed = (img[..., 0].astype(np.int32) << 16) | (img[..., 1].astype(np.int32) << 8) | img[..., 2]
    assert len(np.unique(packed)) > 2000


def test_plan_view_puts_forward_up_and_right_right():
    v = PlanView(np.array([[-1.0, -1.0], [1.0, 1.0]]), margin_m=0.0, max_px=200)
    c, fwd, right = v.px(np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]]))
    assert fwd[1] < c[1] and abs(fwd[0] - c[0]) < 1e-9  # +Z (the panorama's centre) is up the page
    assert right[0] > c[0] and abs(right[1] - c[1]) < 1e-9  # +X is to the right
    np.testing.assert_allclose(c, [100, 100])


def test_partial_scene_shows_missing_stages(synth_scene, tmp_path):
    from panoworld.framework import pipeline as pl

    scene = tmp_path / "scene"
    shutil.copytree(synth_scene, scene, ignore=shutil.ignore_patterns("artifacts"))
    assert pl.run(scene, preset="ci-tiny", until="depth", echo=False).ok
    out = build_scene_report(scene, tmp_path / "r.html")
    text = out.read_text()
    sections = _sections(text)
    assert sections["depth"] == "present" and sections["stages"] == "present"
    assert all(sections[s] == "missing" for s in ["plan", "frames", "poses", "gaussians", "eval", "roam"])
    assert "could not draw" not in text and "runner.py report SCENE --eval" in text
    assert text.count('<span class="na">missing</span>') == len(pl.Pipeline.load().order) - 1  # every stage but depth


@pytest.mark.slow
def test_dataset_report(synth_dataset, tmp_path):
    from panoworld.tools.precompute.run import main as precompute_main
    from panoworld.tools.report.browser import browser_page

    cond = tmp_path / "cond"
    assert precompute_main([str(synth_dataset), "--out", str(cond), "--clips-per-scene", "2", "--frames", "4",
                            "--min-frames", "2", "--height", "32", "--strides", "1,2", "--workers", "1"]) == 0
    assert main([str(cond), "--clips", "3"]) == 0
    out = cond / "report.html"
    text = out.read_text()
    assert _sections(text) == {"summary": "present", "histograms": "present", "clips": "present"}
    rows = [json.loads(x) for x in (cond / "index.jsonl").read_text().splitlines()]
    assert f"<td>clips</td><td>{len(rows)}</td>" in text
    assert text.count("<figcaption>target</figcaption>") == 3
    with browser_page(1200, 800) as (page, console):
        page.goto(out.resolve().as_uri())
        assert page.locator("section#histograms svg").count() == 4
        assert console.errors == []


def test_cli_rejects_what_is_not_a_scene(tmp_path, capsys):
    assert main([str(tmp_path / "nope")]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert main([str(tmp_path)]) == 2
    assert "neither a scene" in capsys.readouterr().err


def test_pinhole_cut_from_erp_looks_along_plus_z():
    from panoworld.tools.report.splats import pinhole_from_erp

    erp = np.zeros((64, 128, 3), np.uint8)
    erp[..., 0] = np.arange(128)[None, :] * 2  # red encodes the column (longitude)
    erp[..., 1] = np.arange(64)[:, None] * 4  # green encodes the row (latitude)
    view = pinhole_from_erp(erp, 32, 90.0)
    # centre of the view = the ERP centre (lon 0, lat 0): column 64, row 32
    assert abs(int(view[16, 16, 0]) - 128) <= 3 and abs(int(view[16, 16, 1]) - 128) <= 6
    # the left edge looks 45 degrees left (lon -pi/4 -> column 48); rows go down in both images
    assert abs(int(view[16, 0, 0]) - 97) <= 3 and view[0, 16, 1] < view[31, 16, 1]


def test_footprint_rings_outline_only_what_reaches_into_the_band():
    from panoworld.tools.report.topdown import footprint_rings

    wall = np.array([[1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [1.0, 2.0, 1.0], [1.0, 2.0, -1.0]])  # vertical, y 0..2
    floor = np.array([[-2.0, 2.5, -2.0], [2.0, 2.5, -2.0], [2.0, 2.5, 2.0], [-2.0, 2.5, 2.0]])  # below the band
    v = np.concatenate([wall, floor])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    view = PlanView(np.array([[-2.0, -2.0], [2.0, 2.0]]), margin_m=0.2, max_px=200)
    rings = footprint_rings(v, f, view, 0.5, 2.3)
    pts = np.concatenate(rings)
    assert len(rings) == 1 and np.abs(pts[:, 0] - 1.0).max() < 3 * view.cell  # the wall's line at x = 1 ...
    assert pts[:, 1].min() < -0.9 and pts[:, 1].max() > 0.9  # ... along its whole length; the floor is not drawn
    assert footprint_rings(v, f, view, 3.0, 4.0) == []


def test_missing_pictures_are_skipped_quietly(tmp_path, capfd):
    """A picture a stage did not write (no capture rig: no nadir before/after) is no picture, and no OpenCV warning
    in the user's terminal."""
    from panoworld.tools.report import encode

    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")
    assert encode.read_rgb(tmp_path / "nadir_before_after.jpg") is None
    assert encode.read_gray(tmp_path / "valid.png") is None
    assert capfd.readouterr().err == ""
    assert encode.read_rgb(tmp_path / "broken.jpg") is None
