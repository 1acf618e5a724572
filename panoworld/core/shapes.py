"""check_shape: one-line InputError when an array's shape (or dtype) is not what a public entry point expects."""

from __future__ import annotations

from typing import Any

import numpy as np

from panoworld.core.errors import InputError


def check_shape(name: str, arr: Any, spec: str, *, dtype: Any = None, dims: dict[str, int] | None = None) -> dict[str, int]:
    """Check `arr` against `spec`, space-separated dims: a number (exact), a name (any size, equal wherever the name
    recurs, here or in `dims` from earlier checks), `*` (any size) or a leading `...` (any number of leading dims).
    `dtype` is a numpy dtype or abstract type (np.floating) the array's dtype must be a sub-type of.

    Returns `dims` updated with the names bound here (pass it to the next check to tie shapes together). Raises
    InputError `name.shape=(6, 12, 1) but expected (H, W)` (names bound earlier shown by their value)."""
    dims = {} if dims is None else dims
    tokens = spec.split()
    shape = tuple(np.shape(arr))
    leading = bool(tokens) and tokens[0] == "..."
    if leading:
        tokens = tokens[1:]
    shown = ", ".join(str(dims.get(t, t)) for t in tokens) + ("," if len(tokens) == 1 else "")
    expected = f"({'..., ' if leading else ''}{shown})" + (f" {np.dtype(dtype).name}" if _concrete(dtype) else "")
    bound = dict(dims)
    ok = len(shape) >= len(tokens) if leading else len(shape) == len(tokens)
    if ok:
        for t, n in zip(tokens, shape[len(shape) - len(tokens):]):
            if t == "*":
                continue
            want = int(t) if t.lstrip("-").isdigit() else bound.setdefault(t, n)
            if n != want:
                ok = False
                break
    if ok and dtype is not None:
        ok = np.issubdtype(np.dtype(_np_dtype(arr)), dtype)
    if not ok:
        got = f"{shape}" + (f" {_np_dtype(arr)}" if dtype is not None else "")
        raise InputError(f"{name}.shape={got} but expected {expected}")
    dims.update(bound)
    return dims


def _concrete(dtype: Any) -> bool:
    try:
        return dtype is not None and not (isinstance(dtype, type) and dtype in (np.floating, np.integer, np.number,
                                                                               np.signedinteger, np.unsignedinteger))
    except TypeError:
        return False


def _np_dtype(arr: Any) -> str:
    dt = getattr(arr, "dtype", None)
    if dt is None:
        return np.asarray(arr).dtype.name
    try:
        return np.dtype(dt).name
    except TypeError:  # a torch dtype
        return str(dt).removeprefix("torch.")
