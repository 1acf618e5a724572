"""The simulation asset checked by its real consumers: usd-core (stage, schemas, validators) and PyBullet (drop, walk,
wall), plus the geometry against the synthetic ground truth."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from panoworld.asset import read_asset_doc, write_asset_doc
from panoworld.core.conventions import invert_pose, transform_points
from tests.test_report import pipeline_scene  # noqa: F401 - the shared session fixture (ci-tiny, every stage run)

pxr = pytest.importorskip("pxr", reason="the sim extra: pip install -e '.[sim]'")
pybullet = pytest.importorskip("pybullet", reason="the sim extra: pip install -e '.[sim]'")

REPO = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.slow  # the shared ci-tiny pipeline run


@pytest.fixture(scope="module")
def asset(pipeline_scene):  # noqa: F811
    a = pipeline_scene / "artifacts" / "asset"
    return a, read_asset_doc(a)


def test_asset_doc_reader_names_the_file(tmp_path):
    from panoworld.core.errors import ArtifactError

    doc = {"asset_from_canonical": np.eye(4).tolist(), "spawn": [0.0, 0.0, 0.0]}
    write_asset_doc(tmp_path, doc)
    assert read_asset_doc(tmp_path) == doc
    (tmp_path / "asset.json").write_text('{"spawn": [0, 0, 0]}')
    with pytest.raises(ArtifactError, match=r"asset\.json: not an asset document"):
        read_asset_doc(tmp_path)
    (tmp_path / "asset.json").write_text("{")
    with pytest.raises(ArtifactError, match=r"asset\.json: unreadable"):
        read_asset_doc(tmp_path)


@pytest.fixture(scope="module")
def stage(asset):
    from pxr import Usd

    s = Usd.Stage.Open(str(asset[0] / "scene.usdc"))
    assert s is not None
    return s


def _bullet(asset):
    from panoworld.asset.physics import Agent, BulletScene

    ag = asset[1]["agent"]
    return BulletScene(asset[0] / "collider.obj",
                       Agent(radius=ag["agent_radius_m"], height=ag["agent_height_m"], step_height=ag["step_height_m"]))


def test_collider_obj_is_the_text_trimesh_writes(tmp_path):
    """write_obj formats without trimesh; trimesh's export_obj (8 decimals, 1-based faces) is its oracle."""
    import trimesh

    from panoworld.asset.collider import write_obj

    rng = np.random.default_rng(0)
    verts = rng.normal(size=(500, 3)) * 3
    verts[0] = [-0.0, 1e-9, -1e-9]  # signed zero and values rounding to it
    verts[1] = [1234.5, 0.5e-8, 1.5e-8]  # ties at the 8th decimal
    faces = rng.integers(0, 500, (300, 3))
    write_obj(tmp_path / "c.obj", verts, faces, "a header")
    ref = trimesh.exchange.obj.export_obj(trimesh.Trimesh(verts, faces, process=False), include_normals=False,
                                          include_color=False, include_texture=False, header=None)
    assert (tmp_path / "c.obj").read_text() == f"# a header\n{ref}"


def test_usd_validators_pass_and_stage_metadata(stage):
    from pxr import UsdGeom, UsdPhysics, UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) >= 20  # every validator usd-core registers (what usdchecker runs)
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    assert [e.GetMessage() for e in errors] == []
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdPhysics.GetStageKilogramsPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/World"
    scene = UsdPhysics.Scene(stage.GetPrimAtPath("/World/PhysicsScene"))
    assert tuple(scene.GetGravityDirectionAttr().Get()) == (0.0, 0.0, -1.0)
    assert scene.GetGravityMagnitudeAttr().Get() == pytest.approx(9.81)


def test_gaussians_are_one_particle_field_with_every_gaussian(stage, asset, pipeline_scene):  # noqa: F811
    from plyfile import PlyData
    from pxr import Usd, UsdVol

    ply = PlyData.read(str(pipeline_scene / "artifacts" / "gaussians" / "gaussians.ply"))["vertex"].data
    fields = [p for p in stage.Traverse() if p.IsA(UsdVol.ParticleField3DGaussianSplat)]
    assert len(fields) == 1
    g = UsdVol.ParticleField3DGaussianSplat(fields[0])
    pos = np.array(g.GetPositionshAttr().Get(), np.float64)
    assert len(pos) == len(ply) > 100
    world = np.array(g.ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T  # Gf row vectors -> column
    ply_xyz = np.stack([ply["x"], ply["y"], ply["z"]], 1)
    a_from_c = np.array(asset[1]["asset_from_canonical"])
    # Half precision about the capture point: off by at most 2^-11 of the distance from it.
    err = np.linalg.norm(transform_points(world, pos) - transform_points(a_from_c, ply_xyz), axis=1)
    assert (err <= 2.0**-11 * np.linalg.norm(ply_xyz, axis=1) + 1e-6).all()
    # Everything in half precision (the schema's *h attributes), and only there.
    assert not any(a.HasAuthoredValue() for a in (g.GetPositionsAttr(), g.GetOrientationsAttr(), g.GetScalesAttr(),
                                                   g.GetOpacitiesAttr(), g.GetRadianceSphericalHarmonicsCoefficientsAttr()))
    assert str(g.GetOrientationshAttr().GetTypeName()) == "quath[]"
    q = np.array([[o.GetReal(), *o.GetImaginary()] for o in g.GetOrientationshAttr().Get()])
    rot = np.stack([ply[f"rot_{k}"] for k in range(4)], 1)
    np.testing.assert_allclose(q, rot / np.linalg.norm(rot, axis=1, keepdims=True), atol=1e-3)
    np.testing.assert_allclose(np.array(g.GetScaleshAttr().Get()),
                               np.exp(np.stack([ply[f"scale_{k}"] for k in range(3)], 1)), rtol=1e-3)
    np.testing.assert_allclose(np.array(g.GetOpacitieshAttr().Get()), 1 / (1 + np.exp(-ply["opacity"])), atol=1e-3)
    deg = g.GetRadianceSphericalHarmonicsDegreeAttr().Get()
    sh = np.array(g.GetRadianceSphericalHarmonicsCoefficientshAttr().Get()).reshape(len(ply), (deg + 1) ** 2, 3)
    np.testing.assert_allclose(sh[:, 0], np.stack([ply[f"f_dc_{k}"] for k in range(3)], 1), rtol=1e-3, atol=1e-4)

def test_collider_mesh_has_physics_apis_and_equals_collider_obj(stage, asset):
    import trimesh
    from pxr import UsdGeom, UsdPhysics

    prim = stage.GetPrimAtPath("/World/Collider")
    assert prim.HasAPI(UsdPhysics.CollisionAPI) and prim.HasAPI(UsdPhysics.MeshCollisionAPI)
    assert UsdPhysics.MeshCollisionAPI(prim).GetApproximationAttr().Get() == UsdPhysics.Tokens.none
    m = UsdGeom.Mesh(prim)
    counts = np.array(m.GetFaceVertexCountsAttr().Get())
    assert (counts == 3).all()
    obj = trimesh.load(asset[0] / "collider.obj", process=False, force="mesh")
    assert len(counts) == len(obj.faces) == asset[1]["counts"]["collider_triangles"]
    np.testing.assert_allclose(np.array(m.GetPointsAttr().Get()), obj.vertices, atol=1e-4)
    nav = stage.GetPrimAtPath("/World/NavMesh")
    assert UsdGeom.Imageable(nav).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
    nav_pts = np.array(UsdGeom.Mesh(nav).GetPointsAttr().Get())
    assert np.abs(nav_pts[:, 2]).max() < 1e-5  # the NavMesh is the floor: z = 0 in the asset frame


def test_camera_animation_follows_the_planned_poses(stage, asset, pipeline_scene):  # noqa: F811
    from pxr import Usd, UsdGeom

    from panoworld.asset import trajectory_paths

    paths, _ = trajectory_paths(pipeline_scene / "artifacts" / "trajectory")  # one camera per planned path
    a_from_c = np.array(asset[1]["asset_from_canonical"])
    for k, poses in enumerate(paths):
        cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/Trajectory/Camera" + (f"_{k}" if k else "")))
        xf = UsdGeom.Xformable(cam)
        assert xf.GetTimeSamples() == list(map(float, range(len(poses))))
        for i in (0, len(poses) // 2, len(poses) - 1):
            m = np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode(i))).T
            np.testing.assert_allclose(m[:3, 3], (a_from_c @ poses[i])[:3, 3], atol=1e-5)
            np.testing.assert_allclose(-m[:3, 2], (a_from_c @ poses[i])[:3, 2], atol=1e-5)  # USD cameras look along -z
    assert stage.GetEndTimeCode() == max(len(p) for p in paths) - 1


def test_asset_frame_and_spawn_match_ground_truth(asset, pipeline_scene):  # noqa: F811
    import trimesh

    from panoworld.tools.synth.scene import SynthScene
    from panoworld.trajectory import mesh_clearance

    gt = SynthScene.load(pipeline_scene / "gt")
    a, doc = asset
    assert doc["up_axis"] == "Z" and doc["meters_per_unit"] == 1.0 and doc["collider"] == "collider.obj"
    world_from_asset = gt.world_from_canonical @ invert_pose(np.array(doc["asset_from_canonical"]))
    spawn_w = transform_points(world_from_asset, np.array([doc["spawn"]]))[0]
    np.testing.assert_allclose(spawn_w[[0, 2]], gt.world_from_canonical[[0, 2], 3], atol=1e-6)  # below the camera
    assert abs(spawn_w[1]) < 0.02  # on the GT floor (world y = 0)
    obj = trimesh.load(a / "collider.obj", process=False, force="mesh")
    pts = transform_points(world_from_asset, obj.vertices)
    dist = mesh_clearance(gt.vertices, gt.faces, pts, cap=1.0)
    assert np.percentile(dist, 95) < 0.03 and np.median(dist) < 0.01, np.percentile(dist, [50, 95, 100])


def _box_room_erp_mesh(lo: np.ndarray, hi: np.ndarray, rows: int = 128):
    """The ERP mesh of an empty box room [lo, hi] (canonical frame, camera at the origin), exact ray distances."""
    from panoworld.core.conventions import erp_dirs
    from panoworld.geometry.erp_mesh import erp_mesh_from_depth

    d = erp_dirs(rows, 2 * rows).astype(np.float64)
    with np.errstate(divide="ignore"):
        depth = np.where(d > 0, hi / d, lo / d).min(-1).astype(np.float32)
    return erp_mesh_from_depth(depth, np.zeros((rows, 2 * rows, 3), np.uint8))


def _off_box(col, lo: np.ndarray, hi: np.ndarray) -> float:
    """99th percentile of the distance from points spread over the collider to the box's walls (its ground truth)."""
    import trimesh

    pts, _ = trimesh.sample.sample_surface(trimesh.Trimesh(col.vertices, col.faces, process=False), 20000, seed=0)
    inside = np.minimum(pts - lo, hi - pts).min(axis=1)
    outside = np.linalg.norm(np.maximum(np.maximum(lo - pts, pts - hi), 0.0), axis=1)
    return float(np.percentile(np.where(inside > 0, inside, outside), 99))


def test_collider_welds_the_pole_slivers_and_decimates_a_room_to_its_walls():
    # The ERP mesh's rows at the poles are slivers quadric decimation cannot collapse: welded first, a box room's mesh
    # of 65k faces decimates to 1000 that lie on its walls.
    from panoworld.asset.collider import collision_mesh

    lo, hi = np.array([-2.0, -1.1, -1.5]), np.array([2.5, 1.5, 2.0])
    mesh = _box_room_erp_mesh(lo, hi)
    col = collision_mesh(mesh, 1000)
    assert col.info["faces_welded"] < 0.95 * col.info["faces_valid"] and len(col.faces) <= 1000, col.info
    assert _off_box(col, lo, hi) < 0.02, col.info


def test_collider_decimation_stays_on_the_walls_it_decimates(monkeypatch):
    # Quadric decimation asked for fewer faces than it can reach (here: the pole slivers left unwelded) stalls, then
    # collapses edges whatever their error: triangles metres long cut the room's corners (a real capture's noisy,
    # holed mesh does it at 100k faces). The error bound decimates again with a larger budget until the collider lies
    # on the walls; a budget the mesh meets is left as it was.
    from panoworld.asset import collider
    from panoworld.asset.collider import collision_mesh

    monkeypatch.setattr(collider, "WELD_M", 0.0)
    lo, hi = np.array([-2.0, -1.1, -1.5]), np.array([2.5, 1.5, 2.0])
    mesh = _box_room_erp_mesh(lo, hi)
    cut = collision_mesh(mesh, 1000)
    assert _off_box(cut, lo, hi) > 0.3, cut.info
    kept = collision_mesh(mesh, 1000, max_error_m=0.02)
    info = kept.info
    assert _off_box(kept, lo, hi) < 0.03, info
    stalled = info["faces"][0]  # the first decimation could not reach 1000 faces: the next starts a quarter above
    assert stalled > 2000 and info["budgets"][:2] == [1000, int(1.25 * stalled)], info
    assert info["error_m"][-1] <= info["own_error_m"] + 0.02, info
    assert info["decimated"] and len(kept.faces) <= len(mesh.faces) / 4, info
    met = collision_mesh(mesh, info["budgets"][-1], max_error_m=0.02)
    plain = collision_mesh(mesh, info["budgets"][-1])
    assert met.info["budgets"] == info["budgets"][-1:]
    assert np.array_equal(met.vertices, plain.vertices) and np.array_equal(met.faces, plain.faces)


def _grid(p0, u, v, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A parallelogram p0 + s u + t v (s, t in [0, 1]) as an n x n grid of triangle pairs."""
    s = np.linspace(0.0, 1.0, n + 1)
    a, b = np.meshgrid(s, s)
    verts = np.asarray(p0, np.float64) + a.ravel()[:, None] * np.asarray(u) + b.ravel()[:, None] * np.asarray(v)
    i = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].ravel()
    return verts, np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])


def test_pushed_capsule_stops_at_a_steep_slope_a_forced_velocity_climbs(tmp_path):
    # A real capture's furniture seen from one side is a sheet leaning away from the camera: a capsule whose velocity
    # is forced every step climbs it and passes over (as it passed through a real sofa); the 300 N push stops at it.
    from panoworld.asset.collider import write_obj
    from panoworld.asset.physics import HZ, Agent, BulletScene, drop_test

    fv, ff = _grid([-3.0, -3.0, 0.0], [6.0, 0.0, 0.0], [0.0, 6.0, 0.0], 20)
    sv, sf = _grid([1.0, -0.5, 0.0], [0.0, 1.0, 0.0], [0.6 / np.tan(np.radians(80)), 0.0, 0.6], 20)
    write_obj(tmp_path / "slope.obj", np.concatenate([fv, sv]), np.concatenate([ff, sf + len(fv)]), "floor + slope")
    reached = {}
    for name in ("forced", "push"):
        with BulletScene(tmp_path / "slope.obj", Agent(radius=0.25, height=1.8)) as sim:
            drop_test(sim, np.zeros(3), drop_m=0.05, seconds=0.5)
            for _ in range(int(6 * HZ)):
                sim.step(np.array([0.5, 0.0])) if name == "forced" else sim.push(np.array([0.5, 0.0]))
            reached[name] = sim.feet()[0]
    assert reached["forced"] > 2.0 and abs(reached["push"] - 0.75) < 0.06, reached


def test_wall_push_picks_a_wall_met_head_on_not_nearer_furniture(tmp_path):
    # A leaning sheet 0.6 m in front of the spawn blocks every ray of the capsule's height, at distances 0.3 m apart:
    # furniture, which a frictionless capsule may slide along. The push goes into a wall of the room instead.
    from panoworld.asset.collider import write_obj
    from panoworld.asset.physics import Agent, BulletScene, nearest_wall, wall_ok, wall_test

    parts = [_grid([-2.0, -3.0, 0.0], [6.0, 0.0, 0.0], [0.0, 6.0, 0.0], 12),  # floor, x -2..4, y -3..3
             _grid([-2.0, -3.0, 0.0], [0.0, 6.0, 0.0], [0.0, 0.0, 2.5], 12),  # walls at x = -2, 4, y = -3, 3
             _grid([4.0, -3.0, 0.0], [0.0, 6.0, 0.0], [0.0, 0.0, 2.5], 12),
             _grid([-2.0, -3.0, 0.0], [6.0, 0.0, 0.0], [0.0, 0.0, 2.5], 12),
             _grid([-2.0, 3.0, 0.0], [6.0, 0.0, 0.0], [0.0, 0.0, 2.5], 12),
             _grid([0.6, -0.6, 0.0], [0.0, 1.2, 0.0], [0.32, 0.0, 1.9], 12)]  # the leaning sheet, x 0.6..0.92
    verts, faces, n = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + n)
        n += len(v)
    write_obj(tmp_path / "room.obj", np.concatenate(verts), np.concatenate(faces), "room with a leaning sheet")
    with BulletScene(tmp_path / "room.obj", Agent(radius=0.25, height=1.8)) as sim:
        wall = nearest_wall(sim, np.zeros(3))
        assert wall["flat"] and abs(wall["distance_m"] - 2.0) < 0.01, wall  # the wall at x = -2, behind the spawn
        np.testing.assert_allclose(wall["direction"], [-1.0, 0.0, 0.0], atol=1e-9)
        r = wall_test(sim, np.zeros(3))
    assert wall_ok(r) and abs(r["gap_m"]) < 0.05 and r["flat"], r


def test_clearance_over_a_dense_mesh_is_the_distance(tmp_path):
    # 80k triangles within a metre of the capsule: one PyBullet query that far returns zero-filled points (or crashes)
    from panoworld.asset.collider import write_obj
    from panoworld.asset.physics import Agent, BulletScene

    write_obj(tmp_path / "floor.obj", *_grid([-1.0, -1.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0], 200), "dense floor")
    write_obj(tmp_path / "speck.obj", *_grid([-0.01, -0.01, 0.0], [0.02, 0.0, 0.0], [0.0, 0.02, 0.0], 200), "speck")
    with BulletScene(tmp_path / "floor.obj", Agent(radius=0.25, height=1.8)) as sim:
        for h in (0.1, 0.5, 0.0005):
            sim.place(np.array([0.0, 0.0, h]))
            assert abs(sim.clearance() - h) < 1e-3, h
        sim.place(np.array([0.0, 0.0, 1.5]))
        assert sim.clearance() == 1.0
    with BulletScene(tmp_path / "speck.obj", Agent(radius=0.25, height=1.8)) as sim:
        sim.place(np.zeros(3))
        with pytest.raises(ValueError, match="within a millimetre of the capsule: decimate the collider"):
            sim.clearance()


def test_capsule_dropped_at_spawn_rests_on_the_floor(asset):
    from panoworld.asset.physics import drop_test

    with _bullet(asset) as sim:
        r = drop_test(sim, np.array(asset[1]["spawn"]), drop_m=0.5)
    assert r["speed_m_s"] < 0.01 and abs(r["rest_height_m"]) < 0.02 and r["drift_m"] < 0.02, r


def test_capsule_walked_along_the_plan_never_penetrates(asset, pipeline_scene):  # noqa: F811
    from panoworld.asset import trajectory_paths
    from panoworld.asset.physics import walk_test

    paths, _ = trajectory_paths(pipeline_scene / "artifacts" / "trajectory")
    a_from_c = np.array(asset[1]["asset_from_canonical"])
    with _bullet(asset) as sim:
        walked = 0.0
        for path in paths:  # every planned path
            xy = transform_points(a_from_c, path[:, :3, 3])[:, :2]
            r = walk_test(sim, xy, floor_z=0.0)
            assert r["min_clearance_m"] > 0.0, r
            walked += r["length_m"]
        assert walked > 0.3
        # the same sweep through the nearest wall collides: the check can fail (sampled every 10 cm: a wall crossed
        # between two samples is within 5 cm of one of them, inside the capsule)
        wall = walk_test(sim, np.stack([xy[0], xy[0] + 6.0 * np.array([1.0, 0.0])]), floor_z=0.0, max_step_m=0.1)
        assert wall["min_clearance_m"] < 0.0, wall


def test_capsule_pushed_towards_a_wall_stops_at_it(asset):
    from panoworld.asset.physics import wall_ok, wall_test

    with _bullet(asset) as sim:
        r = wall_test(sim, np.array(asset[1]["spawn"]))
    assert 0.3 < r["wall_distance_m"] < 6.0, r
    assert wall_ok(r), r  # in contact with an obstacle, not through the wall, not through the floor
    assert abs(r["gap_m"]) < 0.05, r  # the synthetic room: nothing beside the way, so it stops at the wall itself


def test_several_paths_become_several_cameras(pipeline_scene, tmp_path):  # noqa: F811
    from pxr import Usd, UsdGeom

    from panoworld.asset import build_asset
    from panoworld.geometry.erp_mesh import load_erp_mesh
    from panoworld.geometry.navmesh import load_navmesh
    from panoworld.io.splat_ply import read_gaussians_ply

    arts = pipeline_scene / "artifacts"
    traj = tmp_path / "trajectory"
    shutil.copytree(arts / "trajectory", traj)
    doc = json.loads((traj / "trajectory.json").read_text())
    doc["paths"] = [{"start": 1, "stop": len(doc["poses"])}, {"start": 1, "stop": 3}]  # pose ranges, from pose 0
    (traj / "trajectory.json").write_text(json.dumps(doc))
    out = tmp_path / "asset"
    out.mkdir()
    info = build_asset(out, mesh=load_erp_mesh(arts / "mesh"), nav=load_navmesh(arts / "navmesh"), trajectory_dir=traj,
                       gaussians=read_gaussians_ply(arts / "gaussians" / "gaussians.ply"), max_triangles=8000)
    assert info["compliance_errors"] == [] and info["cameras"] == 2
    s = Usd.Stage.Open(str(out / "scene.usdc"))
    cams = [p for p in s.Traverse() if p.IsA(UsdGeom.Camera)]
    assert [len(UsdGeom.Xformable(c).GetTimeSamples()) for c in cams] == [len(doc["poses"]), 3]
    assert info["collider"]["faces_decimated"] <= 8000  # the budget; the NavMesh floor comes on top
    n_nav = len(load_navmesh(arts / "navmesh").triangles)
    assert info["collider_triangles"] == info["collider"]["faces_decimated"] + n_nav


def test_unreadable_gaussians_is_one_line_exit_2_nothing_written(pipeline_scene, tmp_path):  # noqa: F811
    import stages.asset as stage
    from panoworld.core.errors import InputError

    arts = pipeline_scene / "artifacts"
    bad = tmp_path / "gaussians"
    bad.mkdir()
    (bad / "gaussians.ply").write_text("not a ply")
    out = tmp_path / "asset"
    cmd = [sys.executable, "-m", "stages.asset", "--gaussians", str(bad), "--mesh", str(arts / "mesh"),
           "--navmesh", str(arts / "navmesh"), "--trajectory", str(arts / "trajectory"), "--out", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.strip().splitlines() if ln]
    assert len(lines) == 1 and str(bad) in lines[0], res.stderr
    assert not out.exists()
    inputs = {"gaussians": bad, "mesh": arts / "mesh", "navmesh": arts / "navmesh", "trajectory": arts / "trajectory"}
    out.mkdir()
    with pytest.raises(InputError, match="gaussians.ply.*rerun the gaussians stage"):
        stage.run(inputs, stage.Params(), out)
    assert list(out.iterdir()) == []


def _box_room(size: float, floor_y: float):
    """A size x size m room (canonical frame: y down, the floor at floor_y, walls 2.5 m high) as a Collider, and its
    NavMesh: the floor kept 0.35 m (an agent's 0.25 m radius and a cell) from every wall."""
    from panoworld.asset.collider import Collider
    from panoworld.geometry.navmesh import NavMesh

    top = floor_y - 2.5
    c = [(0.0, 0.0), (size, 0.0), (size, size), (0.0, size)]
    v = [(x, floor_y, z) for x, z in c] + [(x, top, z) for x, z in c]
    f = [(0, 1, 2), (0, 2, 3)]
    for k in range(4):  # each wall a quad between floor and top
        a, b = k, (k + 1) % 4
        f += [(a, b, b + 4), (a, b + 4, a + 4)]
    m = 0.35
    ring = np.array([(m, m), (size - m, m), (size - m, size - m), (m, size - m)])
    nav = NavMesh(ring, [[0, 1, 2], [0, 2, 3]], [[-1, 1, -1], [-1, -1, 0]], [ring], floor_y=floor_y,
                  agent={"agent_radius_m": 0.25, "agent_height_m": 1.5, "step_height_m": 0.2})
    return Collider(np.array(v, np.float64), np.array(f, np.int64), {}), nav


def test_a_camera_nearer_a_wall_than_the_agent_spawns_it_on_the_navmesh(tmp_path):
    # A camera 0.15 m from a wall (a closet door, a hallway): the floor below it lies inside the agent's radius of the
    # wall, so the spawn moves to the nearest NavMesh floor, where PyBullet's capsule stands clear of the wall; a camera
    # over the NavMesh keeps the floor below it, and one beyond reach of any NavMesh (1 m) does too.
    from panoworld.asset.build import agent_spawns, capture_spawns
    from panoworld.asset.collider import write_obj
    from panoworld.asset.physics import Agent, BulletScene
    from panoworld.core.conventions import asset_from_canonical

    floor_y = 1.4
    col, nav = _box_room(4.0, floor_y)
    cams = np.array([[0.15, 0.0, 2.0], [2.0, 0.0, 1.0], [-1.5, 0.0, 2.0]])
    (near, src_near, moved_near), (inside, _, moved_inside), (far, _, moved_far) = agent_spawns(col, nav, cams)
    assert src_near == "collider" and abs(moved_near - 0.20) < 0.005, moved_near
    np.testing.assert_allclose(near, [0.35, floor_y, 2.0], atol=0.005)
    assert moved_inside == 0.0 and np.allclose(inside, [2.0, floor_y, 1.0])
    assert moved_far == 0.0 and np.allclose(far[[0, 2]], [-1.5, 2.0])
    a_from_c = asset_from_canonical(floor_y)
    points = capture_spawns(col, nav, {"door": np.array([[1, 0, 0, 0.15], [0, 1, 0, 0], [0, 0, 1, 2.0], [0, 0, 0, 1]])},
                            a_from_c)
    assert points["door"]["spawn_from_floor_m"] == pytest.approx(0.20, abs=0.005)
    np.testing.assert_allclose(points["door"]["spawn"], transform_points(a_from_c, near[None])[0], atol=1e-5)
    write_obj(tmp_path / "room.obj", transform_points(a_from_c, col.vertices), col.faces, "box room")
    with BulletScene(tmp_path / "room.obj", Agent(radius=0.25, height=1.5)) as sim:
        clear = {}
        for k, p in {"below the camera": np.array(points["door"]["floor"]),
                     "spawn": np.array(points["door"]["spawn"])}.items():
            sim.place(p + [0.0, 0.0, 0.05])  # feet just above the floor: what it touches is a wall
            clear[k] = sim.clearance()
    assert clear["below the camera"] < -0.05 and clear["spawn"] > 0.05, clear
