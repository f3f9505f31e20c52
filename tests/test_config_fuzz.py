"""Configuration fuzzing: mutated settings files (tools/faults/config_fuzz.py) through ``mavvo check-config``.

Every file is either accepted or refused with exit 2 and one line that names the file (and, for a bad
value, the key); never a traceback, a crash or a runaway allocation. Accepted files hold only values
within every key's bounds. The fast run (``make test``) tries 150 files; ``make faults`` tries 1200.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mavvo.cli import main
from mavvo.service.settings import ServiceConfig, load_config
from tools.faults.config_fuzz import KINDS, mutated_config


@st.composite
def mutated_files(draw) -> bytes:
    """One settings file from the shared generator (tools/faults/config_fuzz.py), its seed drawn."""
    return mutated_config(draw(st.integers(min_value=0, max_value=2**32 - 1)))[1]


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
        assert all(math.isfinite(x) and abs(x) < 1e9 for x in _numbers(cfg)), (
            "an accepted file holds an unbounded number"
        )
    else:
        assert code == 2, err
        assert err.count("\n") == 1 and err.startswith(f"mavvo: {f}") and "Traceback" not in err, err


def _fuzz(examples: int):
    @settings(
        max_examples=examples, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck), database=None
    )
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
            elif any(
                x in (int, float)
                for x in (t, *typing.get_args(t), *[a for g in typing.get_args(t) for a in typing.get_args(g)])
            ):
                yield f"{prefix}{f.name}", f.metadata

    unbounded = [key for key, md in walk(ServiceConfig, "") if "le" not in md and "lt" not in md]
    assert unbounded == []


def test_the_generator_makes_every_kind_and_repeats_itself():
    kinds = {mutated_config(seed)[0] for seed in range(200)}
    assert kinds == set(KINDS)
    assert mutated_config(17) == mutated_config(17) and mutated_config(17) != mutated_config(18)
