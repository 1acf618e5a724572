"""COLMAP structure from motion on a panoramic video's frames (pycolmap: SIFT, sequential matching, global or
incremental mapping), bounded for speed."""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import time
from pathlib import Path

from panoworld.core.errors import InputError
from panoworld.poses.options import ColmapOptions, Matcher, RenderType


@contextlib.contextmanager
def _quiet_colmap(level: int = 2):
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = level
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.symlink(src.resolve(), dst)
    except OSError:
        shutil.copyfile(src, dst)


SMALL_FRAME_WIDTH = 640


def _spherical_sfm(img_dir: Path, out: Path, matcher: Matcher, sfm: ColmapOptions, timings: dict) -> dict:
    """pycolmap.panorama's spherical pipeline (EQUIRECTANGULAR camera, SIFT, matching, incremental mapping) with
    bounded feature extraction and a sequential window; returns {index: Reconstruction}, seconds per step in timings."""
    import pycolmap

    t0 = time.perf_counter()
    db = out / "database.db"
    rec_path = out / "sparse"
    rec_path.mkdir(parents=True, exist_ok=True)
    pycolmap.set_random_seed(sfm.seed)
    extraction = pycolmap.FeatureExtractionOptions(use_gpu=False, num_threads=sfm.num_threads)
    if sfm.max_image_size > 0:
        extraction.max_image_size = sfm.max_image_size
    extraction.sift.max_num_features = sfm.max_features
    from PIL import Image

    with Image.open(next(iter(sorted(img_dir.iterdir())))) as im:
        width = im.width if sfm.max_image_size <= 0 else min(im.width, sfm.max_image_size)
    upsample = sfm.upsample_features or width < SMALL_FRAME_WIDTH
    extraction.sift.first_octave = -1 if upsample else 0
    timings["features_upsampled"] = upsample
    from panoworld.poses.colmap_images import restore_full_size, set_point_colors, write_thumbnails

    # COLMAP's own shrink (OpenImageIO) is half its extraction time; the same pixels made here give the same features.
    thumbs = out / "thumbnails"
    frames: dict | None = {} if sfm.mapper == "global" else None  # decoded once: the point colours come from them
    size = write_thumbnails(sorted(img_dir.iterdir()), thumbs, sfm.max_image_size, sfm.num_threads, frames)
    timings["thumbnails_s"] = round(time.perf_counter() - t0, 3)
    pycolmap.extract_features(
        db, img_dir if size is None else thumbs,
        reader_options=pycolmap.ImageReaderOptions(camera_model="EQUIRECTANGULAR"),
        camera_mode=pycolmap.CameraMode.SINGLE, extraction_options=extraction,
    )
    if size is not None:
        restore_full_size(db, *size)
    timings["extract_s"] = round(time.perf_counter() - t0, 3)
    t0 = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions(use_gpu=False, num_threads=sfm.num_threads)
    if matcher == Matcher.SEQUENTIAL:
        pairing = pycolmap.SequentialPairingOptions(overlap=sfm.overlap, quadratic_overlap=True)
        pycolmap.match_sequential(db, pairing_options=pairing, matching_options=matching)
    else:
        pycolmap.match_exhaustive(db, matching_options=matching)
    timings["match_s"] = round(time.perf_counter() - t0, 3)
    t0 = time.perf_counter()
    if sfm.mapper == "global":
        mapping = pycolmap.GlobalPipelineOptions(num_threads=sfm.num_threads, random_seed=sfm.seed)
        mapping.mapper.ba_num_iterations = sfm.ba_iterations
        mapping.mapper.keep_max_num_tracks = sfm.max_tracks
        # Pointed at an empty folder COLMAP leaves the points black instead of decoding every frame again.
        no_images = out / "no_images"
        no_images.mkdir(exist_ok=True)
        recs = pycolmap.global_mapping(db, img_dir if size is None else no_images, rec_path, mapping)
        if size is not None:
            for rec in recs.values():
                set_point_colors(rec, frames)
    elif sfm.mapper == "incremental":
        mapping = pycolmap.IncrementalPipelineOptions(num_threads=sfm.num_threads, random_seed=sfm.seed)
        recs = pycolmap.incremental_mapping(db, img_dir, rec_path, mapping)
    else:
        raise ValueError(f"mapper {sfm.mapper!r} not one of global, incremental")
    timings["map_s"] = round(time.perf_counter() - t0, 3)
    return recs


def run_colmap(
    image_paths: list[Path],
    work_dir: Path,
    options: ColmapOptions | None = None,
    *,
    verbose: bool = False,
    timings: dict | None = None,
):
    """COLMAP panorama SfM on the frames with options (None = the defaults) -> (largest reconstruction with
    EQUIRECTANGULAR camera, all models).

    spherical: our bounded pipeline (_spherical_sfm); the perspective rigs: pycolmap.panorama.reconstruct at full size.
    Frames are linked into work_dir/images under their file names (which must be unique).
    """
    import pycolmap
    from pycolmap import panorama

    sfm = options or ColmapOptions()
    render_type, matcher = sfm.render_type, sfm.matcher
    names = [p.name for p in image_paths]
    if len(set(names)) != len(names):
        raise InputError("video frames must have unique file names for COLMAP")
    img_dir = work_dir / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    for p in image_paths:
        _link_or_copy(p, img_dir / p.name)
    out = work_dir / "colmap"
    out.mkdir(parents=True, exist_ok=True)
    with _quiet_colmap(0 if verbose else 2):
        if render_type == RenderType.SPHERICAL:
            recs = _spherical_sfm(img_dir, out, matcher, sfm, {} if timings is None else timings)
        else:
            opts = panorama.PanoramaReconstructionOptions(
                render_type=panorama.PanoRenderType(str(render_type)), matcher=panorama.Matcher(str(matcher)),
                use_gpu=False, num_threads=sfm.num_threads, random_seed=sfm.seed,
                show_progress=verbose and sys.stderr.isatty(),
            )
            recs = panorama.reconstruct(img_dir, out, opts)
            # The rig models were converted back to one EQUIRECTANGULAR image per panorama on disk.
            recs = {i: pycolmap.Reconstruction(out / "sparse_equirectangular" / str(i)) for i in recs}
    if not recs:
        return None, {}
    best = max(recs, key=lambda i: recs[i].num_reg_images())
    return recs[best], recs
