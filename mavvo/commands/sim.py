"""``mavvo sim``: the service flown against the simulated flight controller and camera, or the
simulated flight controller alone (``--fc-only``). ``sim`` is imported only when the command runs."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import signal
import threading
from collections import Counter
from pathlib import Path
from typing import Any

from mavvo.commands.run import with_record
from mavvo.errors import ConfigError, LinkError
from mavvo.service.settings import ServiceConfig, load_config

log = logging.getLogger(__name__)

_DRAIN_S = 0.2  # simulated (real) seconds of serving after a stop
_PROGRESS_EVERY_S = 5.0
_DEFAULT_SCENARIO = "figure_eight"


def add_parser(sub: Any) -> None:
    s = sub.add_parser(
        "sim",
        help="run the service against the simulated drone and print how close it came to the truth",
        description=(
            "Fly a simulated drone: the mavvo service talks MAVLink 2 over UDP on 127.0.0.1 to a simulated flight "
            "controller and reads frames rendered by a simulated camera, then the estimates the flight controller "
            "received are compared with the truth. Lockstep (as fast as the computer allows; the same estimates on every run, bit for bit, "
            "however loaded the computer, docs/service.md) "
            "unless --realtime. With --fc-only, only the simulated flight controller runs, in real time, on --mavlink, "
            "for any MAVLink client (a ground station, a script, or mavvo run with camera.source sim:SCENARIO)."
        ),
    )
    s.add_argument(
        "--scenario",
        default=_DEFAULT_SCENARIO,
        help=f"a shipped scenario name or a .yaml path (see --list); default {_DEFAULT_SCENARIO}",
    )
    s.add_argument("--list", action="store_true", help="list the shipped scenarios and exit")
    s.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="stop after S seconds of flight (default: the scenario's length; --fc-only: until stopped)",
    )
    s.add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="N",
        help="draw the scenario's noise (the camera's pixels, the flight controller's attitude and sensors) with this seed instead of its own; the world's "
        "textures stay. Figures such as the share inside the 99%% ellipse move by a few points from one draw to another: compare several",
    )
    s.add_argument("--realtime", action="store_true", help="run at wall-clock speed instead of lockstep")
    s.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="FILE",
        help="service settings to use (the scenario sets camera, mounting and link); default: the built-in defaults",
    )
    s.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")
    s.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="where the report goes (default mavvo-sim-out/SCENARIO; with --fc-only: none)",
    )
    s.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="DIR",
        help="record the flight (as mavvo run --record does) with its ground truth, for mavvo replay",
    )
    s.add_argument("--fc-only", action="store_true", help="run only the simulated flight controller")
    s.add_argument(
        "--forward",
        default=None,
        metavar="udpout:HOST:PORT",
        help="the flight controller forwards what the service sends it to this ground-station port (watch it with mavvo monitor)",
    )
    s.add_argument(
        "--mavlink",
        default="udpin:127.0.0.1:14550",
        help="--fc-only: where the flight controller listens: udpin:HOST:PORT or tcpin:HOST:PORT (udpout:/tcp: connect out); default udpin:127.0.0.1:14550",
    )
    s.add_argument(
        "--time-source",
        choices=("auto", "timesync", "arrival", "usec"),
        default="auto",
        help="--fc-only: evaluate estimates at their usec stamp mapped through the client's TIMESYNC requests (timesync), at their "
        "arrival (clients that do not send TIMESYNC; the error includes their latency), or at usec read as simulation time; "
        "auto (default): timesync when the client sent TIMESYNC requests, else arrival",
    )
    s.set_defaults(handler=main)


def main(args: argparse.Namespace) -> int:
    from mavvo.sim.scenarios.loader import load_scenario, scenario_names  # sim is loaded only for this command

    if args.list:
        for name in scenario_names():
            print(f"{name:18s} {load_scenario(name).description}")
        return 0
    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        raise ConfigError(f"--duration: expected a positive number of seconds, got {args.duration}")
    scenario = load_scenario(args.scenario)
    if args.seed is not None:
        if args.seed < 0:
            raise ConfigError(f"--seed: expected an integer >= 0, got {args.seed}")
        scenario = dataclasses.replace(scenario, seed=args.seed)
    if args.fc_only:
        return _fc_only(scenario, args)
    return _sim_service(scenario, args)


def _sim_service(scenario: Any, args: argparse.Namespace) -> int:
    from mavvo.sim.scenarios.service_run import run_daemon_in_sim

    base = with_record(load_config(args.config) if args.config is not None else ServiceConfig(), args.record)
    out = args.out if args.out is not None else Path("mavvo-sim-out") / scenario.name
    run = run_daemon_in_sim(
        scenario, base, realtime=args.realtime, duration_s=args.duration, out_dir=out, forward_url=args.forward
    )
    summary = run.summary()
    summary["report_dir"] = str(out) if run.evaluation is not None else None
    summary["plot"] = str(out / "evaluation.png") if run.evaluation is not None else None
    if args.json:
        print(json.dumps(summary))
        return 0
    print(
        f"{scenario.name}: {summary['frames']} frames, {summary['estimates_received']} estimates received by the flight controller, "
        f"{run.resets} resets; {run.duration_s:.1f} s flown in {run.wall_s:.1f} s"
    )
    if run.evaluation is None:
        print("too few estimates to evaluate")
        return 0
    ev = run.evaluation
    print(
        f"ATE {ev.ate_se3_m['rmse']:.3f} m RMSE ({ev.ate_se3_rmse_percent_of_path:.2f}% of {ev.path_length_m:.1f} m), "
        f"Sim(3) {ev.ate_sim3_m['rmse']:.3f} m at scale {ev.sim3_scale:.3f}"
    )
    v = run.safety
    if v.fc_end_error_m is not None and v.path_length_m > 0:
        step = (
            "no reset" if v.largest_reset_step_m is None else f"largest step at a reset {v.largest_reset_step_m:.2f} m"
        )
        print(
            f"what the vehicle felt (no alignment): its EKF {v.fc_end_error_m:.2f} m off at the end "
            f"({100 * v.fc_end_error_m / v.path_length_m:.2f}% of the path), {step}, heading {v.heading_end_error_deg:.2f} deg off"
        )
    if v.nees_median is not None and v.drift_within_3x_fraction is not None:
        print(
            f"covariance over 1 s: median NEES {v.nees_median:.2f}, {100 * v.nees_inside_99_fraction:.0f}% inside the 99% ellipse; "
            f"true error within 3x VO_DRIFT for {100 * v.drift_within_3x_fraction:.0f}% of reports"
        )
    print(f"plot: {summary['plot']}")
    if run.recording is not None:
        print(f"recording: {run.recording} (replay it: mavvo replay {run.recording})")
        dropped = {k: v for k, v in run.daemon.counters.items() if k.startswith("record_dropped") and v}
        if dropped:  # only in real time: in lockstep the recorder holds the simulation back instead
            what = ", ".join(f"{v} {k.removeprefix('record_dropped_')}" for k, v in dropped.items())
            print(f"recording: {what} dropped (the disk did not keep up); its replay will differ from this flight")
    return 0


def _fc_only(scenario: Any, args: argparse.Namespace) -> int:
    from mavvo.evaluation.report import vision_estimates, write_report
    from mavvo.sim.scenarios.flight import Simulation

    try:
        sim = Simulation(scenario, args.mavlink, realtime=True, forward_url=args.forward)
    except LinkError as e:
        raise ConfigError(f"--mavlink {e}") from e
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    until = args.duration if args.duration is not None else math.inf
    log.info(
        "simulated flight controller on %s, scenario %s (%.0f s of trajectory); Ctrl-C stops",
        args.mavlink,
        scenario.name,
        sim.trajectory.duration_s,
    )
    try:
        next_report = _PROGRESS_EVERY_S
        while not stop.is_set() and sim.clock.now_s() < until:
            sim.serve(stop, until_s=min(until, next_report))
            if sim.clock.now_s() >= next_report:
                log.info(
                    "t=%.0f s sent %s received %s",
                    sim.clock.now_s(),
                    _counts(sim.fc.sent_counts),
                    _counts(_received(sim)),
                )
                next_report += _PROGRESS_EVERY_S
        # A bounded drain: what the client sent just before the stop is still in the socket (on a
        # loaded machine the last estimates were lost, and with them the evaluation).
        sim.serve(threading.Event(), until_s=sim.clock.now_s() + _DRAIN_S)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        sim.close()
    log.info("stopped at t=%.1f s; received %s", sim.clock.now_s(), _counts(_received(sim)))
    if args.out is not None:
        tlog = sim.fc.save_tlog(args.out / "received.tlog")
        print(f"received messages: {tlog}")
        source = args.time_source
        if source == "auto":
            source = "timesync" if sim.fc.client_clock_s else "arrival"
        # A request's transit only adds: the smallest (arrival - ts1) is the client's clock offset, to the fastest transit.
        offset = min(sim.fc.client_clock_s) if source == "timesync" and sim.fc.client_clock_s else 0.0
        est = vision_estimates(sim.fc.received, "arrival" if source == "arrival" else "usec", usec_offset_s=offset)
        log.info(
            "estimates evaluated at %s",
            {
                "timesync": f"their usec plus the client's clock offset {offset:+.3f} s (TIMESYNC)",
                "arrival": "their arrival",
                "usec": "their usec as simulation time",
            }[source],
        )
        if len(est) >= 3:
            ev = write_report(args.out, est, sim.truth_at(est.timestamps_s), title=scenario.name)
            print(
                f"{len(est)} vision estimates: ATE {ev.ate_se3_m['rmse']:.3f} m RMSE (SE(3)), {ev.ate_sim3_m['rmse']:.3f} m (Sim(3)), "
                f"{ev.ate_se3_rmse_percent_of_path:.2f}% of {ev.path_length_m:.1f} m; report in {args.out}"
            )
        else:
            print(f"{len(est)} vision estimates received: too few to evaluate")
    return 0


def _received(sim: Any) -> dict[str, int]:
    return Counter(r.type for r in sim.fc.received)


def _counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(d.items())) or "nothing"
