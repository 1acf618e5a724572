"""Small JSON records in the user's cache directory ($XDG_CACHE_HOME/panoworld): read leniently, written atomically."""

from __future__ import annotations

import json
import os
from pathlib import Path


def user_cache_path(name: str) -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "panoworld" / name


def read_user_cache(name: str) -> dict:
    """The record as a dict; {} when it is missing, unreadable or not a JSON object (a cache is never an error)."""
    try:
        doc = json.loads(user_cache_path(name).read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def write_user_cache(name: str, doc: dict) -> None:
    """Replace the record atomically; a read-only home only costs the work again next time."""
    path = user_cache_path(name)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(doc))
        os.replace(tmp, path)
    except OSError:
        pass
