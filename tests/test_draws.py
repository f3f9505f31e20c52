"""The report over draws of the scenarios' noise (mavvo/sim/scenarios/draws.py): tables from summaries as
``mavvo sim --json`` prints them, and the markdown section it rewrites."""

from __future__ import annotations

import pytest

from mavvo.sim.scenarios.draws import BEGIN, END, main, report, write_section


def _summary(
    nees: float, inside: float, end_m: float, step_m: float | None, path_m: float = 80.0, heading_deg: float = 0.5
) -> dict:
    return {
        "path_length_m": path_m,
        "resets": 0 if step_m is None else 2,
        "ate_rmse_m": 0.05,
        "vehicle": {
            "nees_median": nees,
            "nees_inside_99_fraction": inside,
            "drift_within_3x_fraction": 1.0,
            "fc_end_error_m": end_m,
            "largest_reset_step_m": step_m,
            "heading_end_error_deg": heading_deg,
        },
    }


def test_the_report_gives_the_own_seed_and_the_median_and_range_over_draws():
    draws = {
        "faults": {
            "own": _summary(1.2, 0.94, 0.4, 0.02),
            "101": _summary(0.8, 0.98, 0.8, 0.05, heading_deg=1.25),
            "102": _summary(1.0, 0.96, 0.2, None),
        },
        "hover": {"own": _summary(0.3, 0.99, 0.1, None, path_m=3.0)},
    }
    text = report(draws, "2026-11-23")
    assert text.startswith(BEGIN) and text.endswith(END)
    assert "| faults | 80.0 | 2 | 0.050 | 0.40 m (0.50%) | 0.02 m | 0.50 deg | 1.20 | 94.0% | 100% |" in text
    assert "| hover | 3.0 | 0 | 0.050 | 0.10 m | - | 0.50 deg | 0.30 | 99.0% | 100% |" in text  # no % of a 3 m path
    # over draws: median (range); the largest end error is 0.8 m of 80 m; the largest heading error and
    # reset step over all draws
    assert (
        "| faults | 3 | 1.00 (0.80-1.20) | 96.0% (94.0-98.0%) | 100% | 0.40 m (0.20-0.80 m) | 1.00% | 1.25 deg | 0.05 m |"
        in text
    )
    assert (
        "| hover | 1 | 0.30 (0.30-0.30) | 99.0% (99.0-99.0%) | 100% | 0.10 m (0.10-0.10 m) | - | 0.50 deg | no reset |"
        in text
    )
    assert "seeds: own, 101, 102" in text


def test_the_section_is_replaced_between_its_markers(tmp_path):
    doc = tmp_path / "service.md"
    doc.write_text(f"before\n{BEGIN}\nold table\n{END}\nafter\n")
    write_section(doc, f"{BEGIN}\nnew table\n{END}")
    assert doc.read_text() == f"before\n{BEGIN}\nnew table\n{END}\nafter\n"


@pytest.mark.parametrize(
    "args, message",
    [
        (["--scenarios", "nowhere"], "--scenarios: nowhere: not a shipped scenario"),
        (["--seeds", "own,-3"], "--seeds: -3: expected integers >= 0"),
        (["--jobs", "0"], "--jobs: expected at least 1, got 0"),
    ],
)
def test_bad_arguments_are_named(args, message, capsys):
    with pytest.raises(SystemExit) as e:
        main(args)
    assert e.value.code == 2 and message in capsys.readouterr().err


def test_a_failed_flight_is_named_and_the_run_exits_1(monkeypatch, capsys):
    import mavvo.sim.scenarios.draws as draws

    def fly(task):  # runs on a worker process of the sweep engine
        if task[1] == "101":
            raise ValueError("a broken flight")
        return _summary(1.0, 0.97, 0.2, None)

    monkeypatch.setattr(draws, "fly", fly)
    assert main(["--scenarios", "hover", "--seeds", "own,101", "--jobs", "1"]) == 1
    assert "draws: hover seed 101: ValueError: a broken flight" in capsys.readouterr().err
