"""Configuration fuzzing: mutated settings files through ``mavvo check-config``.

Every file is either accepted or refused with exit 2 and one line that names the file (and, for a bad
value, the key); never a traceback, a crash or a runaway allocation. Accepted files hold only values
within every key's bounds. The fast run (``make test``) tries 150 files; ``make faults`` tries 1200.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import typing
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mavvo.cli import main
from mavvo.service.settings import ServiceConfig, load_config

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = yaml.safe_load((ROOT / "config" / "default.yaml").read_text())


def _leaves(d: dict, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out = []
    for k, v in d.items():
        if isinstance(v, dict):
            out.extend(_leaves(v, prefix + (k,)))
        else:
            out.append(prefix + (k,))
    return out


LEAVES = _leaves(DEFAULT)
SECTIONS = sorted(k for k, v in DEFAULT.items() if isinstance(v, dict))

values = st.one_of(
    st.sampled_from([1e30, -1e30, float("nan"), float("inf"), 0, -1, 2**63, 1e-300, True, None, "", "x" * 5000, [], {}, [1, 2], {"a": 1}]),
    st.integers(min_value=-(10**12), max_value=10**12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=40),
)


@st.composite
def mutated_files(draw) -> bytes:
    """One settings file: the default with a mutation of one of several kinds."""
    kind = draw(st.sampled_from(["value", "value", "value", "delete", "unknown_key", "duplicate_section", "alias", "bytes", "truncate", "type_of_section"]))
    data = copy.deepcopy(DEFAULT)
    if kind in ("value", "delete"):
        path = draw(st.sampled_from(LEAVES))
        node = data
        for k in path[:-1]:
            node = node[k]
        if kind == "delete":
            del node[path[-1]]
        else:
            node[path[-1]] = draw(values)
    elif kind == "unknown_key":
        data[draw(st.sampled_from(SECTIONS))][draw(st.text(min_size=1, max_size=12))] = draw(values)
    elif kind == "type_of_section":
        data[draw(st.sampled_from(SECTIONS))] = draw(values)
    text = yaml.safe_dump(data, allow_unicode=True).encode("utf-8")
    if kind == "duplicate_section":
        section = draw(st.sampled_from(SECTIONS))
        text += f"{section}: {{}}\n".encode()
    elif kind == "alias":
        text = b'a: &a ["x","x","x","x","x","x","x","x","x"]\nb: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]\nc: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]\n' + text
    elif kind == "bytes":
        at = draw(st.integers(min_value=0, max_value=len(text)))
        text = text[:at] + draw(st.binary(min_size=1, max_size=16)) + text[at:]
    elif kind == "truncate":
        text = text[: draw(st.integers(min_value=0, max_value=len(text)))]
    return text


def _numbers(obj) -> list[float]:
    if dataclasses.is_dataclass(obj):
        return [x for f in dataclasses.fields(obj) for x in _numbers(getattr(obj, f.name))]
    if isinstance(obj, tuple):
        return [x for v in obj for x in _numbers(v)]
    if isinstance(obj, (int, float)) and not isinstance(obj, bool):
        return [float(obj)]
    return []


def _check(tmp_path: Path, capsys, text: bytes) -> None:
    f = tmp_path / "fuzzed.yaml"
    f.write_bytes(text)
    code = main(["check-config", str(f)])
    out, err = capsys.readouterr()
    if code == 0:
        cfg = load_config(f)
        assert isinstance(cfg, ServiceConfig)
        assert all(math.isfinite(x) and abs(x) < 1e9 for x in _numbers(cfg)), "an accepted file holds an unbounded number"
    else:
        assert code == 2, err
        assert err.count("\n") == 1 and err.startswith(f"mavvo: {f}") and "Traceback" not in err, err


def _fuzz(examples: int):
    @settings(max_examples=examples, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    @given(text=mutated_files())
    def run(tmp_path, capsys, text):
        _check(tmp_path, capsys, text)

    return run


def test_config_fuzz_fast(tmp_path, capsys):
    _fuzz(150)(tmp_path, capsys)


@pytest.mark.slow
@pytest.mark.faults
def test_config_fuzz_1200(tmp_path, capsys):
    _fuzz(1200)(tmp_path, capsys)


def test_every_numeric_key_has_an_upper_bound():
    """60 keys accepted 1e30 before; now each number has a physical bound (an upper one, at least)."""
    def walk(cls, prefix: str):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            t = hints[f.name]
            if dataclasses.is_dataclass(t):
                yield from walk(t, f"{prefix}{f.name}.")
            elif any(x in (int, float) for x in (t, *typing.get_args(t), *[a for g in typing.get_args(t) for a in typing.get_args(g)])):
                yield f"{prefix}{f.name}", f.metadata

    unbounded = [key for key, md in walk(ServiceConfig, "") if "le" not in md and "lt" not in md]
    assert unbounded == []
