"""ErpRasterizer against the Embree oracle: seam, poles, near and tiny triangles, closed rooms, ERP grid meshes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from panoworld.core.conventions import erp_dirs, pose_from_rt, rotmat_from_quat_wxyz
from panoworld.geometry.erp_mesh import erp_mesh_from_depth
from panoworld.render.rasterize import ErpRasterizer, RaycastRenderer, shade_hits


def compare(vertices, faces, pose, h, w, *, colors=None, face_valid=None, min_agree=0.999):
    """Render with both backends; assert coverage, depth and barycentrics agree; return both Hits."""
    fast = ErpRasterizer(vertices, faces, colors, face_valid)
    ref = RaycastRenderer(vertices, faces, colors, face_valid)
    a = fast.render_erp(pose, h, w)
    b = ref.render_erp(pose, h, w)
    hit_a, hit_b = a.face >= 0, b.face >= 0
    agree = (hit_a == hit_b).mean()
    assert agree >= min_agree, f"coverage agrees on {agree:.5f} of pixels"
    both = hit_a & hit_b
    rel = np.abs(a.distance[both] - b.distance[both]) / b.distance[both]
    # Where both hit, the depth is the same surface (different faces only at shared edges or exact ties).
    assert (rel <= 1e-4).mean() >= 0.999, f"depth differs: {np.sort(rel)[-5:]}"
    same = both & (a.face == b.face)
    assert same.sum() >= 0.98 * both.sum()
    assert np.abs(a.bary[same] - b.bary[same]).max() < 1e-3
    np.testing.assert_allclose(a.bary[hit_a].sum(-1), 1.0, atol=1e-5)
    assert np.isinf(a.distance[~hit_a]).all() and (a.bary[~hit_a] == 0).all()
    return a, b


def random_pose(rng, shift=0.3):
    q = rng.normal(size=4)
    return pose_from_rt(rotmat_from_quat_wxyz(q / np.linalg.norm(q)), rng.uniform(-shift, shift, 3))


def soup(rng, n, dist, size):
    """n random triangles at distance ~dist from the origin with edge length ~size."""
    centres = rng.normal(size=(n, 3))
    centres *= dist / np.linalg.norm(centres, axis=1, keepdims=True)
    tris = centres[:, None, :] + rng.normal(size=(n, 3, 3)) * size
    return tris.reshape(-1, 3).astype(np.float32), np.arange(3 * n).reshape(n, 3)


def test_random_soup_matches_embree():
    rng = np.random.default_rng(0)
    for _ in range(4):
        v, f = soup(rng, 300, dist=2.0, size=rng.choice([0.01, 0.1, 0.6]))
        compare(v, f, random_pose(rng), 48, 96)


def test_seam_straddling_triangles():
    # Thin and wide triangles behind the camera (lon = +-pi at the image's left/right border) and along the seam.
    rng = np.random.default_rng(1)
    tris = []
    for _ in range(200):
        z = -rng.uniform(0.5, 5.0)
        x0 = rng.uniform(-0.5, 0.0) * abs(z)
        x1 = rng.uniform(0.0, 0.5) * abs(z)
        y = rng.uniform(-2, 2, 3)
        tris.append([[x0, y[0], z], [x1, y[1], z * rng.uniform(0.8, 1.2)], [rng.uniform(x0, x1), y[2], z]])
    v = np.asarray(tris, np.float32).reshape(-1, 3)
    a, _ = compare(v, np.arange(len(v)).reshape(-1, 3), np.eye(4), 64, 128)
    assert (a.face[:, 0] >= 0).any() and (a.face[:, -1] >= 0).any()


def test_pole_enclosing_triangles():
    # One triangle around the north pole (up = -y) and one around the south pole.
    v = np.array([[-1.0, -1.0, -1.0], [1.5, -1.2, -0.5], [0.0, -0.8, 1.3],
                  [0.2, 1.0, 0.3], [-0.4, 1.1, 0.1], [0.1, 0.9, -0.5]], np.float32)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    for h in (32, 64, 90):
        a, _ = compare(v, f, np.eye(4), h, 2 * h)
        assert a.face[0].min() >= 0 and a.face[-1].min() >= 0  # first and last rows fully covered
    rng = np.random.default_rng(2)
    for _ in range(3):
        compare(v, f, random_pose(rng, 0.2), 64, 128)


@pytest.mark.parametrize("offset", [0.0, 1e-6, 3e-4])
def test_pole_fans(offset):
    # ERP meshes close their poles with fans whose apex is on the pole axis; a hair off it (offset radians) the
    # apex's longitude is numerically meaningless, yet the fan must stay watertight.
    n = 24
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.1
    verts, faces = [], []
    for height in (-2.0, 1.5):
        ring = np.stack([np.sin(ang) * 0.3, np.full(n, height), np.cos(ang) * 0.3], 1)
        base = sum(len(x) for x in verts)
        verts += [np.array([[offset * abs(height), height, 0.5 * offset * abs(height)]]), ring]
        faces += [[base, base + 1 + k, base + 1 + (k + 1) % n] for k in range(n)]
    v, f = np.concatenate(verts).astype(np.float32), np.asarray(faces)
    for h in (32, 64):
        a, _ = compare(v, f, np.eye(4), h, 2 * h, min_agree=1.0)
        assert (a.face[:2] >= 0).all() and (a.face[-2:] >= 0).all()


def test_near_and_tiny_triangles():
    rng = np.random.default_rng(3)
    near_v, near_f = soup(rng, 40, dist=0.02, size=0.02)  # a few cm from the camera, spanning large angles
    tiny_v, tiny_f = soup(rng, 4000, dist=3.0, size=2e-3)  # well below a pixel at 64 x 128
    v = np.concatenate([near_v, tiny_v])
    f = np.concatenate([near_f, tiny_f + len(near_v)])
    compare(v, f, np.eye(4), 64, 128)
    compare(tiny_v, tiny_f, np.eye(4), 256, 512)


def test_thin_faces_seen_edge_on_through_the_camera():
    # Long slivers whose planes pass ~1 cm from the camera: each row meets them in short pieces half a panorama
    # apart (the rasteriser keeps the pieces apart rather than scanning between them); every covered pixel is found.
    rng = np.random.default_rng(5)
    tris = []
    for _ in range(60):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        n = np.cross(u, rng.normal(size=3))
        n /= np.linalg.norm(n)
        w = np.cross(n, u)
        a, b = rng.uniform(1.0, 3.0, 2)
        tris.append([-a * u + 0.01 * n, b * u + 0.01 * n, rng.uniform(0.05, 0.3) * w + rng.uniform(-1, 1) * u])
    v = np.asarray(tris, np.float32).reshape(-1, 3)
    f = np.arange(len(v)).reshape(-1, 3)
    a, b = compare(v, f, np.eye(4), 90, 180)
    assert (a.face >= 0).sum() > 500


def test_camera_inside_closed_box_covers_every_pixel():
    box = trimesh.creation.box(extents=[4.0, 2.5, 3.0])
    rng = np.random.default_rng(4)
    for _ in range(3):
        a, b = compare(box.vertices, box.faces, random_pose(rng, 0.5), 50, 100, min_agree=1.0)
        assert (a.face >= 0).all() and (b.face >= 0).all()


def _grid_mesh(rng, h, w):
    box = trimesh.creation.box(extents=[5.0, 2.8, 6.0])
    spheres = [trimesh.creation.icosphere(2, 0.35).apply_translation(rng.uniform(-1.5, 1.5, 3) * [1, 0.4, 1])
               for _ in range(4)]
    scene = trimesh.util.concatenate([box] + spheres)
    depth = RaycastRenderer(scene.vertices, scene.faces).render_erp(np.eye(4), h, w).distance
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    return erp_mesh_from_depth(depth, rgb)


def test_erp_grid_mesh_shaded_matches_reference():
    rng = np.random.default_rng(5)
    mesh = _grid_mesh(rng, 64, 128)
    assert not mesh.face_valid.all()  # has stretched occluder faces
    fast = ErpRasterizer(mesh.vertices, mesh.faces, mesh.colors, mesh.face_valid)
    ref = RaycastRenderer(mesh.vertices, mesh.faces, mesh.colors, mesh.face_valid)
    for pose in [np.eye(4), pose_from_rt(np.eye(3), [0.4, 0.1, -0.3]), random_pose(rng, 0.3)]:
        compare(mesh.vertices, mesh.faces, pose, 96, 192)
        a, b = fast.render(pose, 96, 192), ref.render(pose, 96, 192)
        assert (a.mask == b.mask).mean() >= 0.999
        both = a.mask & b.mask
        assert np.abs(a.rgb[both].astype(int) - b.rgb[both]).max() <= 2 or (
            np.abs(a.rgb[both].astype(int) - b.rgb[both]).max(-1) > 2).mean() < 1e-3
        np.testing.assert_allclose(a.depth[both], b.depth[both], rtol=1e-4)
        assert (a.rgb[~a.mask] == 0).all() and (a.depth[~a.mask] == 0).all()
        # The fused shading equals the numpy reference shading of the rasteriser's own hits.
        s = shade_hits(fast.render_erp(pose, 96, 192), fast.faces, fast.colors, fast.face_valid)
        np.testing.assert_array_equal(s.mask, a.mask)
        assert np.abs(s.rgb.astype(int) - a.rgb).max() <= 1
    # At the source pose the warp reproduces the source panorama where it is valid.
    src = fast.render(np.eye(4), 64, 128)
    assert src.mask.mean() > 0.95


def test_identity_warp_reproduces_depth():
    h, w = 48, 96
    depth = 2.0 + np.sin(erp_dirs(h, w)[..., 0] * 3).astype(np.float32)
    mesh = erp_mesh_from_depth(depth, np.zeros((h, w, 3), np.uint8))
    a = ErpRasterizer(mesh.vertices, mesh.faces).render_erp(np.eye(4), h, w)
    inner = np.s_[1:-1]  # the pole rows are covered by the pole fans, not the grid
    np.testing.assert_allclose(a.distance[inner], depth[inner], rtol=1e-5)


def test_thread_count_does_not_change_the_result():
    rng = np.random.default_rng(6)
    v, f = soup(rng, 3000, dist=2.0, size=0.05)
    pose = random_pose(rng)
    a = ErpRasterizer(v, f, num_threads=1).render_erp(pose, 64, 128)
    b = ErpRasterizer(v, f).render_erp(pose, 64, 128)
    np.testing.assert_array_equal(a.face, b.face)
    np.testing.assert_array_equal(a.distance, b.distance)


def test_occlusion_culling_changes_nothing():
    # Three rooms side by side (ERP grid meshes of closed boxes) plus loose triangles: the culled rasteriser skips the
    # clusters behind the walls and returns the same buffers as the unculled one, pose after pose along a walk
    # through the rooms (the clusters the previous pose showed go first), at the seam and near the poles too.
    rng = np.random.default_rng(8)
    parts, verts, n = [], [], 0
    for k in range(3):
        m = _grid_mesh(rng, 48, 96)
        verts.append(m.vertices + np.float32([4.0 * k, 0.0, 0.0]))
        parts.append((m.faces + n, m.colors, m.face_valid))
        n += len(m.vertices)
    sv, sf = soup(rng, 400, dist=1.0, size=0.05)
    verts.append(sv + np.float32([4.0, 0.0, 0.0]))
    parts.append((sf + n, np.full((len(sv), 3), 200, np.uint8), np.ones(len(sf), bool)))
    v = np.concatenate(verts)
    f = np.concatenate([p_[0] for p_ in parts])
    c = np.concatenate([p_[1] for p_ in parts])
    ok = np.concatenate([p_[2] for p_ in parts])
    culled = ErpRasterizer(v, f, c, ok, cull_cluster=32, cull_min_faces=0)
    plain = ErpRasterizer(v, f, c, ok, cull_cluster=0)
    assert culled._clusters is not None and plain._clusters is None
    assert ErpRasterizer(v, f, c, ok, cull_cluster=32, cull_min_faces=len(f) + 1)._clusters is None
    skipped = []
    for x in np.linspace(-0.5, 8.5, 12):
        pose = pose_from_rt(rotmat_from_quat_wxyz(rng.normal(size=4) * [4, 0.3, 1, 0.3]), [x, rng.uniform(-0.2, 0.2), 0.1])
        for h in (32, 64):
            a, b = culled.render(pose, h, 2 * h), plain.render(pose, h, 2 * h)
            np.testing.assert_array_equal(a.rgb, b.rgb)
            np.testing.assert_array_equal(a.depth, b.depth)
            np.testing.assert_array_equal(a.mask, b.mask)
            skipped.append(1.0 - culled.rasterised / len(culled._seen))
        ha, hb = culled.render_erp(pose, 48, 96), plain.render_erp(pose, 48, 96)
        np.testing.assert_array_equal(ha.face, hb.face)
        np.testing.assert_array_equal(ha.distance, hb.distance)
        np.testing.assert_array_equal(ha.bary, hb.bary)
    assert np.mean(skipped) > 0.3  # many clusters lie in the other rooms


def test_bad_inputs_raise_clear_errors():
    v, f = soup(np.random.default_rng(7), 10, 2.0, 0.3)
    r = ErpRasterizer(v, f)
    with pytest.raises(ValueError, match="2:1"):
        r.render(np.eye(4), 64, 100)
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        r.render(np.eye(3), 64, 128)
    with pytest.raises(ValueError, match=r"\(F, 3\)"):
        ErpRasterizer(v, f[:, :2])
    with pytest.raises(ValueError, match="index vertices"):
        ErpRasterizer(v, f + 100)
    with pytest.raises(ValueError, match=rf"colors.shape=\(3, 3\) but expected \({len(v)}, 3\)"):  # V bound by vertices
        ErpRasterizer(v, f, colors=np.zeros((3, 3), np.uint8))
