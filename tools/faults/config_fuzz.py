"""Mutated settings files: the default configuration with one thing wrong, as a fuzzer makes them.

:func:`mutated_config` turns a seed into one file (bytes), deterministically; the kinds cover what a
hand-edited or damaged file holds: a value of the wrong type or size (1e30, NaN, a list, 5000
characters), a missing or unknown key, a section replaced by a scalar, a section given twice, YAML
aliases (a "billion laughs" bomb), bytes that are not UTF-8, a file cut short.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import yaml

from mavvo.service.settings import default_yaml

__all__ = ["KINDS", "default_config", "mutated_config"]

KINDS = ("value", "delete", "unknown_key", "section_type", "duplicate_section", "alias", "bytes", "truncate")
_ODD_VALUES: tuple[Any, ...] = (
    1e30,
    -1e30,
    float("nan"),
    float("inf"),
    0,
    -1,
    2**63,
    1e-300,
    True,
    None,
    "",
    "x" * 5000,
    [],
    {},
    [1, 2],
    {"a": 1},
    "1e3",
    "\n\n",
)
_ALIAS_BOMB = b'a: &a ["x","x","x","x","x","x","x","x","x"]\nb: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]\nc: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]\n'


def default_config() -> dict[str, Any]:
    """The default settings as the YAML mapping ``config/default.yaml`` holds."""
    data: dict[str, Any] = yaml.safe_load(default_yaml())
    return data


def _leaves(d: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out: list[tuple[str, ...]] = []
    for k, v in d.items():
        out.extend(_leaves(v, prefix + (k,)) if isinstance(v, dict) else [prefix + (k,)])
    return out


def _odd_value(rng: np.random.Generator) -> Any:
    pick = int(rng.integers(4))
    if pick == 0:
        return _ODD_VALUES[int(rng.integers(len(_ODD_VALUES)))]
    if pick == 1:
        return int(rng.integers(-(10**12), 10**12))
    if pick == 2:
        return float(rng.normal() * 10.0 ** rng.integers(-5, 40))
    return "".join(chr(int(c)) for c in rng.integers(32, 0x2FF, int(rng.integers(0, 20))))


def mutated_config(seed: int, base: dict[str, Any] | None = None) -> tuple[str, bytes]:
    """(kind of mutation, file bytes) for ``seed``: ``base`` (default: :func:`default_config`) with one
    mutation of a kind in :data:`KINDS`."""
    rng = np.random.default_rng(seed)
    data = copy.deepcopy(base if base is not None else default_config())
    leaves = _leaves(data)
    sections = sorted(k for k, v in data.items() if isinstance(v, dict))
    kind = KINDS[int(rng.integers(len(KINDS)))]
    if kind in ("value", "delete"):
        path = leaves[int(rng.integers(len(leaves)))]
        node = data
        for k in path[:-1]:
            node = node[k]
        if kind == "delete":
            del node[path[-1]]
        else:
            node[path[-1]] = _odd_value(rng)
    elif kind == "unknown_key":
        data[sections[int(rng.integers(len(sections)))]][f"no_such_key_{int(rng.integers(1000))}"] = _odd_value(rng)
    elif kind == "section_type":
        data[sections[int(rng.integers(len(sections)))]] = _odd_value(rng)
    text = yaml.safe_dump(data, allow_unicode=True).encode("utf-8")
    if kind == "duplicate_section":
        text += f"{sections[int(rng.integers(len(sections)))]}: {{}}\n".encode()
    elif kind == "alias":
        text = _ALIAS_BOMB + text
    elif kind == "bytes":
        at = int(rng.integers(len(text) + 1))
        text = text[:at] + bytes(rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8)) + text[at:]
    elif kind == "truncate":
        text = text[: int(rng.integers(len(text) + 1))]
    return kind, text
