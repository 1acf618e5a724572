"""The one reader of user images: header and pixel-count check before decoding, a full strict decode, one-line refusals."""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from collections.abc import Callable
from dataclasses import astuple, dataclass
from pathlib import Path

import numpy as np

from panoworld.core.errors import InputError
from panoworld.core.limits import MAX_PIXELS, check_image_size, depth_plane, exr_header, npy_header
from panoworld.io.user_cache import read_user_cache, write_user_cache

MAX_SIDE = 65535
JPEG_SUFFIXES = (".jpg", ".jpeg")


class ImageInputError(InputError):
    """A user image that is missing, truncated, corrupt, of an unknown format or too large."""


@dataclass(frozen=True)
class ImageInfo:
    width: int
    height: int
    """Stored size; `oriented` is the size after the EXIF orientation (width and height swapped by a quarter turn)."""
    format: str
    exif_orientation: int

    @property
    def oriented(self) -> tuple[int, int]:
        quarter = self.exif_orientation in (5, 6, 7, 8)
        return (self.height, self.width) if quarter else (self.width, self.height)


def _fix(path: Path) -> str:
    return f"re-export {path.name} as a complete PNG/JPEG (re-download or re-save it)"


_CHECKED_FILE = "checked_images.json"
_CHECKED_MAX = 256


def _checked_key(path: Path) -> tuple[str, list[int]]:
    st = path.stat()
    return os.path.realpath(path), [st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev]


def _remember_checked(path: Path, info: ImageInfo) -> None:
    key, stat = _checked_key(path)
    doc = read_user_cache(_CHECKED_FILE)
    doc.pop(key, None)
    doc[key] = [stat, list(astuple(info))]
    write_user_cache(_CHECKED_FILE, dict(list(doc.items())[-_CHECKED_MAX:]))


def _check_remembered(path: Path, check: Callable[[], ImageInfo]) -> ImageInfo:
    """check() once per version of the file (path, size, mtime, inode, device) that passed it."""
    key, stat = _checked_key(path)
    hit = read_user_cache(_CHECKED_FILE).get(key)
    if isinstance(hit, list) and len(hit) == 2 and hit[0] == stat:
        try:
            return ImageInfo(*hit[1])
        except TypeError:
            pass
    info = check()
    _remember_checked(path, info)
    return info


def check_image(path: Path | str, what: str = "image", *, remember: bool = False) -> ImageInfo:
    """Check a user image without trusting it: exists, a known format, at most MAX_PIXELS, and fully decodable with no
    decoder warning (truncated or corrupt data is refused). ImageInputError (one line: the file and the fix) otherwise.

    remember: an image that passed before with the same path, size, mtime, inode and device is not decoded again (a
    record of passed checks in the user cache, like DVC's state); readers that decode the pixels check in full anyway.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageInputError(f"{path}: {what} not found (or not a regular file)")
    if remember:
        return _check_remembered(path, lambda: check_image(path, what))
    from PIL import Image

    old = Image.MAX_IMAGE_PIXELS
    try:
        Image.MAX_IMAGE_PIXELS = None  # we apply our own limit below, with the image's size in the message
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                w, h = im.size
                fmt = im.format or "?"
                if w * h > MAX_PIXELS or max(w, h) > MAX_SIDE:
                    raise ImageInputError(
                        f"{path}: pixel bomb: {w}x{h} = {w * h / 1e6:.0f} Mpx exceeds the limit of {MAX_PIXELS / 1e6:.0f} "
                        f"Mpx (16384x8192); downscale the {what} to at most 16384x8192"
                    )
                im.load()
                orientation = int(im.getexif().get(0x0112) or 1)  # (a PNG's eXIf chunk may follow the pixel data)
    except ImageInputError:
        raise
    except Exception as e:  # PIL raises OSError, SyntaxError, ValueError, struct.error ... for broken files
        kind = "truncated" if "truncated" in str(e) else "corrupt or not an image"
        detail = str(e).replace(f"'{path}'", "it").replace(str(path), "it")
        raise ImageInputError(f"{path}: {what} is {kind} ({type(e).__name__}: {detail}); {_fix(path)}") from None
    finally:
        Image.MAX_IMAGE_PIXELS = old
    if fmt == "JPEG":
        _strict_jpeg(path, what)
    return ImageInfo(w, h, fmt, orientation)


def _strict_jpeg(path: Path, what: str) -> None:
    """libjpeg-turbo in strict mode: its warnings (corrupt entropy data, premature end) are errors, unlike PIL/OpenCV."""
    import simplejpeg

    data = path.read_bytes()
    try:
        _, _, colorspace, _ = simplejpeg.decode_jpeg_header(data)
        target = {"Gray": "GRAY", "CMYK": "CMYK", "YCCK": "CMYK"}.get(colorspace, "RGB")
        simplejpeg.decode_jpeg(data, colorspace=target, strict=True)
    except ValueError as e:
        raise ImageInputError(f"{path}: {what} is corrupt or truncated (libjpeg: {e}); {_fix(path)}") from None


def read_image(path: Path | str, flags: int = -1, what: str = "image") -> np.ndarray:
    """check_image, then decode with OpenCV (flags as cv2.imread, default -1 = IMREAD_UNCHANGED: BGR order, 16 bit
    kept)."""
    import cv2  # here, not at module level: the runner imports this module to check panoramas
    check_image(path, what)
    img = cv2.imread(str(path), flags)
    if img is None:
        raise ImageInputError(f"{path}: {what} cannot be decoded by OpenCV; {_fix(Path(path))}")
    return img


def check_depth_file(path: Path | str) -> tuple[int, int]:
    """(width, height) of a user depth file (.npy, .exr or .png) within MAX_PIXELS and MIN_HEIGHT; InputError (one line
    naming the file) otherwise. A .npy is checked from its header and size, a PNG or EXR is decoded (once per file
    version, as check_image(remember=True)), so a truncated one is refused before any panorama is worked on."""
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise InputError(f"{path}: depth file not found (or not a regular file)")
    if suffix == ".npy":
        shape, _ = npy_header(path, "depth array", kinds="fiu")
        h, w = depth_plane(np.broadcast_to(np.float32(0), shape), path).shape
    elif suffix == ".exr":
        exr_header(path)  # the size from the header first: nothing is decoded beyond the limits
        info = _check_remembered(path, lambda: _decoded_exr_info(path))
        w, h = info.width, info.height
    else:
        info = check_image(path, "depth PNG", remember=True)
        w, h = info.width, info.height
    check_image_size(path, w, h, "depth")
    return w, h


def check_mask_file(path: Path | str, what: str = "rig mask") -> tuple[int, int]:
    """(width, height) of a user mask image: check_image, within MIN_HEIGHT, 2:1; InputError (one line) otherwise."""
    w, h = check_image(path, what).oriented
    check_image_size(path, w, h, what)
    if w != 2 * h:
        raise InputError(f"{path}: {what} is {w}x{h} but must be 2:1 like the panorama")
    return w, h


def read_rig_mask(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """A rig mask (a 2:1 grayscale image, white = rig: a user's, or a depth artifact's io.home.RIG_MASK_PNG) -> (H, W)
    bool, resized (nearest) to size (H, W) where given; InputError (one line) when it is not one (check_mask_file)."""
    import cv2

    check_mask_file(path)
    m = read_image(path, cv2.IMREAD_GRAYSCALE, what="rig mask")
    if size is not None and m.shape != tuple(size):
        m = cv2.resize(m, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)
    return m > 127


def read_exr(path: Path | str) -> np.ndarray:
    """The depth plane of an OpenEXR file (the Z, Y, R or depth channel, else the first) as float32 (H, W) (OpenCV with
    OpenEXR, else the `OpenEXR` package); InputError (one line) for a corrupt or truncated file."""
    import cv2

    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    try:
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    except cv2.error:
        depth = None
    if depth is not None:
        return depth
    try:
        import OpenEXR
    except ImportError:
        raise InputError(
            f"{path}: cannot read EXR (this OpenCV has no OpenEXR and the OpenEXR package is missing); "
            "pip install OpenEXR, or save depth.npy"
        ) from None
    try:
        with _c_output_silenced(), OpenEXR.File(str(path)) as f:
            channels = f.channels()
            name = next(c for c in ("Z", "Y", "R", "depth") if c in channels) if channels else None
            if name is None:
                name = next(iter(channels))
            return np.asarray(channels[name].pixels, dtype=np.float32)
    except Exception as e:  # OpenEXR raises plain exceptions for corrupt files
        raise InputError(f"{path}: cannot read the EXR depth, corrupt or truncated ({e}); save it again") from None


@contextlib.contextmanager
def _c_output_silenced():
    """File descriptors 1 and 2 on /dev/null: OpenEXR prints its own lines about a corrupt file, which is refused in one."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, null):
            os.close(fd)


def _decoded_exr_info(path: Path) -> ImageInfo:
    depth = depth_plane(read_exr(path), path)
    return ImageInfo(depth.shape[1], depth.shape[0], "EXR", 1)
