"""``mavvo camera``: list the cameras mavvo can open, or measure one for a few seconds."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path
from typing import Any

from mavvo.errors import ConfigError
from mavvo.service.camera import open_source
from mavvo.service.camera_probe import CameraMeasurement, advice, list_cameras, measure
from mavvo.service.settings import ServiceConfig, load_config
from mavvo.service.timing import MonotonicClock


def add_parser(sub: Any) -> None:
    c = sub.add_parser(
        "camera",
        help="list cameras, or measure one (rate, lost frames, stamps, exposure)",
        description="Without --source or --config: list the V4L2 devices, libcamera cameras and GStreamer support mavvo can use. "
        "The listing shows each camera's modes (format, size, frame rates). "
        "With them: read the camera for --seconds and report its real frame rate, frames lost, how far the stamps lie before "
        "delivery (and how steadily), the brightness, exposure and gain as they move, and advice. Exit 0: measured or listed; 1: no frame; 2: bad input.",
    )
    c.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="settings file whose camera: section to measure (default: the defaults)",
    )
    c.add_argument(
        "--source",
        metavar="SOURCE",
        help="camera.source to measure instead of the config's, e.g. /dev/video0, picamera2:0, 'gst:videotestsrc is-live=true'",
    )
    c.add_argument("--seconds", type=float, default=5.0, help="how long to measure (default 5)")
    c.add_argument("--json", action="store_true", help="print JSON instead of a table")
    c.set_defaults(handler=main)


def _fmt(x: object) -> str:
    if isinstance(x, float):
        return "-" if math.isnan(x) else f"{x:.2f}"
    return "-" if x is None else str(x)


def _table(rows: list[tuple[str, str]]) -> str:
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)


def _print_measurement(m: CameraMeasurement, tips: list[str]) -> None:
    rows = [
        ("source", m.source),
        ("frames", f"{m.frames} in {m.seconds:g} s"),
        ("size", f"{m.width_px}x{m.height_px} px"),
        ("frame rate", f"{_fmt(m.rate_hz)} Hz"),
        ("frames lost", str(m.dropped)),
        ("stamp age", f"{_fmt(m.age_median_ms)} ms median, {_fmt(m.age_spread_ms)} ms spread (5-95%)"),
        ("brightness", f"{_fmt(m.brightness_min)}-{_fmt(m.brightness_max)} of 255"),
    ]
    if not math.isnan(m.exposure_us_max):
        rows.append(("exposure", f"{m.exposure_us_min:.0f}-{m.exposure_us_max:.0f} us"))
    if not math.isnan(m.gain_max):
        rows.append(("gain", f"{m.gain_min:.2f}-{m.gain_max:.2f}"))
    if m.ended:
        rows.append(("ended", m.ended))
    print(_table(rows))
    for tip in tips:
        print(f"advice: {tip}")


def main(args: argparse.Namespace) -> int:
    if not (args.seconds > 0 and math.isfinite(args.seconds)):
        raise ConfigError(f"--seconds: expected a positive number of seconds, got {args.seconds}")
    if args.source is None and args.config is None:
        cams = list_cameras()
        if args.json:
            print(json.dumps([dataclasses.asdict(c) for c in cams], indent=2))
        else:
            width = max(len(c.source) for c in cams)
            for c in cams:
                print(f"{c.source.ljust(width)}  {c.kind:<9}  {c.description}")
                for mode in c.modes:
                    print(f"{'':{width}}    mode: {mode}")
        return 0
    cfg = load_config(args.config) if args.config is not None else ServiceConfig()
    options = cfg.camera if args.source is None else dataclasses.replace(cfg.camera, source=args.source)
    clock = MonotonicClock()
    source = open_source(options, clock)
    try:
        m = measure(source, clock, args.seconds, options.source)
    finally:
        source.close()
    tips = advice(m, options)
    if args.json:
        clean = {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in m.as_dict().items()}
        print(json.dumps({**clean, "advice": tips}, indent=2))
    else:
        _print_measurement(m, tips)
    return 0 if m.frames else 1
