"""Declared params: ranges and choices beside each dataclass field, nested backend options, one validator."""

from __future__ import annotations

import dataclasses
import difflib
import enum
import math
from typing import Any

_KEY = "panoworld"


@dataclasses.dataclass(frozen=True)
class Rule:
    """What a param accepts beyond its type (all bounds inclusive unless named gt/lt)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple | None = None
    finite: bool = True
    """Floats must be finite (no nan, inf)."""

    def problem(self, value: Any) -> str | None:
        """Why `value` is refused (None when it is accepted); None values are the type's business."""
        if value is None or isinstance(value, bool):
            return None
        if self.choices is not None and value not in self.choices:
            return "must be one of " + ", ".join(str(getattr(c, "value", c)) for c in self.choices)
        if not isinstance(value, (int, float)):
            return None
        if isinstance(value, float) and self.finite and not math.isfinite(value):
            return "must be a finite number"
        for bound, op, ok in (
            (self.ge, ">=", lambda v, b: v >= b), (self.gt, ">", lambda v, b: v > b),
            (self.le, "<=", lambda v, b: v <= b), (self.lt, "<", lambda v, b: v < b),
        ):
            if bound is not None and not ok(value, bound):
                return f"must be {op} {bound:g}"
        return None

    def describe(self) -> str:
        """Short text for --help ('>= 1', 'one of 1, 2, 4'), empty when nothing is declared."""
        if self.choices is not None:
            return "one of " + ", ".join(str(getattr(c, "value", c)) for c in self.choices)
        parts = [f"{op} {b:g}" for b, op in ((self.ge, ">="), (self.gt, ">"), (self.le, "<="), (self.lt, "<")) if b is not None]
        return " and ".join(parts)


_DEFAULT_RULE = Rule()


def param(default: Any = dataclasses.MISSING, *, default_factory: Any = dataclasses.MISSING, ge=None, gt=None,
          le=None, lt=None, choices=None, finite: bool = True) -> Any:
    """A dataclass field with its accepted values declared: `stride: int = param(1, choices=(1, 2, 4))`."""
    rule = Rule(ge=ge, gt=gt, le=le, lt=lt, choices=tuple(choices) if choices is not None else None, finite=finite)
    return dataclasses.field(default=default, default_factory=default_factory, metadata={_KEY: rule})


def options(cls: type, backend: str | None = None) -> Any:
    """A nested options field, the dataclass of backend `backend`: `wan: WanOptions = options(WanOptions,
    "wan-shortcut")`; only the chosen backend's options enter the manifest and cache key (active_dict)."""
    return dataclasses.field(default_factory=cls, metadata={_KEY: "options", "backend": backend})


def rule_of(f: dataclasses.Field) -> Rule:
    r = f.metadata.get(_KEY)
    return r if isinstance(r, Rule) else _DEFAULT_RULE


def is_options(f: dataclasses.Field) -> bool:
    return f.metadata.get(_KEY) == "options"


def renamed(cls: type) -> dict[str, str]:
    """Old param names that still work: {old: new dotted name}, declared as `RENAMED` on the params class."""
    return dict(getattr(cls, "RENAMED", {}) or {})


def suggest(name: str, known) -> str:
    """'; did you mean X?' for the closest known name, else the list of known names."""
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else f"; known: {', '.join(sorted(known))}"


def plain(v: Any) -> Any:
    """JSON-ready value (enums as values, tuples as lists, nested dataclasses as dicts)."""
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, enum.Enum):
        return v.value
    if isinstance(v, (tuple, list)):
        return [plain(x) for x in v]
    if hasattr(v, "__fspath__"):
        return str(v)
    return v


def active_dict(params: Any) -> dict[str, Any]:
    """plain(params) without the options of backends other than `params.backend` (all kept for backend auto)."""
    out = plain(params)
    chosen = plain(getattr(params, "backend", None))
    for f in dataclasses.fields(params):
        owner = f.metadata.get("backend") if is_options(f) else None
        if owner is not None and chosen not in (owner, "auto"):
            out.pop(f.name)
    return out


def validate(params: Any, where: str) -> None:
    """ValueError `where.name=value: must be ...` for the first declared rule a value breaks (nested options too)."""
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if is_options(f):
            validate(value, f"{where}.{f.name}")
            continue
        why = rule_of(f).problem(value)
        if why:
            raise ValueError(f"{where}.{f.name}={plain(value)}: {why}")


def flatten(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{'wan': {'steps': 4}} -> {'wan.steps': 4} (for diffs and listings)."""
    out: dict[str, Any] = {}
    for k, v in values.items():
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out
