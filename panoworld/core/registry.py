"""Backend registry: each stage's backends (a module each, with its own options dataclass) under one name."""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Backend:
    """One registered backend of a stage."""

    stage: str
    name: str
    impl: Callable
    """The backend's entry point; its signature is the stage's (see panoworld/<stage>/backends/__init__.py)."""
    options: type | None = None
    """Its options dataclass, nested in the stage's Params under `key` (`video.wan.steps`)."""
    key: str | None = None
    traits: dict[str, Any] = field(default_factory=dict)
    """What the stage needs to know about its output (e.g. has_depth)."""

    def options_of(self, params: Any) -> Any:
        """This backend's options out of a stage's Params (None when it has none)."""
        return getattr(params, self.key) if self.key else None


_REGISTRY: dict[str, dict[str, Backend]] = {}
_PACKAGES = {"rig": "panoworld.depth.rig.backends"}
"""Backend kinds that are not a stage: the module that registers them (a stage's is panoworld.<stage>.backends)."""


def register(stage: str, name: str, impl: Callable, *, options: type | None = None, key: str | None = None,
             **traits: Any) -> Backend:
    """Register `name` as a backend of `stage` (called at import by the backend's module)."""
    if options is not None and (key is None or not dataclasses.is_dataclass(options)):
        raise TypeError(f"backend {stage}/{name}: options must be a dataclass and need a key")
    b = Backend(stage, name, impl, options, key, dict(traits))
    _REGISTRY.setdefault(stage, {})[name] = b
    return b


def backends(stage: str) -> dict[str, Backend]:
    """The backends of a stage, in registration order (imports the stage's backends package, which registers them)."""
    importlib.import_module(_PACKAGES.get(stage, f"panoworld.{stage}.backends"))
    return dict(_REGISTRY.get(stage, {}))


def names(stage: str) -> tuple[str, ...]:
    return tuple(backends(stage))


def pick(stage: str, name: str, given: dict[str, Any]) -> Backend:
    """The backend `name`, or for name auto the one that uses the most of the inputs given (trait needs_inputs)."""
    if name != "auto":
        return get(stage, name)
    usable = [b for b in backends(stage).values() if all(given.get(i) is not None for i in b.traits.get("needs_inputs", ()))]
    return max(usable, key=lambda b: len(b.traits.get("needs_inputs", ())))


def with_trait(stage: str, trait: str) -> Backend:
    """The first backend of a stage whose trait `trait` is true (e.g. poses' copies_plan)."""
    for b in backends(stage).values():
        if b.traits.get(trait):
            return b
    raise KeyError(f"{stage}: no backend with trait {trait!r}")


def get(stage: str, name: str) -> Backend:
    try:
        return backends(stage)[str(name)]
    except KeyError:
        raise KeyError(f"{stage}: unknown backend {name!r}; known: {', '.join(names(stage))}") from None
