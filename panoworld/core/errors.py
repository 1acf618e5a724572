"""One root error type for the project: every refusal a user sees is a `PanoWorldError` with a one-line message."""

from __future__ import annotations


class PanoWorldError(Exception):
    """Root of every error the project raises on purpose; `exit_code` is what the CLIs exit with."""

    exit_code = 1


class InputError(PanoWorldError, ValueError):
    """Bad user input (a file, a flag, a param, a scene): exit code 2, one line naming the input and the fix."""

    exit_code = 2


class ArtifactError(PanoWorldError):
    """An artifact is missing, invalid, tampered with, or of a schema version the code no longer accepts."""

    exit_code = 1


class PipelineError(InputError):
    """A bad request to the runner (unknown stage/param, bad scene, locked scene): exit code 2."""


class WeightsError(InputError):
    """Weights absent, incomplete or unresolvable; the message names the flag, the files or the fetch command."""


class DataError(InputError):
    """A dataset, clip or track that cannot be used (training, precompute, batch)."""


def from_os_error(e: OSError) -> PanoWorldError:
    """An environment error (read-only scene, no permission, a file where a folder must be, a full disk) as one
    line naming the path and the fix: InputError (exit 2) where the user's files or folders are at fault, else a
    PanoWorldError (exit 1)."""
    import errno

    fixes = {
        errno.EROFS: ("the file system is read-only; copy the scene somewhere writable", True),
        errno.EACCES: ("permission denied; make it writable for you or copy the scene", True),
        errno.EPERM: ("operation not permitted; make it writable for you or copy the scene", True),
        errno.EEXIST: ("a file is where a folder must be; move it away", True),
        errno.ENOTDIR: ("a file is where a folder must be; move it away", True),
        errno.EISDIR: ("a folder is where a file must be; move it away", True),
        errno.ENOSPC: ("the disk is full; free some space and run again", False),
        errno.EDQUOT: ("the disk quota is exhausted; free some space and run again", False),
    }
    fix, user = fixes.get(e.errno, (f"{e.strerror or e}; check the disk and run again", False))
    where = e.filename if e.filename is not None else "a file"
    cls = InputError if user else PanoWorldError
    return cls(f"{where}: {e.strerror or type(e).__name__} (errno {e.errno}): {fix}")


class NoFloorError(InputError):
    """The mesh has no walkable floor (no up-facing area below the camera, or nothing left after erosion)."""
