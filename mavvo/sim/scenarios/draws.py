"""Every shipped scenario over several draws of its noise: what the vehicle would feel, median and range.

    python -m mavvo.sim.scenarios.draws [--scenarios hover,faults] [--seeds own,101,102,103,104] [--jobs 2]
                                   [--markdown docs/service.md]

One flight of a scenario is one draw of its noise (camera pixels, the flight controller's attitude and
sensors), and the 1 s covariance figures move by several points from one draw to another. Each
(scenario, seed) is one lockstep flight (the same on every run), flown as one task of the sweep engine
(:mod:`mavvo.fleet.engine`, the same path as ``mavvo batch``) on ``--jobs`` local worker processes;
``own`` is the scenario's own seed. The report has two tables: the own seed's flights, and the median
and range over all draws of each scenario.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import statistics
import sys
from pathlib import Path
from typing import Any, Mapping

from mavvo.fleet.engine import Outcome, run_tasks
from mavvo.sim.scenarios.loader import load_scenario, scenario_names

BEGIN, END = "<!-- draws:begin -->", "<!-- draws:end -->"
OWN = "own"
DEFAULT_SEEDS = (OWN, "101", "102", "103", "104")

Summary = Mapping[str, Any]  # what `mavvo sim --json` prints


def fly(task: tuple[str, str]) -> Summary:
    """One lockstep flight of ``(scenario, seed)``, on a worker: its summary (``mavvo sim --json``'s)."""
    from mavvo.sim.scenarios.service_run import run_daemon_in_sim

    name, seed = task
    scenario = load_scenario(name)
    if seed != OWN:
        scenario = dataclasses.replace(scenario, seed=int(seed))
    return run_daemon_in_sim(scenario).summary()


def _end_error(s: Summary) -> str:
    v, path = s["vehicle"], s["path_length_m"]
    return f"{v['fc_end_error_m']:.2f} m" + (f" ({100 * v['fc_end_error_m'] / path:.2f}%)" if path > 10 else "")


def own_seed_table(flights: Mapping[str, Summary]) -> list[str]:
    """Markdown rows, one flight per scenario: what the vehicle would feel, without alignment."""
    rows = [
        "| scenario | path m | resets | ATE m | EKF end error | largest reset step | heading at the end | NEES median | inside 99% | within 3x `VO_DRIFT` |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, s in flights.items():
        v = s["vehicle"]
        step = "-" if v["largest_reset_step_m"] is None else f"{v['largest_reset_step_m']:.2f} m"
        rows.append(
            f"| {name} | {s['path_length_m']:.1f} | {s['resets']} | {s['ate_rmse_m']:.3f} | {_end_error(s)} | {step} | "
            f"{v['heading_end_error_deg']:.2f} deg | {v['nees_median']:.2f} | {100 * v['nees_inside_99_fraction']:.1f}% | "
            f"{100 * v['drift_within_3x_fraction']:.0f}% |"
        )
    return rows


def _spread(values: list[float], fmt: str, unit: str = "") -> str:
    return f"{statistics.median(values):{fmt}}{unit} ({min(values):{fmt}}-{max(values):{fmt}}{unit})"


def draws_table(draws: Mapping[str, list[Summary]]) -> list[str]:
    """Markdown rows, one per scenario: median and range over its draws."""
    rows = [
        "| scenario | draws | median NEES: median (range) | inside the 99% ellipse | within 3x `VO_DRIFT` (lowest) | EKF end error | "
        "EKF end error, % of the path (largest) | heading at the end (largest) | largest reset step (largest) |",
        "|---|---:|---|---|---:|---|---:|---:|---|",
    ]
    for name, flights in draws.items():
        vs = [s["vehicle"] for s in flights]
        steps = [v["largest_reset_step_m"] for v in vs if v["largest_reset_step_m"] is not None]
        paths = [s["path_length_m"] for s in flights]
        percent = max(100 * v["fc_end_error_m"] / p for v, p in zip(vs, paths)) if min(paths) > 10 else None
        rows.append(
            f"| {name} | {len(flights)} | {_spread([v['nees_median'] for v in vs], '.2f')} | "
            f"{_spread([100 * v['nees_inside_99_fraction'] for v in vs], '.1f', '%')} | "
            f"{100 * min(v['drift_within_3x_fraction'] for v in vs):.0f}% | {_spread([v['fc_end_error_m'] for v in vs], '.2f', ' m')} | "
            f"{'-' if percent is None else f'{percent:.2f}%'} | {max(v['heading_end_error_deg'] for v in vs):.2f} deg | "
            f"{'no reset' if not steps else f'{max(steps):.2f} m'} |"
        )
    return rows


def report(draws: Mapping[str, Mapping[str, Summary]], date: str) -> str:
    """The markdown section: the own seed's flights and the spread over all draws."""
    seeds = sorted({seed for flights in draws.values() for seed in flights}, key=lambda x: (x != OWN, x))
    own = {name: flights[OWN] for name, flights in draws.items() if OWN in flights}
    lines = [BEGIN, ""]
    if own:
        lines += [
            f"Each shipped scenario with its own seed (`mavvo sim --scenario S --json`, lockstep, {date}; the `vehicle` block: "
            "the simulated EKF fusing what mavvo sent, against the truth, without any alignment):",
            "",
            *own_seed_table(own),
            "",
        ]
    lines += [
        f"The same over {len(seeds)} draws of the noise (seeds: {', '.join(seeds)}; `own` is the scenario's), median and range "
        "(`python -m mavvo.sim.scenarios.draws`, `make draws`):",
        "",
        *draws_table({n: list(f.values()) for n, f in draws.items()}),
        "",
        END,
    ]
    return "\n".join(lines)


def write_section(path: Path, section: str) -> None:
    """Replace the text between the markers in ``path`` (or append the section)."""
    text = path.read_text() if path.exists() else ""
    if BEGIN in text and END in text:
        text = text[: text.index(BEGIN)] + section + text[text.index(END) + len(END) :]
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    names = scenario_names()
    parser.add_argument(
        "--scenarios",
        default=",".join(names),
        help=f"comma-separated scenario names (default: all shipped: {', '.join(names)})",
    )
    parser.add_argument(
        "--seeds",
        default=",".join(DEFAULT_SEEDS),
        help=f"comma-separated seeds, '{OWN}' for the scenario's own (default {','.join(DEFAULT_SEEDS)})",
    )
    parser.add_argument(
        "--jobs", type=int, default=2, help="worker processes, flights at a time (default 2; each takes a core)"
    )
    parser.add_argument(
        "--markdown", type=Path, help="rewrite this section of this markdown file (between the draws markers)"
    )
    args = parser.parse_args(argv)
    scenarios = [s for s in args.scenarios.split(",") if s]
    seeds = [s for s in args.seeds.split(",") if s]
    unknown = [s for s in scenarios if s not in names]
    if unknown:
        parser.error(f"--scenarios: {', '.join(unknown)}: not a shipped scenario (expected some of {', '.join(names)})")
    bad = [s for s in seeds if s != OWN and not (s.isdigit())]
    if bad:
        parser.error(f"--seeds: {', '.join(bad)}: expected integers >= 0 or '{OWN}'")
    if args.jobs < 1:
        parser.error(f"--jobs: expected at least 1, got {args.jobs}")
    tasks = [(name, seed) for seed in seeds for name in scenarios]
    draws: dict[str, dict[str, Summary]] = {name: {} for name in scenarios}
    failures: list[str] = []

    def record(o: Outcome) -> None:
        name, seed = o.key  # type: ignore[misc]
        if o.error is not None:
            failures.append(f"{name} seed {seed}: {o.error}")
        else:
            draws[name][seed] = o.result
        print(
            f"[{sum(map(len, draws.values())) + len(failures)}/{len(tasks)}] {name} seed {seed} done", file=sys.stderr
        )

    status = run_tasks(fly, [(t, t) for t in tasks], record, workers=args.jobs)
    if failures or status.cancelled:
        for f in failures:
            print(f"draws: {f}", file=sys.stderr)
        return 1
    draws = {name: dict(sorted(f.items(), key=lambda kv: (kv[0] != OWN, kv[0]))) for name, f in draws.items()}
    section = report(draws, dt.date.today().isoformat())
    print(section)
    if args.markdown:
        write_section(args.markdown, section)
        print(f"wrote {args.markdown}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
