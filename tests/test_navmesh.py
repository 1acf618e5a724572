"""NavMesh: floor height, erosion against ground truth, exact path finding, I/O round trips and the navmesh stage."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from panoworld.core.errors import NoFloorError
from panoworld.geometry.erp_mesh import erp_mesh_from_depth
from panoworld.geometry.navmesh import NavMesh, load_navmesh
from panoworld.geometry.polygons import triangulate_rings
from panoworld.geometry.raycast import Raycaster
from panoworld.navmesh import NavMeshParams, build_navmesh, erp_grid_shape
from panoworld.trajectory import mesh_clearance

CAM_H = 1.5


def box_room(size=(5.0, 2.8, 4.0), cam_xz=(0.0, 0.0), obstacles=(((1.2, 0.8), (0.8, 0.75, 0.6)),)) -> trimesh.Trimesh:
    """Closed box room (x width, height, z depth) around cam_xz, floor at y = CAM_H (camera at the origin).

    obstacles: ((x, z) centre, (ex, ey, ez) extents) boxes standing on the floor.
    """
    sx, sy, sz = size
    t = 0.1
    cx, cz = cam_xz

    def box(ext, c):
        b = trimesh.creation.box(extents=ext)
        b.apply_translation(c)
        return b

    parts = [
        box((sx + 2 * t, t, sz + 2 * t), (cx, CAM_H + t / 2, cz)),
        box((sx + 2 * t, t, sz + 2 * t), (cx, CAM_H - sy - t / 2, cz)),
        box((t, sy, sz), (cx - sx / 2 - t / 2, CAM_H - sy / 2, cz)),
        box((t, sy, sz), (cx + sx / 2 + t / 2, CAM_H - sy / 2, cz)),
        box((sx, sy, t), (cx, CAM_H - sy / 2, cz - sz / 2 - t / 2)),
        box((sx, sy, t), (cx, CAM_H - sy / 2, cz + sz / 2 + t / 2)),
    ]
    for (ox, oz), (ex, ey, ez) in obstacles:
        parts.append(box((ex, ey, ez), (ox, CAM_H - ey / 2, oz)))
    return trimesh.util.concatenate(parts)


def erp_depth(mesh: trimesh.Trimesh, height: int) -> np.ndarray:
    return Raycaster(mesh.vertices, mesh.faces).render_erp(np.eye(4), height, 2 * height).distance.astype(np.float32)


def erp_mesh_of(mesh: trimesh.Trimesh, height: int = 128):
    d = erp_depth(mesh, height)
    return erp_mesh_from_depth(d, np.zeros(d.shape + (3,), np.uint8))


def nav_of(mesh: trimesh.Trimesh, height: int = 128, **kw) -> NavMesh:
    em = erp_mesh_of(mesh, height)
    return build_navmesh(em.vertices, em.faces, em.face_valid, params=NavMeshParams(**kw))


@pytest.fixture(scope="module")
def room():
    gt = box_room(obstacles=(((1.2, 0.8), (0.8, 0.75, 0.6)), ((-1.2, -1.0), (0.04, 1.0, 0.04))))
    return gt, nav_of(gt, 192)


def test_floor_height_and_clearance_against_ground_truth(room):
    gt, nav = room
    assert abs(nav.floor_y - CAM_H) < 0.01
    assert nav.info["camera_on_navmesh"] and nav.contains(np.zeros((1, 2)))[0]
    # Every walkable point keeps the agent radius from all GT geometry (walls, box, thin pole) at camera height.
    pts = np.concatenate([nav.sample_points(400, 0), nav.vertices])
    clear = mesh_clearance(gt.vertices, gt.faces, np.stack([pts[:, 0], np.zeros(len(pts)), pts[:, 1]], 1))
    assert clear.min() >= nav.agent["agent_radius_m"]
    # The eroded area is less than the room minus the radius band, but most of what the camera sees of it.
    assert 8.0 < nav.area < (5.0 - 0.5) * (4.0 - 0.5)
    # The obstacle's footprint and the unseen floor behind it (x 1.6..2.5, z 0.9..1.1) are excluded.
    assert not nav.contains(np.array([[1.2, 0.8], [2.2, 1.0], [-1.2, -1.0]])).any()


def test_thin_obstacle_between_ray_centres_is_kept_out(room):
    _, nav = room
    # The 4 cm pole at (-1.2, -1.0) is thinner than the rays' spacing: nothing within the agent radius is walkable.
    rng = np.random.default_rng(0)
    disc = np.array([-1.2, -1.0]) + 0.25 * np.sqrt(rng.random((500, 1))) * _unit_circle(rng.random(500) * 2 * np.pi)
    assert not nav.contains(disc).any()
    assert nav.clearance(np.array([[-1.2, -1.0]]))[0] < -0.25


def _unit_circle(a):
    return np.stack([np.cos(a), np.sin(a)], 1)


def test_path_is_the_exact_shortest_path():
    # A U-shaped floor: the only way from one arm to the other is round the inner corners.
    u = np.array([[0, 0], [4, 0], [4, 2], [2.5, 2], [2.5, 0.5], [1.5, 0.5], [1.5, 2], [0, 2]], np.float64)
    v, t, adj = triangulate_rings([u], 0.05)
    nav = NavMesh(v, t, adj, [u], floor_y=CAM_H)
    a, b = np.array([0.5, 1.5]), np.array([3.5, 1.5])
    p = nav.path(a, b)
    assert np.allclose(p, [a, [1.5, 0.5], [2.5, 0.5], b], atol=1e-9)
    assert not nav.blocked(p[:-1], p[1:]).any()
    # A chord between boundary vertices across the notch (outside) is blocked; one along the boundary is not.
    assert nav.blocked(np.array([[1.5, 2.0], [0.0, 0.0]]), np.array([[2.5, 2.0], [4.0, 0.0]])).tolist() == [True, False]
    assert nav.blocked(np.array([[1.0, 1.0]]), np.array([[3.0, 1.0]]))[0]  # through the notch
    for i, nbs in enumerate(adj):  # adjacency is symmetric
        for nb in nbs[nbs >= 0]:
            assert i in adj[nb]
    assert np.isclose(nav.area, 8.0 - 1.0 * 1.5)
    assert len(nav.path(np.array([0.2, 0.2]), np.array([1.0, 1.8]))) == 2  # straight when visible
    with pytest.raises(ValueError, match="outside the NavMesh"):
        nav.path(a, np.array([2.0, 1.0]))


def test_path_around_a_hole_takes_the_shorter_side():
    outer = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [0.0, 2.0]])
    hole = np.array([[1.5, 0.5], [1.5, 1.9], [2.5, 1.9], [2.5, 0.5]])  # clockwise; a 0.1 m gap above it
    v, t, adj = triangulate_rings([outer, hole], 0.05)
    nav = NavMesh(v, t, adj, [outer, hole], floor_y=CAM_H)
    p = nav.path(np.array([0.5, 1.5]), np.array([3.5, 1.5]))
    assert np.allclose(p, [[0.5, 1.5], [1.5, 1.9], [2.5, 1.9], [3.5, 1.5]], atol=1e-9)


def test_contains_clearance_and_ray_reach_are_exact():
    sq = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]])
    v, t, adj = triangulate_rings([sq], 0.1)
    nav = NavMesh(v, t, adj, [sq], floor_y=1.0)
    pts = np.array([[0.5, 0.5], [1.9, 0.2], [2.5, 0.5], [-0.3, -0.4]])
    assert nav.contains(pts).tolist() == [True, True, False, False]
    assert np.allclose(nav.clearance(pts), [0.5, 0.1, -0.5, -0.5])
    assert np.allclose(nav.ray_reach(np.array([0.5, 0.5]), np.array([[1.0, 0.0], [0.0, -1.0]])), [1.5, 0.5])
    assert (nav.locate(pts)[:2] >= 0).all() and (nav.locate(pts)[2:] == -1).all()
    s = nav.sample_points(500, 1, min_clearance=0.2)
    assert nav.contains(s).all() and nav.clearance(s).min() >= 0.2


def test_even_odd_matches_the_all_pairs_reference_bit_for_bit():
    from panoworld.geometry.polygons import even_odd, even_odd_reference, ring_segments

    rng = np.random.default_rng(1)
    for _ in range(20):
        rings = []
        for _ in range(int(rng.integers(1, 4))):  # overlapping star rings: holes and self-crossings (even-odd)
            m = int(rng.integers(3, 40))
            t = np.sort(rng.uniform(0, 2 * np.pi, m))
            ring = rng.uniform(-2, 2, 2) + rng.uniform(0.5, 3, (m, 1)) * np.stack([np.cos(t), np.sin(t)], 1)
            rings.append(np.round(ring * 4) / 4 if rng.random() < 0.5 else ring)  # vertices on the points' rows
        segs = ring_segments(rings)
        grid = np.stack(np.meshgrid(np.arange(-24, 25) / 4, np.arange(-24, 25) / 4), -1).reshape(-1, 2)
        pts = np.concatenate([rng.uniform(-6, 6, (2000, 2)), grid, segs[:, 0]])
        ref = even_odd_reference(pts, segs)
        assert 0 < ref.sum() < len(pts)
        assert np.array_equal(even_odd(pts, segs), ref)
        assert np.array_equal(even_odd(pts, segs, max_pairs=int(rng.integers(1, 500))), ref)  # many chunks
    assert even_odd(np.zeros((0, 2)), segs).shape == (0,)


def test_no_floor_is_a_clear_error():
    # A panorama whose lower half has no depth (no floor pixels).
    d = erp_depth(box_room(), 64)
    d[32:] = np.nan
    em = erp_mesh_from_depth(d, np.zeros(d.shape + (3,), np.uint8))
    with pytest.raises(NoFloorError, match="below the camera"):
        build_navmesh(em.vertices, em.faces, em.face_valid)
    # A floor too cramped for the agent: a 0.6 m wide room.
    with pytest.raises(NoFloorError, match="agent radius"):
        nav_of(box_room(size=(0.6, 2.8, 0.6), obstacles=()), 64)


def test_camera_eroded_away_keeps_the_nearest_walkable_component():
    # The camera stands 0.1 m from the left wall: its cell is eroded, the room's floor is kept.
    nav = nav_of(box_room(cam_xz=(2.4, 0.0), obstacles=()), 128)
    assert not nav.info["camera_on_navmesh"]
    assert 0.15 < nav.info["camera_distance_to_navmesh_m"] < 0.35
    assert nav.area > 5.0


def test_blind_nadir_is_walkable_only_when_asked():
    # A real capture's blind spot: no depth within 45 degrees of straight down (floor within 1.5 m unseen).
    d = erp_depth(box_room(), 128)
    d[-32:] = np.nan
    em = erp_mesh_from_depth(d, np.zeros(d.shape + (3,), np.uint8))
    strict = build_navmesh(em.vertices, em.faces, em.face_valid)
    assert not strict.info["camera_on_navmesh"] and not strict.contains(np.zeros((1, 2)))[0]
    trusting = build_navmesh(em.vertices, em.faces, em.face_valid, params=NavMeshParams(camera_footprint_m=1.6))
    assert trusting.info["camera_on_navmesh"] and trusting.area > strict.area
    # The obstacle box at (1.2, 0.8) lies within the footprint but stays out.
    assert not trusting.contains(np.array([[1.2, 0.8], [0.9, 0.6]])).any()


def test_downsampled_erp_mesh_gives_the_same_navmesh(room):
    gt, nav = room  # built from a 192-row mesh (no downsampling)
    em = erp_mesh_of(gt, 384)
    assert erp_grid_shape(em.vertices) == (384, 768)
    nav2 = build_navmesh(em.vertices, em.faces, em.face_valid)
    assert nav2.info["erp_downsample"] == 2
    assert abs(nav2.area - nav.area) < 0.05 * nav.area
    assert erp_grid_shape(np.asarray(gt.vertices)) is None


def test_save_load_round_trip(room, tmp_path):
    _, nav = room
    names = nav.save(tmp_path)
    assert names == ["navmesh.json", "navmesh.obj", "navmesh.glb"]
    back = load_navmesh(tmp_path)
    assert np.array_equal(back.vertices, nav.vertices) and np.array_equal(back.triangles, nav.triangles)
    assert np.array_equal(back.adjacency, nav.adjacency) and back.floor_y == nav.floor_y
    assert np.isclose(back.area, nav.area)
    obj = trimesh.load(tmp_path / "navmesh.obj", process=False)
    assert np.allclose(obj.vertices[:, 1], nav.floor_y) and np.isclose(obj.area, nav.area)
    assert (obj.face_normals[:, 1] < -0.99).all()  # faces point up (-Y)
    d = json.loads((tmp_path / "navmesh.json").read_text())
    assert d["polygons"][0]["outer"] and {"agent_radius_m", "step_height_m"} <= set(d["agent"])
    with pytest.raises(ValueError, match="not a readable NavMesh"):
        (tmp_path / "bad.json").write_text("{}")
        load_navmesh(tmp_path / "bad.json")


def _make_mesh_artifact(root, depth):
    from PIL import Image

    from panoworld.framework.stage import execute_stage, load_stage
    from panoworld.framework.stage_params import params_from_dict

    np.save(root / "depth.npy", depth)
    Image.fromarray(np.full(depth.shape + (3,), 128, np.uint8)).save(root / "panorama.png")
    dspec, mspec = load_stage("depth"), load_stage("mesh")
    execute_stage(dspec, {"panorama": root / "panorama.png", "depth": root / "depth.npy"},
                  params_from_dict(dspec.params_cls, {}), root / "depth")
    execute_stage(mspec, {"depth": root / "depth"}, params_from_dict(mspec.params_cls, {}), root / "mesh")
    return root / "mesh"


def test_stage_writes_navmesh_and_a_stationary_one_without_floor(tmp_path):
    from stages import navmesh as stage

    mesh_dir = _make_mesh_artifact(tmp_path, erp_depth(box_room(), 64))
    assert stage.main(["--mesh", str(mesh_dir), "--out", str(tmp_path / "nav"), "--cell-m", "0.05"]) == 0
    manifest = json.loads((tmp_path / "nav" / "manifest.json").read_text())
    assert set(manifest["files"]) == {"navmesh.json", "navmesh.obj", "navmesh.glb"}
    assert manifest["info"]["camera_on_navmesh"] and abs(manifest["info"]["floor_y"] - CAM_H) < 0.02

    d = erp_depth(box_room(), 64)
    d[34:] = np.nan  # no floor pixels
    bad = tmp_path / "bad"
    bad.mkdir()
    bad_mesh = _make_mesh_artifact(bad, d)
    # No floor is no room to move (issue #24): a stationary NavMesh at the camera, the reason in the manifest.
    assert stage.main(["--mesh", str(bad_mesh), "--out", str(tmp_path / "nav_bad")]) == 0
    info = json.loads((tmp_path / "nav_bad" / "manifest.json").read_text())["info"]
    assert info["no_room"]["decision"] == "stationary" and "no walkable floor" in info["no_room"]["reason"]
    assert info["camera_on_navmesh"] and info["area_m2"] < 0.01


def test_a_floor_hundreds_of_metres_wide_is_refused_before_its_grid_is_allocated():
    # Two floor patches 300 m apart in x and z (capture points of no one home): one line naming the extent, no 200M-cell grid.
    from dataclasses import replace

    from panoworld.core.errors import InputError
    from panoworld.navmesh import NavMeshParams, floor_grid

    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], float)
    vertices = np.concatenate([quad, quad + [300.0, 0, 300.0]]) + [0, 1.5, 0]
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    params = replace(NavMeshParams(), max_range_m=1000.0, max_erp_height=0)  # as a home sets it
    with pytest.raises(InputError, match=r"the walkable floor spans 301 m x 301 m: a NavMesh grid of .* over the limit"):
        floor_grid(vertices, faces, np.ones(4, bool), 1.5, params=params)


def test_a_camera_off_the_floor_snaps_to_a_floor_piece_not_to_a_sliver_beside_it():
    from panoworld.geometry.polygons import cross_section, pick_components

    def square(x0, z0, side):
        return np.array([[x0, z0], [x0 + side, z0], [x0 + side, z0 + side], [x0, z0 + side]], np.float64)

    sliver, room = square(0.1, -0.05, 0.1), square(0.5, -1.0, 2.0)  # 0.01 m^2 at 0.1 m, 4 m^2 at 0.5 m
    cs = cross_section([sliver, room])
    rings, inside, dist = pick_components(cs, np.array([[0.0, 0.0]]), snap_m=1.0, min_area_m2=0.25)
    assert len(rings) == 1 and np.allclose(rings[0].min(0), [0.5, -1.0]) and not inside[0]
    assert abs(dist[0] - 0.5) < 1e-9
    rings = pick_components(cs, np.array([[0.0, 0.0]]), snap_m=0.3, min_area_m2=0.25)[0]  # the room out of reach
    assert len(rings) == 1 and np.allclose(rings[0].min(0), [0.1, -0.05])
    rings = pick_components(cs, np.array([[0.0, 0.0]]), snap_m=1.0)[0]  # no least area: the nearest
    assert len(rings) == 1 and np.allclose(rings[0].min(0), [0.1, -0.05])
