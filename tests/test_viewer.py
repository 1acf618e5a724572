"""The viser viewer: loads a real ci-tiny pipeline run, renders the splats in headless Chromium (software WebGL)."""

from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest

from panoworld.tools.viewer.app import SceneViewer, ViewerParams, main, splat_arrays
from tests.test_report import pipeline_scene  # noqa: F401 - the shared session fixture

# three.js logs this for viser's own splat geometry (a 2-component quad "position" attribute, viser 1.x
# client/src/Splatting/GaussianSplatsHelpers.ts) when it computes a bounding sphere; nothing of ours.
KNOWN_VISER_ERRORS = ("computeBoundingSphere(): Computed radius is NaN",)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def viewer(pipeline_scene):  # noqa: F811
    v = SceneViewer(pipeline_scene, ViewerParams(port=_free_port()))
    yield v
    v.stop()


@pytest.mark.slow
def test_viewer_loads_every_layer_and_binds_localhost(viewer, pipeline_scene):  # noqa: F811
    assert viewer.server.get_host() == "127.0.0.1"
    assert set(viewer.loaded) == {"mesh", "navmesh", "trajectory", "points", "splats", "captures"}
    assert not any(v.startswith(("unreadable", "missing")) for k, v in viewer.loaded.items() if k != "points"), viewer.loaded
    info = json.loads((pipeline_scene / "artifacts" / "gaussians" / "manifest.json").read_text())["info"]
    assert viewer.loaded["splats"] == f"{info['num_gaussians']} Gaussians"
    # the frame slider moves the highlighted frustum onto that pose
    poses = np.asarray(json.loads((pipeline_scene / "artifacts" / "poses" / "poses.json").read_text())["poses"])
    k = len(poses) // 2 + 1
    viewer.select_frame(k)
    np.testing.assert_allclose(viewer.handles["current"].position, poses[k][:3, 3], atol=1e-6)


def test_splat_covariances_match_scales_and_rotations():
    from panoworld.io.gaussian_set import Gaussians

    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g = Gaussians(rng.normal(size=(5, 3)).astype(np.float32), rng.uniform(0.01, 0.2, (5, 3)).astype(np.float32),
                  q.astype(np.float32), rng.uniform(0.1, 1, 5).astype(np.float32), rng.normal(size=(5, 3)).astype(np.float32))
    a = splat_arrays(g, 3)
    assert a["centers"].shape == (3, 3) and a["opacities"].shape == (3, 1)
    kept = np.sort(np.argsort(-g.opacities)[:3])
    for n, i in enumerate(kept):
        ev = np.sort(np.linalg.eigvalsh(a["covariances"][n].astype(np.float64)))
        np.testing.assert_allclose(ev, np.sort(g.scales[i].astype(np.float64) ** 2), rtol=1e-4, atol=1e-9)


@pytest.mark.slow
def test_viewer_canvas_shows_the_splats_in_chromium(viewer, tmp_path):
    from panoworld.tools.report.browser import browser_page, screenshot_array

    with browser_page(800, 450) as (page, console):  # small: SwiftShader renders every pixel on the CPU
        page.goto(viewer.url)
        canvas = page.wait_for_selector("canvas", timeout=60_000)
        box = canvas.bounding_box()
        for name in ("mesh", "navmesh", "planned", "frustums", "current", "points"):
            if name in viewer.handles:
                viewer.handles[name].visible = False
        # left of viser's GUI panel, below its notifications, above its axes gizmo
        clip = {"x": box["x"] + 0.05 * box["width"], "y": box["y"] + 0.4 * box["height"],
                "width": 0.4 * box["width"], "height": 0.45 * box["height"]}

        def settled(visible: bool) -> np.ndarray:
            viewer.handles["splats"].visible = visible
            prev, img = None, None
            shots = 0
            for _ in range(40):  # software WebGL: wait until two screenshots agree
                shots += 1
                time.sleep(0.5)
                img = screenshot_array(page, clip=clip).astype(np.int16)
                if prev is not None and np.abs(img - prev).mean() < 0.5:
                    break
                prev = img
            print(f"splats {'shown' if visible else 'hidden'}: settled after {shots} screenshots")
            return img

        with_splats = settled(True)
        empty = settled(False)
        # "look from this frame" puts the browser's camera on the selected pose
        k = len(viewer._poses) // 2 + 1
        viewer.handles["frame_slider"].value = k
        time.sleep(0.5)
        page.get_by_role("button", name="look from this frame").dispatch_event("click")
        (client,) = viewer.server.get_clients().values()
        for _ in range(40):
            time.sleep(0.25)
            if np.allclose(client.camera.position, viewer._poses[k][:3, 3], atol=1e-4):
                break
        np.testing.assert_allclose(client.camera.position, viewer._poses[k][:3, 3], atol=1e-4)
        errors = [e for e in console.errors if not any(k in e for k in KNOWN_VISER_ERRORS)]
        assert errors == []
    assert empty.std() < 3  # the empty scene is a plain background
    changed = (np.abs(with_splats - empty).max(-1) > 30).mean()
    assert changed > 0.5, changed  # the splats cover most of the view from inside the room
    assert with_splats.std() > 10  # and they are textured, not one flat colour (the wall texture at ci-tiny: ~14)


def test_viewer_skips_missing_stages_and_shows_colmap_points(tmp_path):
    import pycolmap

    sparse = tmp_path / "artifacts" / "poses" / "sparse" / "0"
    sparse.mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    for i in range(3):
        rec.add_point3D(np.array([i, 0.5, 2.0]), pycolmap.Track(), np.array([255, 40 * i, 0], np.uint8))
    rec.write(str(sparse))
    v = SceneViewer(tmp_path, ViewerParams(port=_free_port()))
    try:
        assert v.loaded == {"mesh": "missing (depth and mesh not run)", "navmesh": "missing", "trajectory": "missing",
                            "captures": "missing", "points": "3 points", "splats": "missing"}
        assert set(v.handles) == {"points"}
    finally:
        v.stop()


def test_view_cli_rejects_a_directory_without_artifacts(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "no artifacts/" in capsys.readouterr().err


def test_non_loopback_host_and_taken_port_are_announced(tmp_path):
    from panoworld.tools.viewer.app import is_loopback, serve_warnings

    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1") and is_loopback("127.5.0.1")
    assert not any(is_loopback(h) for h in ("0.0.0.0", "::", "192.168.1.10", "my-host.lan"))
    assert serve_warnings("127.0.0.1", 8080, 8080) == []
    (tmp_path / "artifacts").mkdir()
    with socket.socket() as taken:  # a port someone else holds: the viewer moves, and says so with the real URL
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        v = SceneViewer(tmp_path, ViewerParams(port=port))
        try:
            served = v.server.get_port()
            assert served != port and v.url == f"http://127.0.0.1:{served}"
            with socket.create_connection(("127.0.0.1", served), timeout=5):
                pass  # the printed URL is the one actually served
            lines = serve_warnings("0.0.0.0", port, served)
            assert "WARNING: --host 0.0.0.0 is not a loopback address" in lines[0]
            assert f"port {port} is taken; serving on port {served}" in lines[1]
        finally:
            v.stop()


def test_viewer_shows_a_homes_capture_points(tmp_path):
    reg = tmp_path / "artifacts" / "register"
    reg.mkdir(parents=True)
    moved = np.eye(4)
    moved[:3, 3] = [2.0, 0.0, 1.0]
    (reg / "panoramas.json").write_text(json.dumps({"hall": np.eye(4).tolist(), "kitchen": moved.tolist()}))
    v = SceneViewer(tmp_path, ViewerParams(port=_free_port()))
    try:
        assert v.loaded["captures"] == "2 capture points (hall, kitchen)" and "captures" in v.handles
    finally:
        v.stop()
