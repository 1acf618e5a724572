"""Atomic text writes: readers see the old file or the new one, never a part."""

from __future__ import annotations

import os
from pathlib import Path


def write_text_atomic(path: Path, text: str) -> None:
    """Write text to path through a hidden sibling and a rename: readers see the old file or the new, never a part."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.part")
    tmp.write_text(text)
    os.replace(tmp, path)
