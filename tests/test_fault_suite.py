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
