from pathlib import Path

import cv2
import numpy as np
import pytest

from panoworld.poses.colmap_images import (
    THUMB_SUFFIX,
    Thumbnailer,
    grey_reference,
    resize_reference,
    restore_full_size,
    set_point_colors,
    thumbnail_size,
    write_thumbnails,
)

pycolmap = pytest.importorskip("pycolmap")


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    """(h, w, 3) uint8 RGB: smooth blobs plus noise, so the resize and SIFT both have something to do."""
    rng = np.random.default_rng(seed)
    low = cv2.resize(rng.uniform(0, 255, (h // 16, w // 16, 3)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(low + rng.normal(0, 25, (h, w, 3)), 0, 255).astype(np.uint8)


def _colmap_thumbnail(rgb: np.ndarray, max_image_size: int) -> np.ndarray:
    bitmap = pycolmap.Bitmap.from_array(rgb).clone_as_grey()
    bitmap.thumbnail(max_image_size)
    return bitmap.to_array().reshape(bitmap.height, bitmap.width)


@pytest.mark.parametrize("h, w, size", [(720, 1440, 1024), (181, 362, 128), (100, 300, 77)])
def test_thumbnail_is_colmaps_bit_for_bit(h, w, size):
    rgb = _texture(h, w, seed=h)
    ref = _colmap_thumbnail(rgb, size)
    assert ref.shape[::-1] == thumbnail_size(w, h, size)
    ours = Thumbnailer(h, w, size)(np.ascontiguousarray(rgb[..., ::-1]))
    np.testing.assert_array_equal(ours, ref)
    np.testing.assert_array_equal(resize_reference(grey_reference(rgb), *ref.shape[::-1]), ref)


def _extract(db: Path, img_dir: Path, size: int) -> None:
    opts = pycolmap.FeatureExtractionOptions(use_gpu=False, num_threads=1)
    opts.max_image_size = size
    opts.sift.first_octave = 0
    pycolmap.extract_features(db, img_dir, reader_options=pycolmap.ImageReaderOptions(camera_model="EQUIRECTANGULAR"),
                              camera_mode=pycolmap.CameraMode.SINGLE, extraction_options=opts)


def _features(db_path: Path) -> tuple[list, dict]:
    db = pycolmap.Database.open(db_path)
    try:
        cams = [(c.model, c.width, c.height, list(c.params)) for c in db.read_all_cameras()]
        feats = {i.name: (db.read_keypoints(i.image_id), np.asarray(db.read_descriptors(i.image_id).data))
                 for i in db.read_all_images()}
    finally:
        db.close()
    return cams, feats


def test_thumbnails_give_colmaps_features(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    paths = []
    for i in range(2):
        paths.append(frames / f"{i:06d}.png")
        cv2.imwrite(str(paths[-1]), _texture(240, 480, seed=i))
    _extract(tmp_path / "ref.db", frames, 320)
    size = write_thumbnails(paths, tmp_path / "thumbs", 320, num_threads=2)
    assert size == (480, 240)
    assert sorted(p.name for p in (tmp_path / "thumbs").iterdir()) == [p.name + THUMB_SUFFIX for p in paths]
    _extract(tmp_path / "fast.db", tmp_path / "thumbs", 320)
    restore_full_size(tmp_path / "fast.db", *size)
    cams_ref, ref = _features(tmp_path / "ref.db")
    cams, fast = _features(tmp_path / "fast.db")
    assert cams == cams_ref
    assert fast.keys() == ref.keys() == {p.name for p in paths}
    for name in ref:
        assert len(ref[name][0]) > 50
        np.testing.assert_array_equal(fast[name][0], ref[name][0])
        np.testing.assert_array_equal(fast[name][1], ref[name][1])


def test_write_thumbnails_declines_what_colmap_reads_differently(tmp_path):
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), _texture(64, 128, seed=3))
    assert write_thumbnails([small], tmp_path / "t", 1024) is None  # already fits: nothing to shrink
    jpg = tmp_path / "f.jpg"
    cv2.imwrite(str(jpg), _texture(256, 512, seed=4))
    assert write_thumbnails([jpg], tmp_path / "t", 128) is None  # decoders of lossy formats may differ
    grey = tmp_path / "g.png"
    cv2.imwrite(str(grey), _texture(256, 512, seed=5)[..., 0])
    assert write_thumbnails([grey], tmp_path / "t", 128) is None


def test_point_colors_are_colmaps(tmp_path):
    from panoworld.poses.estimate import reconstruction_from_poses

    h, w = 60, 120
    rng = np.random.default_rng(7)
    names = ["a.png", "b.png"]
    frames = {n: _texture(h, w, seed=10 + i)[..., ::-1].copy() for i, n in enumerate(names)}
    for n, bgr in frames.items():
        cv2.imwrite(str(tmp_path / n), bgr)
    rec = reconstruction_from_poses(names, np.repeat(np.eye(4)[None], 2, axis=0), h, w)
    # Observations anywhere, edges included (out-of-bounds samples are skipped; a point with none stays black).
    xy = {i: np.concatenate([rng.uniform(0, [w, h], (40, 2)), [[0.2, 30.0], [w - 0.3, 5.0], [60.0, h - 0.1]]])
          for i in rec.images}
    for i, img in rec.images.items():
        img.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in xy[i]])
    (i1, i2), n = sorted(rec.images), len(xy[1])
    for k in range(n):
        track = pycolmap.Track()
        track.add_element(i1, k)
        if k % 2:
            track.add_element(i2, k)  # seen twice: the mean of two samples is rounded
        rec.add_point3D(np.array([0.0, 0.0, 1.0 + k]), track)
    ref = pycolmap.Reconstruction(rec)
    ref.extract_colors_for_all_images(str(tmp_path))
    set_point_colors(rec, frames)
    colors = {pid: rec.points3D[pid].color for pid in rec.point3D_ids()}
    assert sum(int(c.max() == 0) for c in colors.values()) >= 1
    for pid in ref.point3D_ids():
        np.testing.assert_array_equal(colors[pid], ref.points3D[pid].color)
