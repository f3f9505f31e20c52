"""``mavvo inspect PATH``: what ``mavvo replay`` would use from a log, a recording, a video or image
folder, or a data set, and what is missing. ``sim`` is imported only when the command runs."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Sequence


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "inspect",
        help="show what replay would read from a log, recording, video or data set, and what is missing",
        description=(
            "Read PATH as mavvo replay would and report, without replaying: each time series (attitude, rangefinder, height, "
            "position, camera triggers, frames, IMU, ground truth) with its source message or file, count, rate, time range and "
            "longest gap; how the attitude pairs with frames (a slow telemetry stream pairs every frame, degraded); the overlap of "
            "frames and attitude when both are known; and what a replay lacks, with the option that supplies it. PATH is a "
            "flight-controller log (.tlog, dataflash .bin or text .log, PX4 .ulg), a mavvo recording, a video file or image folder, "
            "or a EuRoC/ASL folder. Exit 0 when replay can run, 1 when something it needs is missing, 2 when PATH cannot be read."
        ),
    )
    p.add_argument("path", type=Path, metavar="PATH")
    p.add_argument(
        "--video",
        type=Path,
        default=None,
        metavar="PATH",
        help="log: the flight's video file or image folder, to count its frames and check the overlap",
    )
    p.add_argument("--fps", type=float, default=None, help="an image folder without timestamps.txt: its frame rate")
    p.add_argument(
        "--offset-s",
        type=float,
        default=None,
        metavar="S",
        help="log: the log's time at the video's time zero, for the overlap",
    )
    p.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="FILE",
        help="log: the camera settings replay will be given (only checked for presence)",
    )
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.set_defaults(handler=main)


def _fmt(x: float | None, unit: str = "", digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}{unit}"


def series_table(series: Sequence[Any]) -> list[str]:
    """The series as aligned text rows under a header, each column as wide as its longest cell (a PX4
    topic's field path or a long dataflash message name must not push the numbers out of line)."""
    header = ("series", "source", "count", "rate", "from", "to", "longest gap")
    rows = [header] + [
        (
            s.name,
            s.source,
            str(s.count),
            _fmt(s.rate_hz, " Hz", 1),
            _fmt(s.start_s, " s"),
            _fmt(s.end_s, " s"),
            _fmt(s.longest_gap_s, " s"),
        )
        for s in series
    ]
    widths = [max(len(r[k]) for r in rows) for k in range(len(header))]
    left = 2  # names left-aligned, numbers right-aligned
    return [
        " ".join(c.ljust(w) if k < left else c.rjust(w) for k, (c, w) in enumerate(zip(r, widths))).rstrip()
        for r in rows
    ]


def main(args: argparse.Namespace) -> int:
    from mavvo.offline.inspect import inspect_source

    ins = inspect_source(args.path, video=args.video, fps=args.fps, offset_s=args.offset_s, config=args.config)
    if args.json:
        print(json.dumps(ins.to_dict()))
        return 0 if ins.replayable else 1
    print(f"{ins.path}: {ins.kind}")
    for line in series_table(ins.series):
        print(f"  {line}")
    for key, value in ins.facts.items():
        print(f"  {key}: {value}")
    for problem in ins.problems:
        print(f"  problem: {problem}")
    for m in ins.missing:
        print(f"  {'MISSING' if m.blocking else 'lacking'}: {m.what}; {m.fix}")
    print("  replay: " + ("can run" if ins.replayable else "cannot run until the MISSING items are given"))
    return 0 if ins.replayable else 1
