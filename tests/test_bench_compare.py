"""The benchmarks' comparison with the best peer: success counts and paired median differences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.compare import TrialErrors, best_peer_cells, paired_medians


def test_found_needs_both_errors_under_their_bars() -> None:
    e = TrialErrors(np.array([0.1, 1.9, 2.0, 0.5, math.inf]), np.array([9.9, 0.3, 0.3, 10.0, 0.1]))
    assert e.found == 2  # the first two; 2.0 deg of rotation and 10.0 deg of translation are misses


def test_a_constant_gap_has_an_interval_of_exactly_that_gap() -> None:
    rng = np.random.default_rng(5)
    peer = rng.uniform(0.01, 0.2, 101)
    p = paired_medians(peer + 0.003, peer, seed=1)
    assert p.ours == pytest.approx(np.sort(peer)[50] + 0.003)
    assert p.peer == pytest.approx(np.sort(peer)[50])
    assert p.diff_low == pytest.approx(0.003) and p.diff_high == pytest.approx(0.003)
    assert p.ours_lower_share == 0.0


def test_two_draws_of_the_same_noise_give_an_interval_around_zero() -> None:
    rng = np.random.default_rng(6)
    a, b = np.abs(rng.normal(0, 0.05, 400)), np.abs(rng.normal(0, 0.05, 400))
    p = paired_medians(a, b, seed=2)
    assert p.diff_low < 0 < p.diff_high
    assert 0.4 < p.ours_lower_share < 0.6


def test_failures_count_in_the_medians_and_not_in_the_share() -> None:
    ours = np.array([0.1, 0.1, 0.1, math.inf, 0.1])
    peer = np.array([0.2, 0.2, 0.2, 0.2, math.inf])
    p = paired_medians(ours, peer, seed=3)
    assert p.ours == pytest.approx(0.1) and p.peer == pytest.approx(0.2)
    assert p.ours_lower_share == 1.0  # of the three trials where both gave a pose


def test_unpaired_errors_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="paired_medians.*shapes"):
        paired_medians(np.zeros(3), np.zeros(4))


def test_the_cells_name_the_best_peer_for_each_figure() -> None:
    ours = TrialErrors(np.full(4, 0.05), np.full(4, 0.5))
    peers = {
        "finds most": TrialErrors(np.array([0.06, 0.06, 0.06, 0.06]), np.array([0.9, 0.9, 0.9, 0.9])),
        "lowest rotation": TrialErrors(np.full(4, 0.04), np.array([0.8, 0.8, 11.0, 11.0])),
        "lowest translation": TrialErrors(np.array([0.07, 0.07, math.inf, math.inf]), np.array([0.4, 0.4, 0.4, 0.4])),
    }
    success, rotation, translation = best_peer_cells(ours, peers)
    assert success == "4 vs 4 (finds most)"  # the lowest-rotation peer finds 2, the lowest-translation one 2
    assert rotation.startswith("0.0500 vs 0.0400 (lowest rotation): +0.0100 to +0.0100")
    assert translation.startswith("0.5000 vs 0.4000 (lowest translation): +0.1000 to +0.1000")
    # Each peer found its first two trials only (translation 11 deg, no rotation): the common medians are over those.
    assert rotation.endswith("lower on 0%; on the 2 both found 0.0500 vs 0.0400")
    assert translation.endswith("lower on 0%; on the 2 both found 0.5000 vs 0.4000")


def test_the_common_medians_are_over_the_trials_both_found() -> None:
    """A trial that neither found (mavvo's wrong pose, the peer's none) moves the all-trials median by a
    rank and leaves the common one alone."""
    peer = TrialErrors(np.array([0.040, 0.041, 0.050, math.inf]), np.full(4, 0.3))
    without = TrialErrors(np.array([0.042, 0.043, 0.048, math.inf]), np.full(4, 0.3))
    wrong_pose = TrialErrors(np.array([0.042, 0.043, 0.048, 0.001]), np.array([0.3, 0.3, 0.3, 12.0]))
    rot_without = best_peer_cells(without, {"peer": peer})[1]
    rot_wrong = best_peer_cells(wrong_pose, {"peer": peer})[1]
    assert rot_without.startswith("0.0455 vs 0.0455") and rot_wrong.startswith("0.0425 vs 0.0455")
    assert rot_without.endswith("on the 3 both found 0.0430 vs 0.0410") and rot_wrong.endswith(
        "on the 3 both found 0.0430 vs 0.0410"
    )


def test_nothing_found_by_both_is_said() -> None:
    cells = best_peer_cells(
        TrialErrors(np.array([5.0, 0.1]), np.array([1.0, 20.0])),
        {"peer": TrialErrors(np.array([0.1, 0.1]), np.array([1.0, 20.0]))},
    )
    assert cells[0] == "0 vs 1 (peer)"
    assert cells[1].endswith("none found by both")


def test_no_peer_is_refused() -> None:
    with pytest.raises(ValueError, match="no peer"):
        best_peer_cells(TrialErrors(np.zeros(2), np.zeros(2)), {})


def test_the_small_quad_table_tells_the_draws_mavvo_ends_closer_and_the_gap_interval() -> None:
    from benchmarks.small_quad import against_mavvo_cell

    peer_end = [0.05, 0.12, 0.03, 0.08, 0.06]
    runs = [{"mavvo": {"end": e - 0.01}, "script": {"end": e}} for e in peer_end]
    assert against_mavvo_cell(runs, "script") == "-0.01 to -0.01 m; 5 of 5"
    assert against_mavvo_cell(runs, "mavvo") == "-"
    for i in (1, 3):  # two draws of five far behind: counted, and the interval reaches past zero (a
        runs[i]["mavvo"]["end"] = 0.50  # resample holds three of them or more one time in three)
    cell = against_mavvo_cell(runs, "script")
    assert cell.endswith("; 3 of 5") and cell.startswith("-0.01 to +")
