"""Options: frozen dataclasses whose fields carry a default, a help line and bounds.

Every component's settings are one frozen dataclass of :func:`bounded` fields, defined beside the
code that uses them (``FrontendOptions`` in :mod:`mavvo.odometry.frontend`, ``LinkOptions`` in
:mod:`mavvo.service.link`, ...). This module has no dependencies, so every layer may import it; the
YAML loader (:mod:`mavvo.service.yaml_loader`) reads the metadata to check a file and
:func:`mavvo.service.settings.config_yaml` to document it.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import typing
from typing import Any

__all__ = ["BOUNDS", "bounded", "check_fields"]

# Bound keyword -> the comparison it stands for, as error messages spell it.
BOUNDS = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}


def bounded(default: Any, help: str = "", **bounds: float) -> Any:
    """A dataclass field with a default, a one-line help and optional bounds (``ge``, ``gt``, ``le``,
    ``lt``), checked by the YAML loader on every number of the value (each element of a tuple)."""
    unknown = set(bounds) - set(BOUNDS)
    if unknown:
        raise TypeError(f"bounded: unknown bound(s) {sorted(unknown)}")
    if isinstance(default, (list, dict)):
        raise TypeError("bounded: use tuples, not mutable defaults")
    return dataclasses.field(default=default, metadata={"help": help, **bounds})


_COMPARE = {"ge": operator.ge, "gt": operator.gt, "le": operator.le, "lt": operator.lt}


@functools.lru_cache(maxsize=None)
def _declared(cls: type) -> tuple[tuple[str, tuple[Any, ...], tuple[tuple[str, float], ...]], ...]:
    """Per field of ``cls``: (name, Literal choices or (), bounds). Worked out once per class: options
    are made on hot paths (dataclasses.replace per relative pose), and resolving type hints is slow."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        choices = typing.get_args(tp) if typing.get_origin(tp) is typing.Literal else ()
        out.append((f.name, choices, tuple((k, v) for k, v in f.metadata.items() if k in _COMPARE)))
    return tuple(out)


def check_fields(options: Any) -> None:
    """Check an options object made in Python (not through the YAML loader, which checks a file with
    its path in the message) against what its fields declare: bounds on numbers and the choices of a
    ``Literal``. Raises ValueError naming the field, what was expected and what came."""
    for name, choices, bounds in _declared(type(options)):
        value = getattr(options, name)
        if choices and value not in choices:
            raise ValueError(f"{name}: expected one of {', '.join(map(repr, choices))}, got {value!r}")
        if not bounds or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        if not (math.isfinite(value) and all(_COMPARE[k](value, v) for k, v in bounds)):
            wanted = " and ".join(f"{BOUNDS[k]} {v:g}" for k, v in bounds)
            raise ValueError(f"{name}: expected a number {wanted}, got {value!r}")
