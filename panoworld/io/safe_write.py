"""Writing where a user points us: a regular file or a directory only, through an unpredictable O_EXCL temporary."""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from panoworld.core.errors import InputError


class OutputPathError(InputError):
    """An output path a user named that cannot be written safely (a device, a FIFO, a symbolic link, a folder)."""


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory"), (stat.S_ISLNK, "a symbolic link")):
        if test(mode):
            return name
    return "not a regular file"


def _check_parent(path: Path) -> None:
    parent = path.parent
    for p in (parent, *parent.parents):
        if p.is_symlink() or p.exists():
            if not p.is_dir():
                raise OutputPathError(f"{path}: {p} is not a directory; give a path in a directory")
            return


def _check_output(path: Path | str, want, noun: str) -> Path:
    path = Path(path)
    try:
        st = os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):
        _check_parent(path)
        return path
    except OSError as e:
        raise OutputPathError(f"{path}: cannot be written ({e.strerror}); give another output path") from None
    if not want(st.st_mode):
        raise OutputPathError(f"{path}: is {_kind(st.st_mode)}, not {noun}; give the path of {noun} to write")
    return path


def check_output_file(path: Path | str) -> Path:
    """path, when it names nothing yet or a regular file (not a symbolic link); OutputPathError (exit 2) otherwise."""
    return _check_output(path, stat.S_ISREG, "a regular file")


def check_output_dir(path: Path | str) -> Path:
    """path, when it names nothing yet or a directory (not a symbolic link); OutputPathError (exit 2) otherwise."""
    return _check_output(path, stat.S_ISDIR, "a directory")


@contextlib.contextmanager
def atomic_output(path: Path | str, mode: str = "wb", *, encoding: str | None = None, durable: bool = True) -> Iterator[IO]:
    """Open a temporary beside path (a random name created with O_EXCL, never followed through a link), yield it,
    and on success fsync it (durable) and rename it over path; on failure the temporary goes and path stays as it
    was. Not durable: a crash may leave path empty, never half written (for notes whose loss costs nothing)."""
    path = check_output_file(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, mode, encoding=encoding) as f:
            yield f
            f.flush()
            if durable:
                os.fsync(f.fileno())
        check_output_file(path)  # still a regular file (or nothing) at the moment of the swap
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_text_atomic(path: Path | str, text: str, encoding: str = "utf-8", *, durable: bool = True) -> Path:
    """Write text to path through atomic_output: readers see the old file or the new one, never a part."""
    with atomic_output(path, "w", encoding=encoding, durable=durable) as f:
        f.write(text)
    return Path(path)


def write_bytes_atomic(path: Path | str, data: bytes) -> Path:
    with atomic_output(path, "wb") as f:
        f.write(data)
    return Path(path)


def inside(root: Path | str, *parts: str) -> Path:
    """root joined with parts, refused (InputError) unless it stays inside root (no `..`, no absolute part)."""
    root = Path(root)
    joined = root.joinpath(*parts)
    if not os.path.normpath(joined).startswith(os.path.normpath(root) + os.sep):
        raise InputError(f"{joined}: leaves {root}; give file names without '..' or '/'")
    return joined
