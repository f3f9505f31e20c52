"""The fault suite's cases (tools/faults/suite.py) against the real service: the quick ones in ``make
test``, every case behind the ``faults`` marker (``make faults`` runs them and writes the table)."""

from __future__ import annotations

import math

import pytest

from tools.faults.suite import CASES, FAST_CASES, Outcome, markdown_table

EXPECTED = {
    "folder_vanishes": Outcome.RESTARTED,
    "port_in_use": Outcome.REFUSED,
}


@pytest.mark.parametrize("name", FAST_CASES)
def test_fast_case(name, tmp_path):
    row = CASES[name](tmp_path)
    assert row.outcome is EXPECTED.get(name, Outcome.SURVIVED), row
    assert math.isnan(row.longest_gap_s) or row.longest_gap_s <= 1.0, row


@pytest.mark.slow
@pytest.mark.faults
@pytest.mark.parametrize("name", [n for n in CASES if n not in FAST_CASES])
def test_slow_case(name, tmp_path):
    row = CASES[name](tmp_path)
    assert row.outcome is EXPECTED.get(name, Outcome.SURVIVED), row
    assert math.isnan(row.longest_gap_s) or row.longest_gap_s <= 1.0, row


def test_the_table_has_a_row_per_case_and_says_what_failed():
    from tools.faults.suite import FaultRow

    rows = [
        FaultRow("a", Outcome.SURVIVED, 0.25, "nothing", "x"),
        FaultRow("b", Outcome.FAILED, float("nan"), "all", "y"),
    ]
    table = markdown_table(rows).splitlines()
    assert table[2] == "| a | survived | 0.25 s | nothing | x |" and table[3] == "| b | failed | - | all | y |"


def test_cases_run_on_the_sweep_engine_and_a_case_that_breaks_is_a_failed_row():
    """The suite's cases go through mavvo.fleet.engine (a real local cluster, one worker process), as
    make draws and mavvo batch do; a case that raises becomes a failed row naming why, in order."""
    from tools.faults.suite import run_cases

    seen: list[str] = []
    rows = run_cases(["port_in_use", "no_such_case"], progress=seen.append, jobs=1)
    assert [r.case for r in rows][1] == "no_such_case" and rows[0].outcome is Outcome.REFUSED
    assert rows[1].outcome is Outcome.FAILED and "the case itself failed" in rows[1].details
    assert sorted(seen) == ["no_such_case: failed", "port_in_use: refused"]
