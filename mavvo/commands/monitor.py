"""``mavvo monitor``: a live view of what the service tells the ground station."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from mavvo.errors import ConfigError, LinkError
from mavvo.service.link_options import check_udp_port_free, parse_url
from mavvo.service.mavlink import mavutil
from mavvo.service.messages import STATE_CODES
from mavvo.service.monitor import Monitor, render

_REFRESH_S = 1.0


def add_parser(sub: Any) -> None:
    m = sub.add_parser(
        "monitor",
        help="watch the service's state, quality, latency and messages live",
        description="Listen where the service's MAVLink messages arrive (a ground station's port of mavlink-router, the flight "
        "controller's forwarding, or mavvo sim --forward) and show, about once a second, the state, quality, inliers, "
        "latency, drift, resets and the last STATUSTEXT lines. Ctrl-C ends it. Exit 1 if nothing was heard from mavvo.",
    )
    m.add_argument(
        "--mavlink",
        default="udpin:0.0.0.0:14550",
        metavar="URL",
        help="where to listen or connect (default udpin:0.0.0.0:14550, a ground station's port)",
    )
    m.add_argument(
        "--duration", type=float, default=None, metavar="S", help="end after S seconds (default: until Ctrl-C)"
    )
    m.add_argument(
        "--plot",
        type=Path,
        default=None,
        metavar="PNG",
        help="write a timeline of quality, inliers, latency, drift and state here at the end",
    )
    m.set_defaults(handler=main)


def _plot(monitor: Monitor, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tl = monitor.timeline
    t = [p.t_s for p in tl]
    fig, axes = plt.subplots(5, 1, figsize=(10, 9), sharex=True)
    for ax, (label, values) in zip(
        axes,
        (
            ("state", [p.state_code for p in tl]),
            ("quality", [p.quality for p in tl]),
            ("inliers", [p.inliers for p in tl]),
            ("latency, ms", [p.latency_ms for p in tl]),
            ("drift (1 sigma), m", [p.drift_m for p in tl]),
        ),
    ):
        ax.plot(t, values, drawstyle="steps-post" if label == "state" else "default")
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    # The state axis names its states: whole codes only, each labelled (messages.STATE_CODES).
    codes = sorted(STATE_CODES.items(), key=lambda kv: kv[1])
    axes[0].set_yticks([c for _, c in codes], [str(state) for state, _ in codes], fontsize=7)
    axes[0].set_ylim(codes[0][1] - 0.5, codes[-1][1] + 0.5)
    fig.align_ylabels(axes)
    axes[-1].set_xlabel("monitor time, s")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(args: argparse.Namespace) -> int:
    parse_url(args.mavlink)  # ConfigError naming the URL when it is none of the forms
    # pymavlink binds with SO_REUSEADDR: on a port another process holds (a ground station, the flight
    # controller's own) both would start and split the datagrams, silently. Said before opening.
    check_udp_port_free(args.mavlink)
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration: expected a positive number of seconds, got {args.duration}")
    try:
        conn = mavutil().mavlink_connection(args.mavlink, source_system=255, source_component=190)
    except (OSError, ValueError) as e:
        raise LinkError(f"--mavlink {args.mavlink}: cannot open: {getattr(e, 'strerror', None) or e}") from e
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    tty = sys.stdout.isatty()
    monitor = Monitor()
    t0 = time.monotonic()
    next_refresh = t0
    try:
        while not stop.is_set():
            now = time.monotonic() - t0
            if args.duration is not None and now >= args.duration:
                break
            msg = conn.recv_match(blocking=True, timeout=0.1)
            if msg is not None and msg.get_type() != "BAD_DATA":
                monitor.add(msg, time.monotonic() - t0)
            if time.monotonic() >= next_refresh:
                next_refresh += _REFRESH_S
                text = render(monitor.snapshot(time.monotonic() - t0), args.mavlink)
                if tty:
                    sys.stdout.write("\x1b[H\x1b[2J" + text)  # one screen, redrawn
                else:
                    sys.stdout.write(
                        text.splitlines()[0]
                        + " | "
                        + " | ".join(line.strip() for line in text.splitlines()[1:5])
                        + "\n"
                    )
                sys.stdout.flush()
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        conn.close()
    final = monitor.snapshot(time.monotonic() - t0)
    sys.stdout.write(render(final, args.mavlink))
    if args.plot is not None:
        if not monitor.timeline:
            print(f"mavvo monitor: no health values heard: {args.plot} not written", file=sys.stderr)
        else:
            _plot(monitor, args.plot)
            print(f"timeline: {args.plot}", file=sys.stderr)
    return 0 if final.heard else 1  # nothing heard from mavvo: a script can tell
