"""A home from several panoramas through `runner.py run` (issue #27): every stage, capture points on the NavMesh,
the trajectory visiting them, and the Gaussian scene reproducing each panorama at its capture pose."""

from __future__ import annotations

import json
import re
import shutil

import cv2
import numpy as np
import pytest
import torch

from panoworld.core.conventions import invert_pose
from panoworld.framework import pipeline as pl
from panoworld.gaussians.quality import capture_psnr
from panoworld.io import manifest as art
from panoworld.io.depth import read_panorama
from panoworld.io.home import capture_poses, home_depth_dirs

torch.set_num_threads(1)

SMALL = ["mesh.home_stride=4", "trajectory.sectors=4", "gaussians.source_height=128", "register.height=384",
         "gaussians.capture_fit_height=64"]
"""ci-tiny plus: coarser fused mesh, fewer explore paths per capture point, small per-pixel sources (test speed)."""


@pytest.fixture(scope="module")
def home_run(home_dir, tmp_path_factory):
    scene = tmp_path_factory.mktemp("run") / "scene"
    shutil.copytree(home_dir, scene, ignore=shutil.ignore_patterns("artifacts"))
    report = pl.run(scene, preset="ci-tiny", sets=SMALL)
    return scene, report


@pytest.mark.slow
def test_home_runs_every_stage_and_caches(home_run):
    scene, report = home_run
    assert [r.action for r in report.results] == ["ran"] * len(pl.Pipeline.load().order), report.table()
    again = pl.run(scene, preset="ci-tiny", sets=SMALL)
    assert {r.action for r in again.results} == {"cached"}, again.table()
    depth = art.read_manifest(scene / "artifacts" / "depth")["info"]
    assert depth["home"]["names"] == ["pano_00", "pano_01", "pano_02"]
    for r in report.results:  # every stage's CPU seconds (all threads) beside its wall seconds
        m = art.read_manifest(scene / "artifacts" / r.stage)
        assert 0 < m["cpu_s"] < 2 * m["wall_s"] + 1, (r.stage, m["cpu_s"], m["wall_s"])


@pytest.mark.slow
def test_home_capture_points_registered_on_navmesh_and_visited(home_run):
    scene, _ = home_run
    arts = scene / "artifacts"
    est = capture_poses(arts / "register")
    gt = {n: np.asarray(T) for n, T in json.loads((scene / "gt" / "poses.json").read_text()).items()}
    for n, E in est.items():
        G = invert_pose(gt["pano_00"]) @ gt[n]
        assert np.linalg.norm(G[:3, 3] - E[:3, 3]) < 0.05, n
    nav = art.read_manifest(arts / "navmesh")["info"]
    assert nav["capture_points_on_navmesh"] == dict.fromkeys(est, True)
    traj = art.read_manifest(arts / "trajectory")["info"]
    assert traj["kind"] == "home" and traj["invalid_poses"] == [] and traj["plan"]["unreached_captures"] == []
    poses = np.asarray(json.loads((arts / "trajectory" / "trajectory.json").read_text())["poses"])
    for n, k in traj["plan"]["capture_frames"].items():  # a frame stands at every capture point ...
        assert np.allclose(poses[k][:3, 3], est[n][:3, 3], atol=1e-6), n
    walks = [p for p in traj["plan"]["paths"] if "walk" in p]  # ... and walks join them
    assert len(walks) == 2 and all(p["stop"] > p["start"] for p in walks)
    assert len(poses) == traj["frames"] == len(json.loads((arts / "poses" / "poses.json").read_text())["poses"])


@pytest.mark.slow
def test_home_gaussians_reproduce_every_panorama_at_its_capture_pose(home_run):
    scene, _ = home_run
    arts = scene / "artifacts"
    info = art.read_manifest(arts / "gaussians")["info"]
    captures = capture_poses(arts / "register")
    panos = {n: read_panorama(scene / "panoramas" / f"{n}.png") for n in captures}
    scores = capture_psnr(arts / "gaussians" / "gaussians.ply", captures, panos, height=64)
    assert min(scores.values()) > 27.0, scores
    # Every source is anchored, but no surface twice: fewer per-pixel Gaussians than the sources' pixels.
    assert 0.4 * 3 * 128 * 256 < info["num_source_gaussians"] < 0.9 * 3 * 128 * 256


def test_sources_visibility_is_the_or_of_each_source(home_dir):
    """The home's test of what the panoramas already explain asks the sources nearest first and each only about what
    the nearer ones left: the same answer as asking every source about every point (and the same for poking)."""
    from panoworld.gaussians.home import SourcesVisibility
    from panoworld.gaussians.pixel import SourceVisibility
    from panoworld.io.gaussian_set import Gaussians

    poses = {n: np.asarray(T) for n, T in json.loads((home_dir / "gt" / "poses.json").read_text()).items()}
    each = [SourceVisibility(np.load(home_dir / "depths" / f"{n}.npy"), T, 0.03) for n, T in poses.items()]
    rng = np.random.default_rng(0)
    centres = np.array([T[:3, 3] for T in poses.values()])
    # Points around every capture point (in front of, on and behind surfaces) and far from all of them.
    pts = np.concatenate([c + rng.normal(scale=2.0, size=(3000, 3)) for c in centres])
    want = np.logical_or.reduce([s.explained(pts) for s in each])
    assert 0.1 < want.mean() < 0.9  # both kinds are tested
    seen = SourcesVisibility(each)
    assert np.array_equal(seen.explained(pts), want)
    assert np.array_equal(seen.explained(pts[:0]), np.zeros(0, bool))
    n = len(pts)
    g = Gaussians(pts.astype(np.float32), np.full((n, 3), 0.05, np.float32), np.tile([1, 0, 0, 0], (n, 1)).astype(
        np.float32), np.full(n, 0.9, np.float32), np.zeros((n, 3), np.float32))
    assert np.array_equal(seen.poking_through(g), np.logical_or.reduce([s.poking_through(g) for s in each]))


def test_home_rig_masks_override_detection_per_panorama(home_dir, tmp_path, capsys):
    """SCENE/rig_masks/NAME.png is that panorama's rig (as rig_mask.png is one panorama's): inside it the floor is
    made up from the floor plane; the other panoramas are untouched. A mask naming no panorama: exit 2, one line."""
    from stages.depth import main as depth_main

    masks = tmp_path / "rig_masks"
    masks.mkdir()
    pano = read_panorama(home_dir / "panoramas" / "pano_01.png")
    h = pano.shape[0]
    mask = np.zeros((h, 2 * h), np.uint8)
    mask[int(0.93 * h):] = 255  # the nadir cap below -77 degrees
    cv2.imwrite(str(masks / "pano_01.png"), mask)
    out = tmp_path / "depth"
    args = ["--panoramas", str(home_dir / "panoramas"), "--depths", str(home_dir / "depths"), "--rig-masks",
            str(masks), "--complete-dropouts", "false"]
    assert depth_main([*args, "--out", str(out)]) == 0
    info = art.read_manifest(out)["info"]["home"]["panoramas"]
    assert info["pano_01"]["rig"]["kind"] == "user" and info["pano_01"]["rig"]["found"]
    assert all(info[n]["rig"]["kind"] != "user" for n in info if n != "pano_01")
    cleaned = read_panorama(out / "panoramas" / "pano_01" / "panorama.png")
    inside = mask > 0
    assert np.abs(cleaned.astype(int) - pano.astype(int))[~inside].max() == 0  # untouched outside the mask
    assert np.abs(cleaned.astype(int) - pano.astype(int))[inside].mean() > 1  # inpainted inside it

    cv2.imwrite(str(masks / "pano_09.png"), mask)
    capsys.readouterr()
    assert depth_main([*args, "--out", str(tmp_path / "depth2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pano_09.png" in err[0] and "rig_masks" in err[0] and not (tmp_path / "depth2").exists()


def test_conditions_take_each_surface_from_its_nearest_panorama(home_dir):
    """Conditions are rendered from the fused mesh, whose colours come from the panorama that sees each surface
    nearest: rendered at every capture pose they reproduce that panorama (covered and close in colour), also where
    other panoramas' surfaces show."""
    from panoworld.conditions.warp import render_conditions
    from panoworld.mesh.home import home_mesh

    gt = {n: np.asarray(T) for n, T in json.loads((home_dir / "gt" / "poses.json").read_text()).items()}
    poses = {n: invert_pose(gt["pano_00"]) @ T for n, T in gt.items()}
    dirs = {}
    for n in poses:  # a depth artifact's per-panorama folders
        d = home_dir.parent / "home_depth" / n
        d.mkdir(parents=True, exist_ok=True)
        depth = np.load(home_dir / "depths" / f"{n}.npy")
        np.save(d / "depth.npy", depth)
        cv2.imwrite(str(d / "valid.png"), (depth > 0).astype(np.uint8) * 255)
        shutil.copy(home_dir / "panoramas" / f"{n}.png", d / "panorama.png")
        dirs[n] = d
    mesh, _, sources = home_mesh(dirs, poses, stride=4)
    assert [s["name"] for s in sources] == list(poses)
    h = 64
    for n, T in poses.items():
        frame = render_conditions(mesh, T[None], h, 2 * h)[0]
        ref = cv2.resize(read_panorama(home_dir / "panoramas" / f"{n}.png"), (2 * h, h), interpolation=cv2.INTER_AREA)
        ok = frame.mask > 0
        err = np.abs(frame.rgb.astype(np.float32) - ref.astype(np.float32))[ok].mean()
        assert ok.mean() > 0.97 and err < 8.0, (n, ok.mean(), err)


@pytest.mark.slow
def test_home_report_marks_every_capture_point(home_run, tmp_path):
    from panoworld.tools.report.cli import build_scene_report

    scene, _ = home_run
    page = build_scene_report(scene, tmp_path / "report.html").read_text()
    for n in ("pano_00", "pano_01", "pano_02"):
        assert f"capture point {n}" in page
    assert "3 capture points" in page


def _home_section(page: str) -> str:
    start = page.index('<section id="home"')
    return page[start:page.index("</section>", start)]


@pytest.mark.slow
def test_home_report_shows_how_each_panorama_was_placed(home_run, tmp_path):
    from panoworld.tools.report.browser import browser_page
    from panoworld.tools.report.cli import build_scene_report

    scene, _ = home_run
    arts = scene / "artifacts"
    reg = json.loads((arts / "register" / "registration.json").read_text())["panoramas"]
    fit = art.read_manifest(arts / "gaussians")["info"]["color_fit"]
    out = build_scene_report(scene, tmp_path / "report.html")
    page = out.read_text()
    home = _home_section(page)
    assert 'class="present"' in home and "could not draw" not in page
    assert "3 of 3 panoramas registered (0 given in poses.json)" in home and "Not placed" not in home
    plan = re.search(r"<svg.*?</svg>", home, re.S).group(0)
    for n, p in reg.items():
        assert f"<td>{n}</td>" in home and f">{n}</text>" in plan  # a table row and a label on the plan
        if p["parent"] is not None:  # the edge that placed it, drawn and named
            assert f"<td>{p['parent']} ({p['edge']}, {p['inliers']} inliers)</td>" in home
        assert f"{20 * np.log10(1 / fit['rmse_after'][n]):.2f}" in home  # its capture pose's colour-fit PSNR
    assert home.count("<polyline") == sum(p["parent"] is not None for p in reg.values())
    pairs = json.loads((arts / "register" / "registration.json").read_text())["pairs"]  # the matrix: a cell each way
    assert home.count('stroke="#000" stroke-width="2"><title>') == 2 * sum(p["parent"] is not None for p in reg.values())
    for r in pairs:
        assert home.count(f"<title>{r['a']} - {r['b']}: ") == 2 and f"floor {r['floor_inliers']} inliers" in home
    data = json.loads(re.search(r'id="report-data">(.*?)</script>', page, re.S).group(1))["home"]
    assert [t.split(":")[0] for t in data["text"]["label"]] == list(reg)
    assert all(u.startswith("data:image/jpeg;base64,") for c in ("panorama", "depth") for u in data["images"][c])
    with browser_page(1280, 900) as (tab, console):
        tab.goto(out.resolve().as_uri())
        tab.wait_for_load_state("load")
        assert tab.locator("section#home").is_visible()
        pano = tab.locator('img[data-slot="home:panorama"]')
        assert pano.get_attribute("src") == data["images"]["panorama"][0]
        tab.locator('input[data-slider="home"]').fill("2")
        assert pano.get_attribute("src") == data["images"]["panorama"][2]
        assert tab.locator('[data-text="home:label"]').text_content() == data["text"]["label"][2]
        assert console.errors == []


@pytest.mark.slow
def test_home_report_names_a_panorama_left_unregistered_and_why(home_run, tmp_path):
    from panoworld.io.manifest import manifest_checksum
    from panoworld.tools.report.cli import build_scene_report

    scene = tmp_path / "scene"
    shutil.copytree(home_run[0], scene, ignore=shutil.ignore_patterns("conditions", "video", "poses", "asset"))
    reg_dir = scene / "artifacts" / "register"
    doc = json.loads((reg_dir / "registration.json").read_text())
    why = "no pair with the registered panoramas (group: pano_01, pano_02; 2 pair(s) tried)"
    for n in ("pano_01", "pano_02"):
        doc["panoramas"][n] = {"registered": False, "source": None, "parent": None, "reason": why,
                               "group": ["pano_01", "pano_02"]}
    (reg_dir / "registration.json").write_text(json.dumps(doc))
    poses = json.loads((reg_dir / "panoramas.json").read_text())
    (reg_dir / "panoramas.json").write_text(json.dumps({"pano_00": poses["pano_00"]}))
    home = _home_section(build_scene_report(scene, tmp_path / "report.html").read_text())
    assert "1 of 3 panoramas registered" in home
    assert home.count('<span class="bad">not registered</span>') == 2 and home.count(why) >= 2
    assert "Not placed, by group (panoramas joined to each other but to no registered one): pano_01, pano_02." in home
    assert "levelled for registration" not in home
    doc["panoramas"]["pano_00"]["levelled_tilt_deg"] = 1.962  # as register writes it for a camera that was not level
    (reg_dir / "registration.json").write_text(json.dumps(doc))
    home = _home_section(build_scene_report(scene, tmp_path / "report.html").read_text())
    assert "Taken with the camera not level, levelled for registration" in home and "pano_00 2.0°" in home
    assert "levelled by the depth stage" not in home
    manifest = scene / "artifacts" / "depth" / "manifest.json"
    doc = json.loads(manifest.read_text())  # as the depth stage writes it for pano_01 taken 2 deg off level
    doc["info"]["home"]["panoramas"]["pano_01"]["level"] = {"image_tilt_deg": 2.1, "verticals": 80, "tilt_deg": 2.04,
                                                            "floor_residual_deg": 0.2, "level_from_cam": np.eye(3).tolist()}
    doc["checksum"] = manifest_checksum(doc)
    manifest.write_text(json.dumps(doc))
    home = _home_section(build_scene_report(scene, tmp_path / "report.html").read_text())
    assert "Taken off level, levelled by the depth stage" in home and "pano_01 2.0°" in home
    plan = re.search(r"<svg.*?</svg>", home, re.S).group(0)  # the capture points from above: the registered one alone
    assert ">pano_00</text>" in plan and ">pano_01</text>" not in plan and "<polyline" not in plan


@pytest.mark.slow
def test_eval_scores_a_home_registration_and_names_a_misplaced_panorama(home_run, tmp_path):
    from panoworld.tools.eval.cli import evaluate
    from panoworld.tools.eval.common import EvalParams

    scene, _ = home_run
    report, errors = evaluate(scene, EvalParams(gs_height=64, views=1), stages=["register", "mesh", "gaussians"],
                              progress=False)
    reg, mesh, gs = (report["stages"][k] for k in ("register", "mesh", "gaussians"))
    captures = capture_poses(scene / "artifacts" / "register")  # every capture pose against its cleaned panorama
    dirs = home_depth_dirs(scene / "artifacts" / "depth")
    scores = capture_psnr(scene / "artifacts" / "gaussians" / "gaussians.ply", captures,
                          {n: read_panorama(dirs[n] / "panorama.png") for n in captures}, height=64)
    assert gs["capture_psnr_min"] == min(scores.values()) > 27.0 and scores[gs["capture_worst"]] == min(scores.values())
    assert gs["capture_psnr_median"] == float(np.median(list(scores.values())))
    assert report["targets"]["gaussians"]["capture_psnr_min"]["met"]
    assert errors == [] and reg["registered"] == 3 and reg["registered_fraction"] == 1.0 and reg["anchor"] == "pano_00"
    assert reg["trans_cm_max"] < 5.0 and reg["rot_deg_max"] < 1.0 and reg["misplaced"] == 0
    assert all(report["targets"]["register"][k]["met"] for k in ("registered_fraction", "trans_cm_max", "misplaced"))
    assert mesh["pose0_at"] == "pano_00" and mesh["coverage_pose0"] > 0.9 and mesh["surface_error_median_m"] < 0.02

    copy = tmp_path / "scene"  # pano_02 placed 0.5 m off, pano_01 left out: the errors follow
    shutil.copytree(scene, copy, ignore=shutil.ignore_patterns("conditions", "video", "poses", "gaussians", "asset"))
    doc = json.loads((copy / "artifacts" / "register" / "panoramas.json").read_text())
    doc["pano_02"][0][3] += 0.5
    del doc["pano_01"]
    (copy / "artifacts" / "register" / "panoramas.json").write_text(json.dumps(doc))
    reg = evaluate(copy, stages=["register"], progress=False)[0]["stages"]["register"]
    assert reg["registered"] == 2 and reg["unregistered"] == ["pano_01"] and reg["worst"] == "pano_02"
    assert reg["misplaced"] == 1 and 45.0 < reg["trans_cm_max"] < 55.0


@pytest.mark.slow
def test_eval_takes_the_home_frame_when_the_first_panorama_is_not_registered(home_dir, tmp_path):
    from panoworld.tools.eval.cli import evaluate
    from panoworld.tools.synth import generate_scene

    scene = tmp_path / "scene"
    shutil.copytree(home_dir, scene, ignore=shutil.ignore_patterns("artifacts"))
    h = read_panorama(scene / "panoramas" / "pano_00.png").shape[0]
    other = generate_scene(3, "ci-tiny")  # pano_00 becomes a room of another home: the world is pano_01's camera
    # (pano_01 and pano_02 given their true poses, which join them)
    rgb, depth = other.render(other.world_from_canonical, h, 2 * h)
    cv2.imwrite(str(scene / "panoramas" / "pano_00.png"), rgb[..., ::-1])
    np.save(scene / "depths" / "pano_00.npy", depth)
    truth = json.loads((scene / "gt" / "poses.json").read_text())
    (scene / "poses.json").write_text(json.dumps({n: truth[n] for n in ("pano_01", "pano_02")}))
    assert pl.run(scene, preset="ci-tiny", sets=SMALL, until="navmesh").ok
    assert sorted(capture_poses(scene / "artifacts" / "register")) == ["pano_01", "pano_02"]
    report, errors = evaluate(scene, stages=["register", "mesh", "navmesh"], progress=False)
    reg, mesh, nav = (report["stages"][k] for k in ("register", "mesh", "navmesh"))
    assert errors == [] and reg["anchor"] == "pano_01" and reg["unregistered"] == ["pano_00"]
    assert reg["trans_cm_max"] < 5.0 and reg["misplaced"] == 0
    # geometry is scored in the home's frame: pano_01's camera stands metres from pano_00's
    assert mesh["pose0_at"] == "pano_01" and mesh["surface_error_median_m"] < 0.02
    assert nav["floor_height_error_m"] < 0.02 and nav["free_fraction"] > 0.9


@pytest.mark.slow
def test_home_asset_spawns_at_every_capture_point_in_usd_and_physics(home_run):
    from pxr import Usd, UsdGeom

    from panoworld.asset import read_asset_doc, trajectory_paths
    from panoworld.asset.physics import Agent, BulletScene, drop_test, walk_test
    from panoworld.core.conventions import transform_points
    from panoworld.geometry.navmesh import load_navmesh

    scene, _ = home_run
    arts = scene / "artifacts"
    doc = read_asset_doc(arts / "asset")
    captures = capture_poses(arts / "register")
    a_from_c = np.asarray(doc["asset_from_canonical"])
    assert sorted(doc["capture_points"]) == sorted(captures)
    assert art.read_manifest(arts / "asset")["info"]["capture_points"] == len(captures)
    stage = Usd.Stage.Open(str(arts / "asset" / "scene.usdc"))
    ag = doc["agent"]
    with BulletScene(arts / "asset" / "collider.obj", Agent(radius=ag["agent_radius_m"], height=ag["agent_height_m"],
                                                            step_height=ag["step_height_m"])) as sim:
        for n, T in captures.items():
            cp = doc["capture_points"][n]
            cam = transform_points(a_from_c, T[:3, 3][None])[0]
            np.testing.assert_allclose(cp["camera"], cam, atol=1e-5)
            assert np.allclose(cp["floor"][:2], cam[:2], atol=1e-5) and abs(cp["floor"][2]) < 0.03  # on the floor below
            fwd = a_from_c[:3, :3] @ T[:3, 2]  # the panorama's centre, seen from above
            assert abs(np.degrees(np.arctan2(fwd[1], fwd[0])) - cp["yaw_deg"]) < 1e-3
            prim = stage.GetPrimAtPath(f"/World/CapturePoints/{n}")
            assert prim.IsValid() and prim.GetCustomDataByKey("panorama") == n
            xf = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
            assert cp["spawn_from_floor_m"] == 0.0 and cp["spawn"] == cp["floor"]  # each camera stood on the NavMesh
            np.testing.assert_allclose(np.array(xf.ExtractTranslation()), cp["spawn"], atol=1e-5)
            r = drop_test(sim, np.array(cp["spawn"]), drop_m=0.5)  # the agent stands there
            assert r["speed_m_s"] < 0.01 and abs(r["rest_height_m"]) < 0.02 and r["drift_m"] < 0.02, (n, r)
        # and walks the planned paths through the rooms without touching the decimated collider: from pose to pose
        # where the straight line stays on the NavMesh (ci-tiny's few frames lie metres apart on curved paths)
        nav = load_navmesh(arts / "navmesh")
        walked = []
        for path in trajectory_paths(arts / "trajectory")[0]:
            xz, xy = path[:, :3, 3][:, [0, 2]], transform_points(a_from_c, path[:, :3, 3])[:, :2]
            for j in np.flatnonzero(nav.segment_inside(xz[:-1], xz[1:])):
                walked.append(walk_test(sim, xy[j:j + 2], floor_z=0.0))
        assert len(walked) >= 10 and min(r["min_clearance_m"] for r in walked) > 0.0, walked
