"""JSON in and out with one policy: numpy scalars and arrays as Python values, non-finite floats as null."""

from __future__ import annotations

import enum
import json
import math
import os
from pathlib import Path
from typing import Any

_MISSING = object()


def to_jsonable(obj: Any) -> Any:
    """obj as plain JSON values: numpy scalars and arrays as numbers and lists, enums as their values, paths as
    strings, and every non-finite float (nan, inf, -inf) as None (JSON null: strict JSON that any parser reads;
    readers treat null as "not available")."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, enum.Enum):
        return to_jsonable(obj.value)
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "tolist") and callable(obj.tolist):  # numpy scalars and arrays
        return to_jsonable(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def write_json(path: Path | str, obj: Any, *, indent: int | None = 1, sort_keys: bool = False, atomic: bool = False) -> Path:
    """Write obj (through to_jsonable) as strict JSON with a trailing newline; returns the path. atomic: through a
    hidden sibling and a rename (readers of a live file see the old or the new document, never a part)."""
    from panoworld.io.safe_write import write_text_atomic

    path = Path(path)
    text = json.dumps(to_jsonable(obj), indent=indent, sort_keys=sort_keys, allow_nan=False) + "\n"
    write_text_atomic(path, text) if atomic else path.write_text(text)
    return path


def read_json(path: Path | str, *, default: Any = _MISSING) -> Any:
    """The JSON document at path; with `default`, that value when the file is missing or not valid JSON (else the
    OSError / ValueError propagates)."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        if default is _MISSING:
            raise
        return default
