"""The README's quoted output of ``make sim`` against what ``mavvo sim`` prints now, so the page cannot go
stale: the same lines word for word; counts within 2% (a quoted 0 exactly); measured figures within what
another CPU's rounding or a small change moves them (a quarter, or 0.02 of the unit, 0.1 deg); the wall
time and the plot's folder free."""

from __future__ import annotations

import re
from pathlib import Path

from mavvo.cli import main

ROOT = Path(__file__).resolve().parents[1]
_NUMBER = re.compile(r"-?\d+(?:\.\d+)?")


def quoted_sim_output() -> list[str]:
    """The lines of the README's code block that follows "It ends with"."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = text[text.index("It ends with") :]
    block = block[block.index("```\n") + 4 :]
    return block[: block.index("```")].splitlines()


def differences(quoted: list[str], printed: list[str]) -> list[str]:
    """Where ``printed`` does not bear out ``quoted`` (empty: it does)."""
    out = []
    if len(quoted) != len(printed):
        return [f"{len(quoted)} lines quoted, {len(printed)} printed"]
    for q, p in zip(quoted, printed):
        if (
            q.startswith("plot: ")
            and p.startswith("plot: ")
            and q.endswith("evaluation.png")
            and p.endswith("evaluation.png")
        ):
            continue
        if _NUMBER.sub("#", q) != _NUMBER.sub("#", p):
            out.append(f"quoted {q!r}, printed {p!r}")
            continue
        wall = q.index(" flown in ") if " flown in " in q else len(q)
        for mq, mp in zip(_NUMBER.finditer(q), _NUMBER.finditer(p)):
            if mq.start() > wall:
                continue  # the wall time
            a, b = float(mq.group()), float(mp.group())
            # Counts and percentages (integers): within 2% (an estimate more or less on another CPU), a
            # quoted 0 exactly (no reset); figures: within a quarter or 0.02 of their unit, angles 0.1 deg
            # (a heading error of hundredths is rounding's to move).
            floor = 0.1 if q[mq.end() :].startswith(" deg") else 0.02
            tol = (max(0.02 * abs(a), 1.0) if a else 0.0) if "." not in mq.group() else max(0.25 * abs(a), floor)
            if abs(a - b) > tol:
                out.append(f"{mq.group()} quoted, {mp.group()} printed: {p!r}")
    return out


def test_the_check_finds_a_stale_line() -> None:
    q = ["figure_eight: 949 frames, 0 resets; 47.4 s flown in 14.4 s", "ATE 0.047 m RMSE"]
    assert differences(q, ["figure_eight: 949 frames, 0 resets; 47.4 s flown in 99.0 s", "ATE 0.050 m RMSE"]) == []
    assert differences(q, [q[0].replace("949", "900"), q[1]]) != []  # a count
    assert differences(q, [q[0].replace("0 resets", "1 resets"), q[1]]) != []  # a quoted 0
    assert differences(q, [q[0], "ATE 0.090 m RMSE"]) != []  # a figure off by more than a quarter
    assert differences(q, [q[0], "ATE 0.047 m RMS error"]) != []  # the words
    h = ["heading 0.00 deg off"]
    assert differences(h, ["heading 0.08 deg off"]) == [] and differences(h, ["heading 0.20 deg off"]) != []


def test_make_sims_quoted_output_is_what_mavvo_sim_prints(tmp_path, capsys) -> None:
    assert main(["sim", "--out", str(tmp_path / "out")]) == 0
    printed = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert differences(quoted_sim_output(), printed) == []
