"""Options: frozen dataclasses whose fields carry a default, a help line and bounds.

Every component's settings are one frozen dataclass of :func:`bounded` fields, defined beside the
code that uses them (``FrontendOptions`` in :mod:`mavvo.odometry.frontend`, ``LinkOptions`` in
:mod:`mavvo.service.link`, ...). This module has no dependencies, so every layer may import it; the
YAML loader (:mod:`mavvo.service.yaml_loader`) reads the metadata to check a file and
:func:`mavvo.service.settings.config_yaml` to document it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

__all__ = ["BOUNDS", "bounded"]

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
