"""YAML to frozen dataclasses, strictly.

Every dataclass field is a key; its type annotation is the expected type and its metadata (set by
:func:`mavvo.options.bounded`) may carry bounds (``ge``, ``gt``, ``le``, ``lt``) and a one-line ``help``. An unknown key, a wrong type or a value
out of range is a :class:`ConfigError` that names the source, the key path and what was expected::

    mavvo/sim/scenarios/hover.yaml: trajectory.altitude_m: expected a number > 0, got -3

Supported field types: bool, int, float, str, ``Literal[...]``, ``tuple[T, ...]``, fixed tuples,
``T | None``, nested dataclasses (also in tuples), and unions of dataclasses told apart by a ``type``
key that matches each class's ``TYPE`` class attribute.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin

import yaml

from mavvo.errors import ConfigError
from mavvo.options import BOUNDS

T = TypeVar("T")

MAX_CONFIG_BYTES = 10 * 1024 * 1024  # a settings file is a few kB; anything near this is not one


def _one_line(e: yaml.YAMLError) -> str:
    """A YAML error as one line: what is wrong and where (PyYAML's own text spans several lines)."""
    problem = getattr(e, "problem", None)
    mark = getattr(e, "problem_mark", None)
    if problem is None:
        return " ".join(str(e).split())
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    context = getattr(e, "context", None)
    return f"{problem}{where}" + (f" ({context})" if context else "")


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader without aliases (a few hundred bytes of nested aliases expand to
    gigabytes) and without duplicate keys (a second ``link:`` would silently replace the first)."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.constructor.ConstructorError(
                None, None, "aliases (*name) are not allowed in a settings file", event.start_mark
            )
        return super().compose_node(parent, index)

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; ConfigError naming the file if it is missing, larger than 10 MiB, not
    UTF-8, unparsable (aliases and duplicate keys included) or not a mapping."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise ConfigError(f"{p}: expected a settings file of at most 10 MiB, got {size} bytes")
        raw = p.read_bytes()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read: {e.strerror or e}") from e
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: expected UTF-8 text, got byte 0x{raw[e.start]:02x} at offset {e.start}") from e
    try:
        data = yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not valid YAML: {_one_line(e)}") from e
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping of keys at the top level, got {type(data).__name__}")
    return data


def build(cls: type[T], data: Any, source: str, path: str = "") -> T:
    """Instantiate dataclass ``cls`` from a mapping, checking every key against its fields."""
    return _convert(cls, data, source, path)


def _fail(source: str, path: str, expected: str, value: Any) -> ConfigError:
    where = f"{source}: {path}" if path else source
    return ConfigError(f"{where}: expected {expected}, got {value!r}")


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _build_dataclass(cls: type, data: Any, source: str, path: str) -> Any:
    if not isinstance(data, dict):
        raise _fail(source, path, f"a mapping of {cls.__name__} keys", data)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = [k for k in data if k not in fields]
    retired = getattr(cls, "RETIRED_KEYS", {})
    for k in unknown:
        if k in retired:
            raise ConfigError(f"{source}: {_join(path, str(k))}: no longer a key: {retired[k]}")
    if unknown:
        raise ConfigError(
            f"{source}: {_join(path, str(unknown[0]))}: unknown key; expected one of {', '.join(sorted(fields))}"
        )
    kwargs = {}
    for name, f in fields.items():
        key_path = _join(path, name)
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{source}: {key_path}: required key is missing")
            continue
        value = _convert(hints[name], data[name], source, key_path)
        _check_bounds(f.metadata, value, source, key_path)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{source}: {path or cls.__name__}: {e}") from e


def _convert_tagged(classes: list[type], value: Any, source: str, path: str) -> Any:
    """A union of dataclasses told apart by the mapping's ``type`` key (each class's ``TYPE``)."""
    by_tag = {c.TYPE: c for c in classes}
    if not isinstance(value, dict):
        raise _fail(source, path, "a mapping with a 'type' key", value)
    tag = value.get("type")
    if tag not in by_tag:
        raise _fail(source, _join(path, "type"), "one of " + ", ".join(repr(t) for t in by_tag), tag)
    return _build_dataclass(by_tag[tag], {k: v for k, v in value.items() if k != "type"}, source, path)


def _check_bounds(meta: Any, value: Any, source: str, path: str) -> None:
    items = value if isinstance(value, tuple) else (value,)
    for name, op in BOUNDS.items():
        if name not in meta:
            continue
        b = meta[name]
        for v in items:
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                ok = {"ge": v >= b, "gt": v > b, "le": v <= b, "lt": v < b}[name]
                if not ok:
                    raise _fail(source, path, f"a number {op} {b}", value)


def _convert(tp: Any, value: Any, source: str, path: str) -> Any:
    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _build_dataclass(tp, value, source, path)
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:
            return _convert(rest[0], value, source, path)
        if all(dataclasses.is_dataclass(a) and hasattr(a, "TYPE") for a in rest):
            return _convert_tagged(rest, value, source, path)
        raise TypeError(f"config: unsupported union {tp}")
    if origin is Literal:
        choices = get_args(tp)
        if value not in choices or isinstance(value, bool) != isinstance(choices[0], bool):
            raise _fail(source, path, "one of " + ", ".join(repr(c) for c in choices), value)
        return value
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise _fail(source, path, "a list", value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, source, f"{path}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise _fail(source, path, f"a list of {len(args)} values", value)
        return tuple(_convert(a, v, source, f"{path}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if tp is bool:
        if not isinstance(value, bool):
            raise _fail(source, path, "true or false", value)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(source, path, "an integer", value)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise _fail(source, path, "a finite number", value)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise _fail(source, path, "a string", value)
        return value
    raise TypeError(f"config: unsupported field type {tp!r} at {path}")
