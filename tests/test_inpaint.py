"""warp-inpaint: background layer geometry, temporal consistency against the per-frame baseline, seam awareness."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from panoworld.conditions.warp import render_conditions
from panoworld.core.conventions import erp_dirs, points_from_depth
from panoworld.geometry.erp_mesh import erp_mesh_from_depth
from panoworld.geometry.raycast import Raycaster
from panoworld.render.metrics import psnr, reprojection_error
from panoworld.video.background_layer import BackgroundLayer, build_background_layer, floor_ceiling, layer_mean_color
from panoworld.video.erp_fill import erp_gaussian_blur, erp_inpaint, erp_pad
from panoworld.video.inpaint import (
    FOREGROUND_RATIO,
    CommittedPoints,
    WarpInpainter,
    _max_distance,
    background_fill,
    erp_dir_at,
    frame_inpaint,
    max_translation,
    warp_inpaint_video,
)

H, W = 96, 192


def texture(points: np.ndarray) -> np.ndarray:
    """Smooth procedural colour of world points (..., 3) -> (..., 3) uint8: the same surface point, the same colour."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    rgb = np.stack([np.sin(3 * x + 1.3 * z), np.sin(4 * y + 2 * x), np.cos(2.5 * z - 3 * y)], axis=-1)
    return np.clip(np.rint(128 + 100 * rgb), 0, 255).astype(np.uint8)


class BoxScene:
    """A room (x in [-3, 3], floor at y = 1.2, z in [-3, 4]) with a thin panel standing 1.5 m in front of the source camera (no side faces to uncover)."""

    def __init__(self):
        room = trimesh.creation.box(bounds=[[-3.0, -1.6, -3.0], [3.0, 1.2, 4.0]])
        box = trimesh.creation.box(bounds=[[-0.35, -0.4, 1.5], [0.35, 1.2, 1.53]])
        scene = trimesh.util.concatenate([room, box])
        self.raycaster = Raycaster(scene.vertices, scene.faces)

    def render(self, world_from_cam: np.ndarray, height: int = H, width: int = W) -> tuple[np.ndarray, np.ndarray]:
        hits = self.raycaster.render_erp(world_from_cam, height, width)
        pts = points_from_depth(hits.distance.astype(np.float64), world_from_cam)
        return texture(pts), hits.distance.astype(np.float32)


def sideways_poses(n: int, total: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.linspace(0.0, total, n)
    poses[:, 2, 3] = np.linspace(0.0, 0.3 * total, n)
    return poses


@pytest.fixture(scope="module")
def box_case():
    scene = BoxScene()
    rgb0, d0 = scene.render(np.eye(4))
    mesh = erp_mesh_from_depth(d0, rgb0)
    poses = sideways_poses(6, 0.6)
    cond = render_conditions(mesh, poses, H, W, backend="raycast")
    gt = [scene.render(T) for T in poses]
    return scene, mesh, poses, cond, gt


def test_erp_pad_wraps_columns_and_mirrors_poles():
    img = np.arange(4 * 8).reshape(4, 8)
    p = erp_pad(img, 2, 1)
    assert p.shape == (6, 12)
    np.testing.assert_array_equal(p[1:5, :2], img[:, 6:])
    np.testing.assert_array_equal(p[1:5, -2:], img[:, :2])
    # Above the top row lies the top row itself, half a turn of longitude away.
    np.testing.assert_array_equal(p[0, 2:10], np.roll(img[0], 4))
    with pytest.raises(ValueError, match="cannot pad"):
        erp_pad(img, 9)


def test_erp_inpaint_is_continuous_across_the_seam():
    # A smooth colour of the viewing direction (continuous over the sphere); the hole straddles the left/right border.
    img = texture(erp_dirs(H, W, np.float64) * 1.5)
    mask = np.zeros((H, W), bool)
    mask[:, :5] = mask[:, -5:] = True
    holed = np.where(mask[..., None], 0, img).astype(np.uint8)
    out = erp_inpaint(holed, mask)
    np.testing.assert_array_equal(out[~mask], img[~mask])
    # Seam-aware = equivariant to a rotation in longitude: filling the hole at the image centre gives the same.
    rolled = erp_inpaint(np.roll(holed, W // 2, axis=1), np.roll(mask, W // 2, axis=1))
    assert np.abs(np.roll(rolled, -W // 2, axis=1).astype(int) - out.astype(int)).max() <= 1
    naive = cv2.inpaint(holed, mask.astype(np.uint8), 3.0, cv2.INPAINT_TELEA)
    assert np.abs(naive.astype(int) - out.astype(int)).max() > 20  # without wrapping each side is filled alone


def test_erp_inpaint_float_and_errors():
    d = np.linspace(1.0, 3.0, W, dtype=np.float32)[None].repeat(H, 0)
    mask = np.zeros((H, W), bool)
    mask[20:30, 50:60] = True
    out = erp_inpaint(np.where(mask, 0, d).astype(np.float32), mask)
    assert out.dtype == np.float32
    assert np.abs(out - d)[mask].max() < 0.1  # OpenCV's own float Telea is garbage: quantised to 16 bits here
    with pytest.raises(ValueError, match="mask.shape"):
        erp_inpaint(d, mask[:10])
    with pytest.raises(ValueError, match="whole image"):
        erp_inpaint(d, np.ones((H, W), bool))


def test_background_layer_lies_on_the_hidden_wall(box_case):
    scene, mesh, poses, _, _ = box_case
    layer = build_background_layer(mesh, max_translation(poses))
    assert layer.layer_faces > 0 and layer.synthesized.any()
    # Every synthesized pixel is a box pixel of the source view, and its layer depth is behind the box.
    _, d0 = scene.render(np.eye(4))
    box_pixels = d0 < 2.6
    assert box_pixels[layer.synthesized].all()
    assert (layer.layer_depth[layer.synthesized] > d0[layer.synthesized] * 1.02).all()
    # The true surface behind the box (the scene without the box) is the far wall / floor.
    room = trimesh.creation.box(bounds=[[-3.0, -1.6, -3.0], [3.0, 1.2, 4.0]])
    behind = Raycaster(room.vertices, room.faces).render_erp(np.eye(4), H, W).distance
    rel = np.abs(layer.layer_depth - behind)[layer.synthesized] / behind[layer.synthesized]
    assert np.median(rel) < 0.05


@pytest.mark.parametrize("side_depth_m", [0.0, 0.5])
def test_background_layer_with_its_ray_caster_is_the_same_layer(box_case, side_depth_m):
    _, mesh, poses, cond, _ = box_case
    plain = build_background_layer(mesh, max_translation(poses), side_depth_m=side_depth_m)
    layer = build_background_layer(mesh, max_translation(poses), side_depth_m=side_depth_m, ray_caster=True)
    assert plain.built is None and layer.built is not None and layer.built._scene.is_committed
    for name in ("vertices", "faces", "colors", "synthesized", "layer_depth"):
        np.testing.assert_array_equal(getattr(layer, name), getattr(plain, name))
    assert layer.layer_faces == plain.layer_faces
    a = WarpInpainter(plain).fill(cond[-1].rgb, cond[-1].mask, cond[-1].depth, poses[-1])
    b = WarpInpainter(layer).fill(cond[-1].rgb, cond[-1].mask, cond[-1].depth, poses[-1])
    assert a.filled_3d.any()
    for name in ("rgb", "depth", "filled_3d", "filled_2d"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_warp_inpaint_is_temporally_consistent_and_fills_in_3d(box_case):
    _, mesh, poses, cond, gt = box_case
    rgb = np.stack([c.rgb for c in cond])
    mask = np.stack([c.mask for c in cond])
    depth = np.stack([c.depth for c in cond])
    assert (~mask[1:]).mean() > 0.005  # the box uncovers the wall behind it
    warp, _ = warp_inpaint_video(rgb, mask, depth, poses, mesh, progress=False)
    base = [frame_inpaint(rgb[t], mask[t], depth[t]) for t in range(len(rgb))]
    holes = sum(int((~m).sum()) for m in mask)
    assert sum(int(f.filled_3d.sum()) for f in warp) > 0.9 * holes
    for f, m, c in zip(warp, mask, cond):
        np.testing.assert_array_equal(f.rgb[m], c.rgb[m])  # valid condition pixels are kept as they are
        assert (f.depth[f.filled_3d] > 0).all()

    def temporal(frames):
        errs = []
        for t in range(len(frames) - 1):
            err, ok = reprojection_error(frames[t].rgb, frames[t + 1].rgb, gt[t][1], gt[t + 1][1], poses[t],
                                         poses[t + 1], mask_t=~mask[t])
            errs.append(err[ok & ~mask[t + 1]])  # filled in both frames
        e = np.concatenate(errs)
        assert len(e) > 50
        return float(np.sqrt((e**2).mean()))

    warp_err, base_err = temporal(warp), temporal(base)
    assert warp_err < 0.5 * base_err, (warp_err, base_err)
    # Fidelity on the disoccluded pixels is no worse than the per-frame fill.
    p_warp = np.mean([psnr(f.rgb, g[0], ~m) for f, g, m in zip(warp[1:], gt[1:], mask[1:])])
    p_base = np.mean([psnr(f.rgb, g[0], ~m) for f, g, m in zip(base[1:], gt[1:], mask[1:])])
    assert p_warp > p_base - 0.5, (p_warp, p_base)


def test_no_motion_means_no_layer(box_case):
    _, mesh, _, _, _ = box_case
    layer = build_background_layer(mesh, 0.0)
    assert layer.layer_faces == 0 and not layer.synthesized.any()
    assert len(layer.faces) == int(mesh.face_valid.sum())


def test_shape_errors(box_case):
    _, mesh, poses, cond, _ = box_case
    with pytest.raises(ValueError, match="expected .T, H, W, 3."):
        warp_inpaint_video(cond[0].rgb, cond[0].mask, None, poses, mesh)
    with pytest.raises(ValueError, match="mask.shape"):
        frame_inpaint(cond[0].rgb, cond[0].mask[:10])
    with pytest.raises(ValueError, match="N, 4, 4"):
        max_translation(np.eye(4))


def test_warp_inpaint_across_the_seam_equals_the_centred_case(box_case):
    """Turn the source camera by 180 degrees: the panel now straddles the left/right border, and every filled frame
    must be the unturned one shifted by W/2 columns."""
    scene, mesh, poses, cond, _ = box_case
    world_from_src = np.diag([-1.0, 1.0, -1.0, 1.0])  # yaw by pi
    rgb0, d0 = scene.render(world_from_src)
    mesh_t = erp_mesh_from_depth(d0, rgb0)
    poses_t = np.stack([np.linalg.inv(world_from_src) @ T @ world_from_src for T in poses])  # cameras turned too
    cond_t = render_conditions(mesh_t, poses_t, H, W, backend="raycast")
    i, j = np.nonzero(~cond_t[-1].mask)
    assert j.min() < 5 and j.max() > W - 5  # the holes sit at both borders
    stack = [np.stack([getattr(c, k) for c in cs]) for cs in (cond, cond_t) for k in ("rgb", "mask", "depth")]
    warp, _ = warp_inpaint_video(*stack[:3], poses, mesh, progress=False)
    warp_t, _ = warp_inpaint_video(*stack[3:], poses_t, mesh_t, progress=False)
    for a, b, m in zip(warp, warp_t, stack[1]):
        diff = np.abs(np.roll(b.rgb, W // 2, axis=1).astype(int) - a.rgb.astype(int)).max(axis=-1)
        assert np.mean(diff[~m] <= 2) > 0.99


def _panel_frame():
    """A blue wall at 3 m with a red panel at 1 m (columns 40-59) and a hole right of the panel (columns 60-74)."""
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 2] = 200
    depth = np.full((H, W), 3.0, np.float32)
    rgb[20:70, 40:60] = (220, 30, 30)
    depth[20:70, 40:60] = 1.0
    hole = np.zeros((H, W), bool)
    hole[25:65, 60:75] = True
    return rgb, depth, hole


def test_background_fill_continues_the_far_side_not_the_occluder():
    rgb, depth, hole = _panel_frame()
    out, out_d = background_fill(rgb, np.where(hole, 0, depth), hole)
    np.testing.assert_allclose(out_d[hole], 3.0)
    np.testing.assert_array_equal(out[~hole], rgb[~hole])
    plain = erp_inpaint(rgb, hole)
    red = lambda img: img[hole][:, 0].astype(float).mean()
    assert red(out) < 10 < red(plain)  # the plain fill smears the panel's red into the wall


def test_background_fill_of_a_band_of_rows_equals_that_of_the_whole_frame():
    # Holes away from the poles are filled on the band of rows around them; a second, tiny hole at the pole (far from
    # the first) makes the same call fill the whole frame: the first hole's fill is the same, bit for bit.
    rng = np.random.default_rng(0)
    h, w = 192, 384
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)  # texture: a nearest-rim pixel chosen differently shows
    depth = (3.0 + 0.5 * rng.random((h, w))).astype(np.float32)
    depth[70:120, 100:130] = 1.0  # an occluder with a hole on its right
    hole = np.zeros((h, w), bool)
    hole[75:115, 130:142] = True
    polar = hole.copy()
    polar[1, 320:322] = True
    band = background_fill(rgb, np.where(hole, 0, depth), hole)
    whole = background_fill(rgb, np.where(polar, 0, depth), polar)
    for a, b in zip(band, whole):
        np.testing.assert_array_equal(a[hole], b[hole])
    np.testing.assert_allclose(band[1][hole], depth[75:115, 142:143].mean(), rtol=0.2)  # the far side's depth


def _background_fill_reference(rgb, depth, hole, *, radius=3.0, max_window=129):
    """background_fill as first written (scipy's transforms and dilation, whole-band arrays): the oracle of the
    faster one, which must match it bit for bit."""
    from scipy import ndimage

    H, W = hole.shape
    rows = np.flatnonzero(hole.any(axis=1))
    r0, r1 = max(int(rows[0]) - 1, 0), min(int(rows[-1]) + 1, H - 1)
    thick = float(ndimage.distance_transform_edt(hole[r0:r1 + 1]).max())
    window = int(min(4 * thick + 3, max_window))
    sigma = max(radius, 1.0)
    pad_y = int(np.ceil(3 * sigma)) + 1
    reach = max(window // 2, int(np.ceil(4 * sigma))) + 2
    a, b = r0 - reach - pad_y, r1 + reach + pad_y
    polar = a < 0 or b > H - 1 or W % 2
    a, b = (0, H - 1) if polar else (a + pad_y, b - pad_y)
    ring = ndimage.binary_dilation(hole[a:b + 1], structure=np.ones((3, 3))) & ~hole[a:b + 1] & (depth[a:b + 1] > 0)
    out_rgb, out_d = rgb.copy(), np.asarray(depth, np.float32).copy()
    rgb, depth, hole = rgb[a:b + 1], depth[a:b + 1], hole[a:b + 1]
    far = ndimage.maximum_filter(np.where(ring, depth, 0.0), size=window, mode="wrap")
    bg_rim = ring & (depth >= FOREGROUND_RATIO * far)
    pad = W // 4
    padded = np.concatenate([~bg_rim[:, -pad:], ~bg_rim, ~bg_rim[:, :pad]], axis=1)
    _, (ii, jj) = ndimage.distance_transform_edt(padded, return_indices=True)
    ii, jj = ii[:, pad:pad + W], (jj[:, pad:pad + W] - pad) % W
    fill_d = np.where(hole, depth[ii, jj], depth).astype(np.float32)
    known = (hole | bg_rim).astype(np.float32)
    col = np.where(hole[..., None], rgb[ii, jj], rgb).astype(np.float32) * known[..., None]
    num, den = (erp_gaussian_blur(x, sigma, across_poles=polar) for x in (col, known))
    smooth = num / np.maximum(den, 1e-6)[..., None]
    out_rgb[a:b + 1] = np.where(hole[..., None], np.clip(np.rint(smooth), 0, 255).astype(np.uint8), rgb)
    out_d[a:b + 1] = fill_d
    return out_rgb, out_d


@pytest.mark.parametrize("seed", range(6))
def test_background_fill_equals_its_scipy_reference(seed):
    # Textured frames with occluders and holes of every size: thin slivers, wide holes (the window at max_window),
    # holes at a pole (the whole frame) and across the seam; the fill must be the reference's, bit for bit.
    rng = np.random.default_rng(seed)
    h, w = 120, 240
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    depth = (3.0 + rng.random((h, w))).astype(np.float32)
    hole = np.zeros((h, w), bool)
    for _ in range(rng.integers(1, 6)):
        i, j = rng.integers(0, h), rng.integers(0, w)
        hh, ww = rng.integers(1, 3 if seed % 3 == 0 else 70, size=2)
        occ = (slice(max(i - 5, 0), min(i + hh + 5, h)), slice(max(j - 30, 0), j))
        depth[occ] = rng.uniform(0.8, 2.0)
        hole[i:i + hh, j:j + ww] = True
        hole[i:i + hh, :max(j + ww - w, 0)] = True  # across the seam
    if seed == 4:  # 70 x 70 across the seam: the window at max_window
        depth[35:115, w - 40:w - 20] = 1.0
        hole[40:110, w - 20:] = hole[40:110, :50] = True
    if seed == 5:
        hole[0, 10:20] = True
    out = background_fill(rgb, np.where(hole, 0, depth), hole)
    ref = _background_fill_reference(rgb, np.where(hole, 0, depth), hole)
    for a, b in zip(out, ref):
        np.testing.assert_array_equal(a, b)


def test_warp_inpainter_ray_tables_equal_erp_dir_at(box_case):
    _, mesh, poses, _, _ = box_case
    filler = WarpInpainter(build_background_layer(mesh, max_translation(poses)))
    rng = np.random.default_rng(0)
    ti, tj = rng.integers(0, H, 5000), rng.integers(0, W, 5000)
    for du, dv in ((0.0, 0.0), (0.25, -0.25), (-0.25, 0.25)):
        np.testing.assert_array_equal(filler._dirs_at(ti, tj, H, W, du, dv), erp_dir_at(tj + 0.5 + du, ti + 0.5 + dv, H, W))


def _stretch_reference(p, faces):
    """background_layer._stretch in numpy, as first written: the oracle of its numba kernel."""
    depth = np.linalg.norm(p, axis=1)
    dirs = p / np.maximum(depth, 1e-12)[:, None]
    out = np.zeros(len(faces), np.float32)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        va, vb = faces[:, a], faces[:, b]
        length = np.linalg.norm(p[va] - p[vb], axis=1)
        chord = np.linalg.norm(dirs[va] - dirs[vb], axis=1)
        np.maximum(out, length / np.maximum(np.minimum(depth[va], depth[vb]) * chord, 1e-12), out=out)
    return out


def test_stretch_equals_its_numpy_reference(box_case):
    from panoworld.geometry.erp_mesh import grid_faces
    from panoworld.video.background_layer import _stretch, erp_grid_shape

    _, mesh, _, _, _ = box_case
    h, w = erp_grid_shape(mesh)
    p = mesh.vertices[:h * w].astype(np.float64)
    faces = grid_faces(h, w)
    rng = np.random.default_rng(0)
    q = rng.standard_normal((500, 3)) * 10.0 ** rng.uniform(-3, 2, (500, 1))
    q[:5] = 0.0  # points at the camera: zero depth and direction
    for pts, f in ((p, faces), (p, faces.astype(np.int32)), (q, rng.integers(0, 500, (3000, 3)))):
        np.testing.assert_array_equal(_stretch(pts, f), _stretch_reference(pts, f))


def test_raycaster_interpolate_equals_the_summed_form(box_case):
    scene, _, _, _, _ = box_case
    rc = scene.raycaster
    hits = rc.render_erp(np.eye(4), H, W)
    hits.face[::7, ::5] = -1  # misses take `fill`
    rng = np.random.default_rng(0)
    for attr in (rng.random((len(rc.vertices), 3)).astype(np.float32) * 255, rng.random((len(rc.vertices), 2)),
                 rng.integers(0, 256, (len(rc.vertices), 3), dtype=np.uint8)):
        valid = hits.face >= 0
        ref = (attr[rc.faces[np.where(valid, hits.face, 0)]] * hits.bary[..., None]).sum(axis=-2)
        np.testing.assert_array_equal(rc.interpolate(hits, attr, fill=-1.0), np.where(valid[..., None], ref, -1.0))


def test_max_distance_equals_scipys():
    from scipy import ndimage

    rng = np.random.default_rng(0)
    for _ in range(200):
        h, w = rng.integers(2, 90, size=2)
        mask = ndimage.binary_dilation(rng.random((h, w)) < rng.uniform(0.001, 0.3), iterations=int(rng.integers(0, 25)))
        if mask.any():
            assert _max_distance(mask) == float(ndimage.distance_transform_edt(mask).max())


def test_committed_points_are_reused_at_their_place():
    rgb, depth, hole = _panel_frame()
    pts = CommittedPoints()
    px = np.flatnonzero(hole)
    pts.add(np.eye(4), px, depth.reshape(-1)[px], rgb.reshape(-1, 3)[px], H, W)
    pix, dist, col = pts.project(np.eye(4), H, W)
    order = np.argsort(pix)
    np.testing.assert_array_equal(pix[order], px)
    np.testing.assert_allclose(dist[order], 3.0, rtol=1e-6)
    moved = np.eye(4)
    moved[:3, 3] = (0.2, 0.0, 0.5)
    pix, dist, _ = pts.project(moved, H, W)
    world = erp_dirs(H, W, np.float64).reshape(-1, 3)[px] * 3.0
    assert abs(np.sort(dist).mean() - np.linalg.norm(world - moved[:3, 3], axis=1).mean()) < 1e-6 + 0.05 * (len(px) - len(pix))
    # A warp-inpainter with reuse fills a hole it filled before from those points: same colours, with depth.
    empty = BackgroundLayer(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.uint8), 0,
                            np.zeros((H, W), bool), np.zeros((H, W), np.float32))
    filler = WarpInpainter(empty, reuse=True)
    first = filler.fill(rgb, ~hole, depth, np.eye(4))
    assert first.filled_2d[hole].all() and (first.depth[hole] > 2.9).all()
    second = filler.fill(rgb, ~hole, depth, np.eye(4))
    assert second.filled_3d[hole].all() and not second.filled_2d.any()
    np.testing.assert_array_equal(second.rgb, first.rgb)


def test_warp_inpainter_last_resort_fill_has_background_depth():
    # Hole pixels the layer misses get the depth-aware fill by default: the far side's depth (so the Gaussians stage
    # places them) and no occluder colour; depth_fill=False keeps the plain colour-only fill (no depth).
    rgb, depth, hole = _panel_frame()
    empty = BackgroundLayer(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.uint8), 0,
                            np.zeros((H, W), bool), np.zeros((H, W), np.float32))
    f = WarpInpainter(empty).fill(rgb, ~hole, depth, np.eye(4))
    assert f.filled_2d[hole].all()
    np.testing.assert_allclose(f.depth[hole], 3.0)
    assert f.rgb[hole][:, 0].astype(float).mean() < 10
    plain = WarpInpainter(empty, depth_fill=False).fill(rgb, ~hole, depth, np.eye(4))
    assert (plain.depth[hole] == 0).all() and plain.rgb[hole][:, 0].astype(float).mean() > 10


def test_occluder_sides_lie_on_the_hidden_side_of_a_cabinet():
    # A cabinet 0.7 m wide and 0.5 m deep, 1.5 m in front of the source: its sides (x = +-0.35, z in [1.5, 2]) are
    # hidden from the source; the side sheets start at its silhouette and go straight back.
    room = trimesh.creation.box(bounds=[[-3.0, -1.6, -3.0], [3.0, 1.2, 4.0]])
    cab = trimesh.creation.box(bounds=[[-0.35, -0.4, 1.5], [0.35, 1.2, 2.0]])
    scene = trimesh.util.concatenate([room, cab])
    d0 = Raycaster(scene.vertices, scene.faces).render_erp(np.eye(4), H, W).distance.astype(np.float32)
    pts = points_from_depth(d0.astype(np.float64), np.eye(4))
    mesh = erp_mesh_from_depth(d0, texture(pts))
    plain = build_background_layer(mesh, 0.6)
    layer = build_background_layer(mesh, 0.6, side_depth_m=0.5)
    assert len(plain.faces) < len(layer.faces) and len(layer.vertices) > len(plain.vertices)
    side = layer.vertices[len(plain.vertices):].astype(np.float64)
    on_side = (np.abs(np.abs(side[:, 0]) - 0.35) < 0.08)  # a pixel is 5 cm at 1.5 m
    on_side &= (side[:, 2] > 1.45) & (side[:, 2] < 2.05)
    assert on_side.mean() > 0.8, on_side.mean()
    assert side[on_side, 2].max() > 1.9  # reaches back the asked 0.5 m
    # upright silhouettes only: no sheet hangs down from the cabinet's top edge
    assert not ((side[:, 1] > -0.35) & (np.abs(side[:, 0]) < 0.3)).any()


def test_edge_depth_ratio_leaves_small_steps_to_the_2d_fill():
    # A panel 0.5 m in front of the far wall (depth ratio ~0.88) and one 2.5 m in front of it (ratio ~0.38).
    room = trimesh.creation.box(bounds=[[-3.0, -1.6, -3.0], [3.0, 1.2, 4.0]])
    near = trimesh.creation.box(bounds=[[-1.2, -0.4, 1.5], [-0.5, 1.2, 1.53]])
    flat = trimesh.creation.box(bounds=[[0.5, -0.4, 3.47], [1.2, 1.2, 3.5]])
    scene = trimesh.util.concatenate([room, near, flat])
    d0 = Raycaster(scene.vertices, scene.faces).render_erp(np.eye(4), H, W).distance.astype(np.float32)
    mesh = erp_mesh_from_depth(d0, texture(points_from_depth(d0.astype(np.float64), np.eye(4))))
    x = points_from_depth(d0.astype(np.float64), np.eye(4))[..., 0]
    for ratio, flat_layer in ((0.95, True), (0.7, False)):
        layer = build_background_layer(mesh, 0.6, edge_depth_ratio=ratio, max_edge_ratio=3.0)  # 96 rows: the small step stretches a face ~4x
        assert layer.synthesized[(x < -0.4) & (d0 < 2.0)].any()  # the deep step keeps its background layer
        assert layer.synthesized[(x > 0.4) & (d0 < 3.6)].any() == flat_layer


def test_layout_planes_keep_the_hidden_floor_on_the_floor():
    # A wide panel 1 m in front of the camera, standing on the floor: the floor behind it is hidden.
    room = trimesh.creation.box(bounds=[[-3.0, -1.6, -3.0], [3.0, 1.2, 4.0]])
    panel = trimesh.creation.box(bounds=[[-0.8, 0.2, 1.0], [0.8, 1.2, 1.03]])
    scene = trimesh.util.concatenate([room, panel])
    d0 = Raycaster(scene.vertices, scene.faces).render_erp(np.eye(4), H, W).distance.astype(np.float32)
    assert np.allclose(floor_ceiling(d0, d0 > 0), (1.2, -1.6), atol=0.02)
    mesh = erp_mesh_from_depth(d0, texture(points_from_depth(d0.astype(np.float64), np.eye(4))))
    behind = Raycaster(room.vertices, room.faces).render_erp(np.eye(4), H, W).distance
    y = erp_dirs(H, W, np.float64)[..., 1]
    errs = {}
    for layout in (False, True):
        layer = build_background_layer(mesh, 1.0, layout_planes=layout)
        s = layer.synthesized & (y > 0.1)  # rays down behind the panel: the hidden floor
        assert s.sum() > 20
        errs[layout] = np.abs(layer.layer_depth - behind)[s] / behind[s]
        if layout:
            assert (layer.layer_depth[s] * y[s] <= 1.2 * 1.02).all()  # nothing below the floor
    assert np.quantile(errs[True], 0.9) < 0.01 and np.mean(errs[True] < 0.01) > np.mean(errs[False] < 0.01)


def test_layer_mean_color_continues_the_visible_colour_only():
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, : W // 2] = (200, 40, 40)
    rgb[:, W // 2 :] = (40, 40, 200)
    hide = np.zeros((H, W), bool)
    hide[30:60, 10:40] = True  # inside the red half
    hide[:, W - 8 :] = True  # a band at the seam, blue on the left of it, red across the seam
    hide[:3] = True  # the top rows, far from some known pixels
    hide[40:50, W // 2 - 20 : W // 2 + 20] = True  # straddles the red / blue border
    out = layer_mean_color(rgb, hide, 2.0)
    assert (out[~hide] == rgb[~hide]).all()
    assert np.abs(out[35:55, 15:35].astype(int) - (200, 40, 40)).max() <= 1  # a wide hole: no bleed, no streaks
    seam = out[60, W - 8 :].astype(int)  # the seam band: blue near its left edge, red near the wrapped edge
    assert seam[0, 2] > seam[0, 0] and seam[-1, 0] > seam[-1, 2]
    mid = out[45, W // 2 - 20 : W // 2 + 20].astype(int)
    assert mid[0, 0] > 150 and mid[-1, 2] > 150  # each side of the border keeps its own colour
    everything = layer_mean_color(rgb, np.ones((H, W), bool) & ~(np.arange(W) == 0)[None], 2.0)
    assert np.isfinite(everything.astype(float)).all() and (everything[:, 0] == rgb[:, 0]).all()
