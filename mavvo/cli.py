"""The ``mavvo`` command line: the only place that parses argv, maps errors to exit codes and exits.

Exit codes: 0 a clean stop (also after SIGINT/SIGTERM), 2 bad arguments or configuration, 1 anything
else, always with one readable line on stderr (the traceback only with ``--log-level debug``).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
from collections import Counter
from pathlib import Path
from typing import Any, Sequence

from mavvo import __version__
from mavvo.errors import ConfigError, LinkError, MavvoError

log = logging.getLogger("mavvo")

_PROGRESS_EVERY_S = 5.0
_DEFAULT_SCENARIO = "figure_eight"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mavvo", description="Visual odometry for drones over MAVLink: roll/pitch from the flight controller, pose back to it.")
    p.add_argument("--version", action="version", version=f"mavvo {__version__}")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"), help="log detail on stderr (default info)")
    p.add_argument("-v", "--verbose", action="store_true", help="same as --log-level debug")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser(
        "run", help="run the service (what systemd starts)",
        description="Run the visual-odometry service: read ATTITUDE from the flight controller, frames from the camera, "
        "send VISION_POSITION_ESTIMATE back. Stops cleanly on SIGTERM or Ctrl-C.",
    )
    r.add_argument("--config", required=True, type=Path, metavar="FILE", help="the YAML settings (see config/default.yaml for every key)")
    r.add_argument("--record", type=Path, default=None, metavar="DIR", help="record the flight for mavvo replay into a new folder under DIR (sets record.dir)")

    c = sub.add_parser("check-config", help="check a settings file and exit", description="Load a settings file strictly and report the first problem, with its key path.")
    c.add_argument("file", type=Path, metavar="FILE")

    s = sub.add_parser(
        "sim",
        help="run the service against the simulated drone and print how close it came to the truth",
        description=(
            "Fly a simulated drone: the mavvo service talks MAVLink 2 over UDP on 127.0.0.1 to a simulated flight "
            "controller and reads frames rendered by a simulated camera, then the estimates the flight controller "
            "received are compared with the truth. Lockstep (as fast as the computer allows, the same on every run) "
            "unless --realtime. With --fc-only, only the simulated flight controller runs, in real time, on --mavlink, "
            "for any MAVLink client (a ground station, a script, or mavvo run with camera.source sim:SCENARIO)."
        ),
    )
    s.add_argument("--scenario", default=_DEFAULT_SCENARIO, help=f"a shipped scenario name or a .yaml path (see --list); default {_DEFAULT_SCENARIO}")
    s.add_argument("--list", action="store_true", help="list the shipped scenarios and exit")
    s.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds of flight (default: the scenario's length; --fc-only: until stopped)")
    s.add_argument("--realtime", action="store_true", help="run at wall-clock speed instead of lockstep")
    s.add_argument("--config", type=Path, default=None, metavar="FILE", help="service settings to use (the scenario sets camera, mounting and link); default: the built-in defaults")
    s.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")
    s.add_argument("--out", type=Path, default=None, metavar="DIR", help="where the report goes (default mavvo-sim-out/SCENARIO; with --fc-only: none)")
    s.add_argument("--record", type=Path, default=None, metavar="DIR", help="record the flight (as mavvo run --record does) with its ground truth, for mavvo replay")
    s.add_argument("--fc-only", action="store_true", help="run only the simulated flight controller")
    s.add_argument(
        "--mavlink", default="udpin:127.0.0.1:14550",
        help="--fc-only: where the flight controller listens: udpin:HOST:PORT or tcpin:HOST:PORT (udpout:/tcp: connect out); default udpin:127.0.0.1:14550",
    )
    s.add_argument(
        "--time-source", choices=("arrival", "usec"), default="arrival",
        help="--fc-only: evaluate estimates at their arrival time (default; clients on their own clock) or at their usec stamp read as simulation time",
    )
    _replay_parser(sub)
    return p


def _replay_parser(sub: Any) -> None:
    rp = sub.add_parser(
        "replay",
        help="run a logged flight through the service, faster than real time, and evaluate it",
        description=(
            "Feed a logged flight to the mavvo service through the simulated flight controller and camera: the service runs "
            "its normal code path on a lockstep clock, as fast as the computer allows, with the same result every time. "
            "SOURCE is a mavvo recording (mavvo run --record), a flight-controller log (.tlog with ATTITUDE, or an ArduPilot "
            "dataflash .bin with ATT) with --video and --config, or a EuRoC/ASL dataset folder (the one holding mav0/). "
            "Writes estimate.tum, quality.csv/.png, summary.json and, with a reference, evaluation.png into --out."
        ),
    )
    rp.add_argument("source", type=Path, metavar="SOURCE")
    rp.add_argument("--config", type=Path, default=None, metavar="FILE", help="settings: for a recording or dataset, the keys given replace the recorded ones (tuning); for a log, the camera and mounting (required)")
    rp.add_argument("--video", type=Path, default=None, metavar="PATH", help="log: the flight's video file or image folder (timestamps.txt 'T_S FILENAME', else the folder's frame rate from --fps)")
    rp.add_argument("--fps", type=float, default=None, help="log with an image folder without timestamps.txt: its frame rate")
    rp.add_argument("--offset-s", type=float, default=None, metavar="S", help="log: the log's time (s since boot) at the video's time zero; default: estimated from the rotation the camera sees")
    rp.add_argument("--ground-truth", type=Path, default=None, metavar="FILE", help="reference trajectory: TUM file, or EuRoC state_groundtruth_estimate0/data.csv (default: ground_truth.tum in a recording, the dataset's own)")
    rp.add_argument("--attitude", choices=("imu", "truth"), default="imu", help="EuRoC: roll/pitch from the IMU through an attitude filter (default) or from the ground truth plus --attitude-noise-deg")
    rp.add_argument("--attitude-noise-deg", type=float, default=0.1, metavar="D", help="EuRoC --attitude truth: roll/pitch noise, 1 sigma (default 0.1)")
    rp.add_argument("--out", type=Path, default=None, metavar="DIR", help="where the report goes (default mavvo-replay-out/NAME)")
    rp.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else getattr(logging, args.log_level.upper())
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "run":
            return _run(args)
        if args.command == "check-config":
            return _check_config(args)
        if args.command == "replay":
            return _replay(args)
        return _sim(args)
    except ConfigError as e:
        print(f"mavvo: {e}", file=sys.stderr)
        return 2
    except MavvoError as e:
        print(f"mavvo: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C before the service installed its handler
        return 0
    except Exception as e:  # a bug: one line for the operator, the traceback for the developer
        log.debug("unexpected error", exc_info=True)
        print(f"mavvo: unexpected {type(e).__name__}: {e} (--log-level debug shows where)", file=sys.stderr)
        return 1


def _sim_camera(argument: str, options: Any, clock: Any) -> Any:
    """``camera.source: sim:SCENARIO``: the simulator's rendered camera, in real time on the host clock."""
    from sim.camera_source import scenario_camera  # sim is loaded only when asked for

    return scenario_camera(argument, clock)


def _run(args: argparse.Namespace) -> int:
    from mavvo.daemon import Daemon
    from mavvo.settings import load_config

    config = _with_record(load_config(args.config), args.record)
    daemon = Daemon(config, schemes={"sim": _sim_camera})
    daemon.run()
    return 0


def _with_record(config: Any, record: Path | None) -> Any:
    """``config`` recording into ``record`` when given."""
    import dataclasses

    return config if record is None else dataclasses.replace(config, record=dataclasses.replace(config.record, dir=str(record)))


def _check_config(args: argparse.Namespace) -> int:
    from mavvo.settings import load_config

    cfg = load_config(args.file)
    print(f"{args.file}: ok (link {cfg.link.url}, camera {cfg.camera.source} {cfg.camera.width_px}x{cfg.camera.height_px}, scale from {cfg.odometry.scale.source})")
    return 0


def _sim(args: argparse.Namespace) -> int:
    from sim.scenario import load_scenario, scenario_names  # sim is loaded only for this command

    if args.list:
        for name in scenario_names():
            print(f"{name:18s} {load_scenario(name).description}")
        return 0
    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        raise ConfigError(f"--duration: expected a positive number of seconds, got {args.duration}")
    scenario = load_scenario(args.scenario)
    if args.fc_only:
        return _fc_only(scenario, args)
    return _sim_service(scenario, args)


def _sim_service(scenario: Any, args: argparse.Namespace) -> int:
    from mavvo.settings import ServiceConfig, load_config
    from sim.service import run_daemon_in_sim

    base = _with_record(load_config(args.config) if args.config is not None else ServiceConfig(), args.record)
    out = args.out if args.out is not None else Path("mavvo-sim-out") / scenario.name
    run = run_daemon_in_sim(scenario, base, realtime=args.realtime, duration_s=args.duration, out_dir=out)
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
    print(f"plot: {summary['plot']}")
    if run.recording is not None:
        print(f"recording: {run.recording} (replay it: mavvo replay {run.recording})")
    return 0


def _replay(args: argparse.Namespace) -> int:
    from sim.replay import empty_result, replay
    from sim.replay_report import write_replay_report
    from sim.replay_sources import open_replay_source

    inp = open_replay_source(
        args.source, config=args.config, video=args.video, fps=args.fps, offset_s=args.offset_s, ground_truth=args.ground_truth,
        attitude=args.attitude, attitude_noise_deg=args.attitude_noise_deg,
    )
    out = args.out if args.out is not None else Path("mavvo-replay-out") / (args.source.resolve().name or "replay")
    for note, value in inp.notes.items():
        log.info("%s: %s", note, value)
    for problem in inp.problems:
        log.warning("%s", problem)
    if inp.frames and inp.messages:
        log.info("replaying %s (%s): %d frames, %d messages", inp.source, inp.kind, len(inp.frames), len(inp.messages))
        res = replay(inp, progress=lambda k, n: log.info("replay: frame %d of %d (%.0f%%)", k, n, 100.0 * k / n))
    else:
        res = empty_result()
    summary = write_replay_report(out, inp, res)
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"{inp.kind} {inp.source}: {summary['frames_replayed']} of {summary['frames']} frames, {summary['estimates_received']} estimates, "
            f"{summary['resets']} resets; {summary['duration_s']:.1f} s replayed in {summary['wall_s']:.1f} s"
        )
        if summary["identical_to_recording"] is not None:
            same = "identical to" if summary["identical_to_recording"] else "DIFFERENT from"
            print(f"estimates {same} the recorded flight's ({summary['recorded_estimates']} recorded)")
        ev = summary["evaluation"]
        if ev is not None:
            print(
                f"vs {summary['reference']}: ATE {ev['ate_se3_m']['rmse']:.3f} m RMSE ({ev['ate_se3_rmse_percent_of_path']:.2f}% of "
                f"{ev['path_length_m']:.1f} m), Sim(3) {ev['ate_sim3_m']['rmse']:.3f} m at scale {ev['sim3_scale']:.3f}"
            )
        print(f"report: {out} ({', '.join(summary['files'])})")
    for problem in inp.problems:
        print(f"mavvo: {problem}", file=sys.stderr)
    if res.stopped and inp.frames:  # Ctrl-C: a clean stop, like the service's
        print(f"mavvo: replay interrupted after {res.frames_replayed} of {len(inp.frames)} frames; the report covers those", file=sys.stderr)
    return 1 if inp.problems else 0


def _fc_only(scenario: Any, args: argparse.Namespace) -> int:
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


def _received(sim: Any) -> dict[str, int]:
    return Counter(r.type for r in sim.fc.received)


def _counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(d.items())) or "nothing"


if __name__ == "__main__":
    sys.exit(main())
