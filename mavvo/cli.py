"""The ``mavvo`` command line: the only place that parses argv, maps errors to exit codes and exits.

Exit codes: 0 done (also after SIGINT/SIGTERM), 1 a runtime failure, 2 bad arguments or configuration.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import threading
from collections import Counter
from pathlib import Path
from typing import Sequence

from mavvo.errors import ConfigError, LinkError, MavvoError

log = logging.getLogger("mavvo")

_PROGRESS_EVERY_S = 5.0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mavvo", description="Visual odometry for drones over MAVLink.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser(
        "sim",
        help="run the simulated drone (flight controller and camera)",
        description=(
            "Run a simulated drone. With --fc-only, the simulated flight controller alone speaks MAVLink 2 on "
            "--mavlink in real time, flying its scenario until stopped (Ctrl-C), for any MAVLink client: a "
            "ground station, a script, or mavvo run on another machine. It streams nothing but HEARTBEAT until "
            "asked with MAV_CMD_SET_MESSAGE_INTERVAL, like a freshly booted ArduPilot."
        ),
    )
    s.add_argument("--scenario", default="hover", help="a shipped scenario name or a .yaml path (see --list); default hover")
    s.add_argument("--list", action="store_true", help="list the shipped scenarios and exit")
    s.add_argument("--fc-only", action="store_true", help="run only the simulated flight controller")
    s.add_argument(
        "--mavlink", default="udpin:127.0.0.1:14550",
        help="where the flight controller listens: udpin:HOST:PORT or tcpin:HOST:PORT (udpout:/tcp: connect out); default udpin:127.0.0.1:14550",
    )
    s.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: until stopped)")
    s.add_argument("--out", type=Path, default=None, metavar="DIR", help="on stop, write received.tlog and, given vision estimates, an evaluation")
    s.add_argument(
        "--time-source", choices=("arrival", "usec"), default="arrival",
        help="evaluate estimates at their arrival time (default; clients on their own clock) or at their usec stamp read as simulation time",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "sim":
            return _sim(args)
    except ConfigError as e:
        print(f"mavvo: {e}", file=sys.stderr)
        return 2
    except MavvoError as e:
        print(f"mavvo: {e}", file=sys.stderr)
        return 1
    return 2


def _sim(args: argparse.Namespace) -> int:
    from sim.scenario import load_scenario, scenario_names  # sim is loaded only for this command

    if args.list:
        for name in scenario_names():
            print(f"{name:18s} {load_scenario(name).description}")
        return 0
    if not args.fc_only:
        print(
            "mavvo sim: running the daemon against the simulator arrives with the service; "
            "use --fc-only to run the simulated flight controller for another MAVLink client",
            file=sys.stderr,
        )
        return 2
    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        raise ConfigError(f"--duration: expected a positive number of seconds, got {args.duration}")
    return _fc_only(load_scenario(args.scenario), args)


def _fc_only(scenario, args: argparse.Namespace) -> int:
    from sim.report import vision_estimates, write_report
    from sim.simulation import Simulation

    try:
        sim = Simulation(scenario, args.mavlink, realtime=True)
    except LinkError as e:
        raise ConfigError(f"--mavlink {e}") from e
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    until = args.duration if args.duration is not None else math.inf
    log.info("simulated flight controller on %s, scenario %s (%.0f s of trajectory); Ctrl-C stops", args.mavlink, scenario.name, sim.trajectory.duration_s)
    try:
        next_report = _PROGRESS_EVERY_S
        while not stop.is_set() and sim.clock.now_s() < until:
            sim.serve(stop, until_s=min(until, next_report))
            if sim.clock.now_s() >= next_report:
                log.info("t=%.0f s sent %s received %s", sim.clock.now_s(), _counts(sim.fc.sent_counts), _counts(_received(sim)))
                next_report += _PROGRESS_EVERY_S
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        sim.close()
    log.info("stopped at t=%.1f s; received %s", sim.clock.now_s(), _counts(_received(sim)))
    if args.out is not None:
        tlog = sim.fc.save_tlog(args.out / "received.tlog")
        print(f"received messages: {tlog}")
        est = vision_estimates(sim.fc.received, args.time_source)
        if len(est) >= 3:
            ev = write_report(args.out, est, sim.truth_at(est.timestamps_s), title=scenario.name)
            print(
                f"{len(est)} vision estimates: ATE {ev.ate_se3_m['rmse']:.3f} m RMSE (SE(3)), {ev.ate_sim3_m['rmse']:.3f} m (Sim(3)), "
                f"{ev.ate_se3_rmse_percent_of_path:.2f}% of {ev.path_length_m:.1f} m; report in {args.out}"
            )
        else:
            print(f"{len(est)} vision estimates received: too few to evaluate")
    return 0


def _received(sim) -> dict[str, int]:
    return Counter(r.type for r in sim.fc.received)


def _counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(d.items())) or "nothing"


if __name__ == "__main__":
    sys.exit(main())
