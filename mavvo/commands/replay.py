"""``mavvo replay SOURCE``: a logged flight run through the service and evaluated. ``sim`` is imported
only when the command runs."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def add_parser(sub: Any) -> None:
    rp = sub.add_parser(
        "replay",
        help="run a logged flight through the service, faster than real time, and evaluate it",
        description=(
            "Feed a logged flight to the mavvo service through the simulated flight controller and camera: the service runs "
            "its normal code path on a lockstep clock, as fast as the computer allows, with the same result every time. "
            "SOURCE is a mavvo recording (mavvo run --record), a flight-controller log (a telemetry .tlog, an ArduPilot "
            "dataflash .bin or text .log of any firmware age, a PX4 .ulg) with --video and --config, or a EuRoC/ASL dataset "
            "folder (the one holding mav0/). mavvo inspect SOURCE shows what would be read and what is missing. "
            "Writes estimate.tum, quality.csv/.png, summary.json and, with a reference, evaluation.png into --out."
        ),
    )
    rp.add_argument("source", type=Path, metavar="SOURCE")
    rp.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="FILE",
        help="settings: for a recording or dataset, the keys given replace the recorded ones (tuning); for a log, the camera and mounting (required)",
    )
    rp.add_argument(
        "--video",
        type=Path,
        default=None,
        metavar="PATH",
        help="log: the flight's video file or image folder (timestamps.txt 'T_S FILENAME', else the folder's frame rate from --fps)",
    )
    rp.add_argument(
        "--fps", type=float, default=None, help="log with an image folder without timestamps.txt: its frame rate"
    )
    rp.add_argument(
        "--offset-s",
        type=float,
        default=None,
        metavar="S",
        help="log: the log's time (s since boot) at the video's time zero (a video file: its first frame; an image folder's timestamps.txt: its own clock, so 0 when it lists the flight controller's times); default: estimated from the rotation the camera sees",
    )
    rp.add_argument(
        "--ground-truth",
        type=Path,
        default=None,
        metavar="FILE",
        help="reference trajectory: TUM file, or EuRoC state_groundtruth_estimate0/data.csv (default: ground_truth.tum in a recording, the dataset's own)",
    )
    rp.add_argument(
        "--attitude",
        choices=("imu", "truth"),
        default="imu",
        help="EuRoC: roll/pitch from the IMU through an attitude filter (default) or from the ground truth plus --attitude-noise-deg",
    )
    rp.add_argument(
        "--attitude-noise-deg",
        type=float,
        default=0.1,
        metavar="D",
        help="EuRoC --attitude truth: roll/pitch noise, 1 sigma (default 0.1)",
    )
    rp.add_argument(
        "--out", type=Path, default=None, metavar="DIR", help="where the report goes (default mavvo-replay-out/NAME)"
    )
    rp.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")

    rp.set_defaults(handler=main)


def main(args: argparse.Namespace) -> int:
    from mavvo.offline.driver import empty_result, replay
    from mavvo.offline.report import write_replay_report
    from mavvo.offline.sources import open_replay_source

    inp = open_replay_source(
        args.source,
        config=args.config,
        video=args.video,
        fps=args.fps,
        offset_s=args.offset_s,
        ground_truth=args.ground_truth,
        attitude=args.attitude,
        attitude_noise_deg=args.attitude_noise_deg,
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
            + (
                f"; odometry {summary['odometry_cpu_ms_per_frame']:.1f} ms of CPU a frame"
                if summary["odometry_cpu_ms_per_frame"] is not None
                else ""
            )
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
        ap = summary["attitude_pairing"]
        if ap is not None and ap["degraded"]:
            print(
                f"attitude: samples up to {ap['gap_s_max']:.2f} s apart (median {ap['gap_s_median']:.3f} s): roll/pitch sigma "
                f"{ap['sigma_deg_median']:.2f} deg median, {ap['sigma_deg_p95']:.2f} deg 95th percentile; {ap['degraded']} estimates degraded for it"
            )
        print(f"report: {out} ({', '.join(summary['files'])})")
    for warning in inp.warnings:
        print(f"mavvo: warning: {warning}", file=sys.stderr)
    for problem in inp.problems:
        print(f"mavvo: {problem}", file=sys.stderr)
    if res.stopped and inp.frames:  # Ctrl-C: a clean stop, like the service's
        print(
            f"mavvo: replay interrupted after {res.frames_replayed} of {len(inp.frames)} frames; the report covers those",
            file=sys.stderr,
        )
    return 1 if inp.problems else 0
