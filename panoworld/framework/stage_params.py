"""Param values of a stage: read from JSON, YAML or flags into its params dataclass, checked, merged, hashed."""

from __future__ import annotations

import ast
import dataclasses
import enum
import functools
import inspect
import textwrap
import types
import typing
from pathlib import Path
from typing import Any

from panoworld.core import params as P
from panoworld.io import manifest as art


def field_docs(cls: type) -> dict[str, str]:
    """Docstrings written under each dataclass field (PEP 257 attribute docstrings)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body
        for a, b in zip(body, body[1:]):
            if (
                isinstance(a, ast.AnnAssign)
                and isinstance(a.target, ast.Name)
                and isinstance(b, ast.Expr)
                and isinstance(getattr(b, "value", None), ast.Constant)
                and isinstance(b.value.value, str)
            ):
                docs[a.target.id] = " ".join(b.value.value.split())
    return docs


def unwrap_optional(tp):
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return rest[0], True
    return tp, False


def coerce(value: Any, tp: Any, where: str) -> Any:
    """Convert a JSON/YAML/CLI value into the field type; ValueError names `where` on failure."""
    tp, optional = unwrap_optional(tp)
    if value is None or (optional and isinstance(value, str) and value.lower() in ("none", "null")):
        if optional:
            return None
        raise ValueError(f"{where}: None is not allowed")
    origin = typing.get_origin(tp)
    try:
        if inspect.isclass(tp) and issubclass(tp, enum.Enum):
            try:
                return tp(value)
            except ValueError:
                raise ValueError(f"{where}: {value!r} is not one of {[m.value for m in tp]}") from None
        if tp is bool:
            if isinstance(value, bool):
                return value
            if str(value).lower() in ("1", "true", "yes", "on"):
                return True
            if str(value).lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(f"{where}: {value!r} is not a boolean")
        if tp is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(f"{where}: {value!r} is not an integer")
            return int(value)
        if tp is float:
            return float(value)
        if tp is str:
            return str(value)
        if tp is Path:
            return str(value)
        if origin in (tuple, list):
            (item_tp, *_) = typing.get_args(tp) or (str,)
            items = value.split(",") if isinstance(value, str) else list(value)
            return tuple(coerce(v.strip() if isinstance(v, str) else v, item_tp, where) for v in items if v != "")
    except (TypeError, ValueError) as e:
        if str(e).startswith(where):
            raise
        raise ValueError(f"{where}: cannot read {value!r} as {getattr(tp, '__name__', tp)}") from None
    return value


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """typing.get_type_hints of a params class, evaluated once per process (every layer of every stage asks)."""
    return typing.get_type_hints(cls)


@functools.cache
def _fields(cls: type) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(cls)}


def shown_name(name: str) -> str:
    """A user's key as an error message shows it: as typed when it is a name, else its repr (a newline or a control
    character in a key never breaks the message's one line)."""
    return name if name.isidentifier() else repr(name)


def normalize(cls: type, values: Any, where: str) -> dict[str, Any]:
    """A nested {param: value} dict from a layer of values (dotted keys and old names resolved, options nested);
    ValueError naming the param (with a "did you mean") for unknown names and wrong shapes."""
    if not isinstance(values, dict):
        raise ValueError(f"{where}: expected a mapping of param: value, got {type(values).__name__} {values!r}")
    fields = _fields(cls)
    hints = _hints(cls)
    old = P.renamed(cls)
    out: dict[str, Any] = {}
    for key, v in values.items():
        key = old.get(str(key), str(key))
        head, dot, rest = key.partition(".")
        f = fields.get(head)
        if f is None:
            raise ValueError(f"{where}.{shown_name(head)}: unknown param{P.suggest(head, list(fields) + list(old))}")
        if P.is_options(f):
            if dot:
                v = {rest: v}
            if not isinstance(v, dict):
                raise ValueError(f"{where}.{head}: expected a mapping of {head} options, got {v!r}")
            sub = normalize(hints[head], v, f"{where}.{head}")
            out[head] = merge(out.get(head) or {}, sub)
        elif dot:
            raise ValueError(f"{where}.{head}: {head} has no sub-params (got {key})")
        else:
            out[head] = v
    return out


def merge(a: dict, b: dict) -> dict:
    """Deep merge of nested param dicts: b wins."""
    out = dict(a)
    for k, v in b.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _build(cls: type, values: dict[str, Any], where: str) -> Any:
    hints = _hints(cls)
    fields = _fields(cls)
    kwargs = {k: _build(hints[k], v, f"{where}.{k}") if P.is_options(fields[k]) else coerce(v, hints[k], f"{where}.{k}")
              for k, v in values.items()}
    return cls(**kwargs)


def params_from_dict(cls: type, values: Any, where: str = "params") -> Any:
    """Build and validate a params dataclass from plain values (nested or dotted `wan.steps`); ValueError
    `where.param=value: what is allowed` naming the first bad param."""
    return params_from_normalized(cls, normalize(cls, values, where), where)


def params_from_normalized(cls: type, values: dict[str, Any], where: str = "params") -> Any:
    """params_from_dict of values normalize() already returned."""
    params = _build(cls, values, where)
    P.validate(params, where)
    return params


def params_to_dict(params: Any) -> dict[str, Any]:
    """JSON-ready dict of a params dataclass (enums as values, tuples as lists, the chosen backend's options nested;
    the options of the other backends are left out, so they neither enter the cache key nor rerun the stage)."""
    return P.active_dict(params)


def params_hash(params_dict: dict[str, Any]) -> str:
    return art.json_digest(params_dict)

