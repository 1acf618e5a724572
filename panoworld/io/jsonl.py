"""JSON Lines (index.jsonl, failures.jsonl): one JSON object a line, keys sorted, written atomically."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

from panoworld.core.errors import InputError
from panoworld.io.jsonio import to_jsonable
from panoworld.io.safe_write import write_text_atomic


def write_jsonl(path: Path | str, rows: Iterable[dict]) -> Path:
    """Write rows (through to_jsonable) one a line, keys sorted, through a rename; returns the path."""
    path = Path(path)
    write_text_atomic(path, "".join(json.dumps(to_jsonable(r), sort_keys=True, allow_nan=False) + "\n" for r in rows))
    return path


def read_jsonl(path: Path | str, *, missing_ok: bool = False) -> list[dict]:
    """The objects of a JSON Lines file (blank lines skipped); [] for a missing file with missing_ok; else InputError
    naming the file (and the line) that cannot be read."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        if missing_ok:
            return []
        raise InputError(f"{path}: missing") from None
    except OSError as e:
        raise InputError(f"{path}: unreadable ({e})") from None
    rows = []
    for k, line in enumerate(text.splitlines(), 1):
        if line.strip():
            try:
                rows.append(json.loads(line))
            except ValueError as e:
                raise InputError(f"{path}: line {k} is not JSON ({e})") from None
    return rows
