"""The README's quoted outputs of ``make sim`` and of replaying its flight against what ``mavvo sim`` and
``mavvo replay`` print now, so the page cannot go stale: the same lines word for word; counts within 2%
(a quoted 0 exactly); measured figures within what another CPU's rounding or a small change moves them
(a quarter, or 0.02 of the unit, 0.1 deg); the wall and CPU times and the folders free."""

from __future__ import annotations

import re
from pathlib import Path

from mavvo.cli import main

ROOT = Path(__file__).resolve().parents[1]
_NUMBER = re.compile(r"-?\d+(?:\.\d+)?")


_FOLDERS = (
    (re.compile(r"^recording \S+: "), "recording REC: "),
    (re.compile(r"^report: \S+ \("), "report: OUT ("),
)
_FREE_FROM = (" flown in ", " replayed in ")  # what follows is the wall time (and the CPU's speed)


def quoted_output(after: str) -> list[str]:
    """The lines of the README's first plain code block (an output, not a ```sh one) after ``after``."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    fences = list(re.finditer(r"^```(\w*)\n", text, re.M))  # alternately opening and closing
    at = text.index(after)
    for k in range(0, len(fences) - 1, 2):
        opening, closing = fences[k], fences[k + 1]
        if opening.start() > at and not opening.group(1):
            return text[opening.end() : closing.start()].splitlines()
    raise AssertionError(f"no output block after {after!r} in README.md")


def _folders_free(line: str) -> str:
    for pattern, name in _FOLDERS:
        line = pattern.sub(name, line)
    return line


def differences(quoted: list[str], printed: list[str]) -> list[str]:
    """Where ``printed`` does not bear out ``quoted`` (empty: it does)."""
    out = []
    if len(quoted) != len(printed):
        return [f"{len(quoted)} lines quoted, {len(printed)} printed"]
    for q, p in zip(map(_folders_free, quoted), map(_folders_free, printed)):
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
        wall = min([q.index(m) for m in _FREE_FROM if m in q], default=len(q))
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
    r = ["recording recordings/20261128-040548: 949 of 949 frames; 47.4 s replayed in 11.4 s; odometry 4.4 ms"]
    assert (
        differences(
            r, ["recording /tmp/x/20261201-101010: 949 of 949 frames; 47.4 s replayed in 30.0 s; odometry 9.9 ms"]
        )
        == []
    )
    assert differences(r, [r[0].replace("949 of", "900 of")]) != []  # folders and times free, counts not
    h = ["heading 0.00 deg off"]
    assert differences(h, ["heading 0.08 deg off"]) == [] and differences(h, ["heading 0.20 deg off"]) != []


def test_the_quoted_outputs_of_make_sim_and_of_its_replay_are_what_mavvo_prints(tmp_path, capsys) -> None:
    assert main(["sim", "--out", str(tmp_path / "out"), "--record", str(tmp_path / "rec")]) == 0
    printed = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert sum(line.startswith("recording: ") for line in printed) == 1  # --record's own line
    assert differences(quoted_output("It ends with"), [x for x in printed if not x.startswith("recording: ")]) == []
    (recording,) = (tmp_path / "rec").iterdir()
    assert main(["replay", str(recording), "--out", str(tmp_path / "replay1")]) == 0
    printed = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert differences(quoted_output("mavvo replay recordings/"), printed) == []
