"""``mavvo batch FLIGHT...``: many logged flights under one or several settings, on Dask. The fleet and
offline layers are imported only when the command runs."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

_METRICS = (
    "end_error_m",
    "end_error_horizontal_m",
    "ate_rmse_m",
    "resets",
    "failed_frames",
    "coverage",
    "cpu_ms_per_frame",
    "odometry_cpu_ms_per_frame",
)


def add_parser(sub: Any) -> None:
    bp = sub.add_parser(
        "batch",
        help="replay many flights under one or several settings, on all local cores or a Dask cluster",
        description=(
            "Replay every FLIGHT under every settings set, each pair one task on a Dask worker (local worker processes, "
            "one per core, by default; --scheduler reaches a running cluster). A FLIGHT is a mavvo recording or EuRoC "
            "folder, a glob of them, or a manifest (a .yaml with 'flights:', a list of paths or {source, video, config, "
            "fps, offset_s, ground_truth} for flight-controller logs). Settings: --config files (the keys given replace "
            "the flight's own) crossed with --grid (dotted keys with lists of values). Writes results.jsonl (a row per "
            "task, as it comes: a batch started again resumes), results.csv/.json, summary.csv/.json (median and worst "
            "per settings, the best by --metric) and batch.png into --out. A flight that cannot be read, or whose "
            "worker dies twice, is one failed row. Needs the fleet extra: pip install 'mavvo[fleet]'."
        ),
    )
    bp.add_argument("flights", nargs="+", metavar="FLIGHT")
    bp.add_argument(
        "--config", type=Path, action="append", default=[], metavar="FILE", help="a settings set (repeatable)"
    )
    bp.add_argument(
        "--grid", type=Path, default=None, metavar="FILE", help="YAML of dotted keys and value lists, crossed"
    )
    bp.add_argument("--out", type=Path, default=Path("mavvo-batch-out"), metavar="DIR", help="default mavvo-batch-out")
    bp.add_argument(
        "--workers", type=int, default=None, metavar="N", help="local worker processes (default: the core count)"
    )
    bp.add_argument("--scheduler", default=None, metavar="URL", help="a running Dask scheduler, e.g. tcp://host:8786")
    bp.add_argument(
        "--metric", default="end_error_m", choices=_METRICS, help="what 'best settings' means (default end_error_m)"
    )
    bp.add_argument("--retry-failed", action="store_true", help="run the tasks that failed last time again")
    bp.add_argument("--dry-run", action="store_true", help="list the tasks and exit")
    bp.set_defaults(handler=main)


def _progress_printer() -> Any:
    tty = sys.stderr.isatty()

    def show(p: Any) -> None:
        eta = "" if p.eta_s is None else f", ETA {int(p.eta_s) // 60}m{int(p.eta_s) % 60:02d}s"
        line = f"batch: {p.done + p.failed}/{p.total} tasks, {p.failed} failed{eta}"
        print(("\r" + line) if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True)

    return show


def main(args: argparse.Namespace) -> int:
    from mavvo.errors import ConfigError
    from mavvo.fleet.batch import (
        Journal,
        expand_flights,
        expand_settings,
        make_tasks,
        replay_task,
        task_row,
        write_tables,
    )
    from mavvo.fleet.engine import quiet_dask_logs, run_tasks

    if not log.isEnabledFor(logging.DEBUG):  # Dask's own INFO lines (workers starting, closing) drown the progress
        quiet_dask_logs()

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: expected at least 1, got {args.workers}")
    flights = expand_flights(args.flights)
    settings = expand_settings(args.config, args.grid)
    tasks = make_tasks(flights, settings)
    journal = Journal(args.out)
    previous = {r["key"]: r for r in journal.rows()}
    skip = {k for k, r in previous.items() if r["status"] == "ok" or not args.retry_failed}
    todo = [t for t in tasks if t.key not in skip]
    print(
        f"batch: {len(flights)} flights x {len(settings)} settings = {len(tasks)} tasks; "
        f"{len(tasks) - len(todo)} finished before, {len(todo)} to run",
        file=sys.stderr,
    )
    if args.dry_run:
        for t in todo:
            print(f"{t.key}  {t.settings.name}  {t.flight.source}")
        return 0
    by_key = {t.key: t for t in todo}

    def record(outcome: Any) -> None:
        row = task_row(by_key[outcome.key], outcome.result, outcome.error)
        journal.append(row)
        if outcome.error is not None:
            log.warning("%s under %s failed: %s", row["flight"], row["settings"], outcome.error)

    status = None
    if todo:
        status = run_tasks(
            replay_task,
            [(t.key, t) for t in todo],
            record,
            workers=args.workers,
            scheduler=args.scheduler,
            progress=_progress_printer(),
        )
        if sys.stderr.isatty():
            print(file=sys.stderr)
    keys = {t.key for t in tasks}
    rows = [r for r in journal.rows() if r["key"] in keys]
    summary = write_tables(args.out, rows, args.metric)
    failed = sum(1 for r in rows if r["status"] != "ok")
    best = summary["best"]
    if best is not None:
        print(
            f"best by {args.metric}: {best['settings']} (median {best[args.metric + '_median']:.4g}, worst {best[args.metric + '_worst']:.4g})"
        )
    print(f"{len(rows)} of {len(tasks)} tasks done, {failed} failed; tables in {args.out}")
    if status is not None and status.cancelled:
        print(
            f"mavvo: batch interrupted: {status.cancelled} tasks not run; run the same command again to resume",
            file=sys.stderr,
        )
        return 130
    return 1 if failed else 0
