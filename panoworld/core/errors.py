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


class NoFloorError(InputError):
    """The mesh has no walkable floor (no up-facing area below the camera, or nothing left after erosion)."""
