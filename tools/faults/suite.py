"""The fault suite: each hostile or broken input of the hardening work, against the real service over
127.0.0.1, with what came of it.

Every case returns a :class:`FaultRow`: the outcome (``survived``: estimates kept flowing, no gap over
1 s that the input itself did not cause; ``restarted``: the process ended non-zero for systemd to
restart it, as it should; ``refused``: a clear error at start; ``failed``: anything else), the longest
gap between estimates the flight controller received, and what was lost. ``python -m tools.faults.suite``
(``make faults``) runs them all and prints the table (``--markdown FILE`` also writes it into
docs/reliability.md between its markers).

Where the service reads from a socket the flight controller pushes to (``udpin``), attackers send from
their own sockets on 127.0.0.1: they are what a process on the companion computer or a device on the
vehicle's network can do without the signing key.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import re
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from mavvo.cli import main as cli
from mavvo.fleet.engine import Outcome as TaskOutcome
from mavvo.fleet.engine import run_tasks
from mavvo.service.link import Link
from mavvo.service.link_options import LinkOptions
from mavvo.service.timing import MonotonicClock
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.service_run import run_daemon_in_sim
from tools.faults.config_fuzz import mutated_config
from tools.faults.harness import (
    FaultRow,
    Lines,
    Outcome,
    estimates_sent,
    flow_outcome,
    image_folder,
    longest_gap_s,
    lost,
    run_config,
    run_mavvo,
)
from tools.faults.link_cases import (
    foreign_sender_udpout,
    forged_clock,
    impostor_heartbeat,
    signing_forgery_and_replay,
    udp_flood,
)

__all__ = ["Outcome", "FaultRow", "CASES", "FAST_CASES", "run_cases", "markdown_table", "main"]


def undistortable_corners(tmp: Path) -> FaultRow:
    """A strongly distorted lens (k1 0.3, k2 -0.8) whose image corners have no bearing: before, one
    such frame killed the odometry until the process restarted."""
    sc = load_scenario("figure_eight")
    sc = replace(sc, camera=replace(sc.camera, distortion=(0.3, -0.8, 0.0, 0.0)), duration_s=20.0)
    run = run_daemon_in_sim(sc)
    gap = longest_gap_s(run)
    c = run.daemon.counters
    return FaultRow(
        "lens with undistortable corners (k1 0.3, k2 -0.8)",
        flow_outcome(run, gap),
        gap,
        lost(c, "odometry_errors", "bad_frames"),
        f"{len(run.vision_messages)} estimates, ATE {run.evaluation.ate_se3_m['rmse']:.2f} m" if run.evaluation else "",
    )


def pymavlink_imported_first(tmp: Path) -> FaultRow:
    """An embedding program imported pymavlink (MAVLink 1 by default) before mavvo."""
    code = (
        "import sys, pymavlink.mavutil\n"
        "from mavvo.cli import main\n"
        f"sys.exit(main(['sim', '--scenario', 'hover', '--duration', '9', '--json', '--out', {str(tmp / 'out')!r}]))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        return FaultRow("pymavlink imported before mavvo", Outcome.FAILED, float("nan"), "?", proc.stderr[-300:])
    s = json.loads(proc.stdout)
    ok = s["estimates_received"] > 20 and s["received"].get("VISION_POSITION_ESTIMATE", 0) == s["estimates_received"]
    return FaultRow(
        "pymavlink imported before mavvo",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        float("nan"),
        lost(s["counters"], "errors", "link_send_dropped"),
        f"{s['estimates_received']} estimates received as MAVLink 2",
    )


def full_disk_and_sighup(tmp: Path) -> FaultRow:
    """A disk that fills during the flight (a file-size limit on ``mavvo run``: its writes fail with
    EFBIG, as with ENOSPC), SIGHUP before it, SIGTERM at the end (before: the recorder died silently,
    SIGTERM exited 1 and the recording had no readable frame; SIGHUP killed the process). The flight
    controller is ``mavvo sim --fc-only`` in its own process, the camera the simulator's ``sim:hover``."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    rec = tmp / "rec"
    sc = load_scenario("hover")
    cam = sc.camera
    cfg = run_config(
        tmp,
        (
            f"camera: {{source: 'sim:hover', rate_hz: {cam.rate_hz}, width_px: {cam.width_px}, height_px: {cam.height_px}, fx_px: {cam.fx_px}, "
            f"fy_px: {cam.fy_px}, cx_px: {cam.cx_px}, cy_px: {cam.cy_px}}}\n"
            f"mounting: {{R_body_cam: {[[float(x) for x in r] for r in cam.R_body_cam()]}}}\n"
            f"link: {{url: 'udpout:127.0.0.1:{port}'}}\nservice: {{state_file: '', health_log_interval_s: 1.0}}\n"
            f"record: {{dir: '{rec}', frames: jpg, jpeg_quality: 50, min_free_mb: 0}}\n"  # frames well under the limit; the .tlog reaches it
        ),
    )

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))

    fc = Lines(run_mavvo("sim", "--fc-only", "--scenario", "hover", "--mavlink", f"udpin:127.0.0.1:{port}"))
    try:
        fc.wait_for("simulated flight controller on", 60)
        lines = Lines(run_mavvo("run", "--config", str(cfg), preexec=limit))
        hup = lines.wait_for("-> tracking", 120)
        if hup:
            lines.proc.send_signal(signal.SIGHUP)
        stopped = lines.wait_for("recording stopped", 120)
        lines.wait_for("health:", 30)
        sent_at_stop = estimates_sent(lines.lines)
        time.sleep(2.0)  # vision goes on after the recording stopped
        lines.proc.send_signal(signal.SIGTERM)
        code, _, err = lines.finish(120)
    finally:
        fc.proc.send_signal(signal.SIGTERM)
        fc.finish(60)
    sent = estimates_sent(err.splitlines())
    folders = list(rec.iterdir()) if rec.is_dir() else []
    readable = (
        sum(1 for p in (folders[0] / "frames").glob("*.jpg") if cv2.imread(str(p), cv2.IMREAD_UNCHANGED) is not None)
        if folders
        else 0
    )
    ok = (
        code == 0
        and hup
        and stopped
        and "files reopened (segment 1)" in err
        and readable > 0
        and sent > sent_at_stop > 0
    )
    return FaultRow(
        "a full disk while recording; SIGHUP; SIGTERM",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        float("nan"),
        "frames after the disk filled (recording stopped; vision went on)",
        f"exit {code}; {readable} recorded frames readable; estimates sent {sent_at_stop} when recording stopped, {sent} at the end"
        + ("" if ok else f"; last line: {err.strip().splitlines()[-1][:160] if err.strip() else ''}"),
    )


def huge_images(tmp: Path) -> FaultRow:
    """Three 20000 x 20000 image files in an image-folder source (before: 149 MB -> 1263 MB, no
    estimates for 11 s)."""
    folder = tmp / "frames"
    image_folder(folder, 40, 0.1, huge=(10, 20, 30))
    cfg = run_config(
        tmp, f"camera: {{source: '{folder}'}}\nlink: {{url: 'udpout:127.0.0.1:9'}}\nservice: {{state_file: ''}}\n"
    )
    lines = Lines(run_mavvo("run", "--config", str(cfg)))
    code, _, err = lines.finish(120)
    peak_mb = lines.peak_rss_mb
    final = [line for line in err.splitlines() if "final:" in line]
    counts = {k: int(v) for k, v in re.findall(r"(\w+) (\d+)", final[0])} if final else {}
    frames = counts.get("frames", 0) + counts.get("frames_dropped", 0)
    ok = code == 0 and frames == 37 and peak_mb < 600 and "refused" in err
    return FaultRow(
        "three 20000x20000 images in an image-folder source",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        float("nan"),
        "the 3 oversized frames (refused from their headers)",
        f"{frames} of 37 other frames processed; peak memory of the process {peak_mb:.0f} MB",
    )


def folder_vanishes(tmp: Path) -> FaultRow:
    """The image folder disappears mid-run (before: the service exited 0; systemd did not restart it)."""
    folder = tmp / "frames"
    image_folder(folder, 60, 0.1)
    cfg = run_config(
        tmp,
        f"camera: {{source: '{folder}', lost_after_s: 2.0, reconnect_max_s: 0.5}}\nlink: {{url: 'udpout:127.0.0.1:9'}}\n"
        "service: {health_log_interval_s: 0.2, state_file: ''}\n",
    )
    lines = Lines(run_mavvo("run", "--config", str(cfg)))
    started = lines.wait_for("skipped_attitude_missing 3", 60)
    for p in folder.iterdir():
        p.unlink()
    folder.rmdir()
    code, _, err = lines.finish(60)
    ok = started and code == 1 and "camera.lost_after_s" in err
    return FaultRow(
        "the image folder disappears mid-run",
        Outcome.RESTARTED if ok else Outcome.FAILED,
        float("nan"),
        "nothing (no frames left to read)",
        f"exit {code} after camera.lost_after_s = 2 s of retries",
    )


def port_in_use(tmp: Path) -> FaultRow:
    """A second process on the same UDP port (before: both started silently, sharing the datagrams)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    folder = tmp / "frames"
    image_folder(folder, 300, 0.1)
    cfg = run_config(
        tmp, f"camera: {{source: '{folder}'}}\nlink: {{url: 'udpin:127.0.0.1:{port}'}}\nservice: {{state_file: ''}}\n"
    )
    first = Lines(run_mavvo("run", "--config", str(cfg)))
    try:
        first.wait_for("mavvo running", 60)
        code, _, err = Lines(run_mavvo("run", "--config", str(cfg))).finish(60)
    finally:
        first.proc.send_signal(signal.SIGTERM)
        first.finish(60)
    ok = code == 1 and "cannot listen on 127.0.0.1" in err
    return FaultRow(
        "a second process on the same UDP port",
        Outcome.REFUSED if ok else Outcome.FAILED,
        float("nan"),
        "nothing",
        err.strip().splitlines()[-1][:200] if err.strip() else f"exit {code}",
    )


def send_after_stop(tmp: Path) -> FaultRow:
    """``send()`` after the link stopped (before: wrote into a closed descriptor another file may own)."""
    link = Link(LinkOptions(url="udpout:127.0.0.1:9"), MonotonicClock(), None)  # type: ignore[arg-type]
    stop = threading.Event()
    stop.set()
    link.run(stop)
    r, w = os.pipe()  # the descriptors the link closed are free again: these may be them
    try:
        link.send("STATUSTEXT", {"severity": 6, "text": b"late"})
        os.set_blocking(r, False)
        try:
            leaked = os.read(r, 10)
        except BlockingIOError:
            leaked = b""
    finally:
        os.close(r)
        os.close(w)
    ok = leaked == b"" and link.counters["sent_after_stop"] == 1
    return FaultRow(
        "send() after the link stopped",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        float("nan"),
        "the late message (by design)",
        f"sent_after_stop {link.counters['sent_after_stop']}; nothing written to a reused descriptor",
    )


def config_fuzz(tmp: Path, cases: int = 1200) -> FaultRow:
    """Mutated settings files through ``mavvo check-config`` (in process, as the CLI runs it)."""
    tally = Counter[str]()
    bad: list[str] = []
    f = tmp / "fuzzed.yaml"
    for seed in range(cases):
        kind, text = mutated_config(seed)
        f.write_bytes(text)
        err_out = io.StringIO()
        with contextlib.redirect_stderr(err_out), contextlib.redirect_stdout(io.StringIO()):
            code = cli(["check-config", str(f)])
        err = err_out.getvalue()
        if code == 0:
            tally["accepted"] += 1
        elif code == 2 and err.count("\n") == 1 and err.startswith(f"mavvo: {f}") and "Traceback" not in err:
            tally["refused with one line"] += 1
        else:
            tally["other"] += 1
            bad.append(f"seed {seed} ({kind}): exit {code}: {err[:200]!r}")
    ok = tally["other"] == 0
    return FaultRow(
        f"config fuzzing, {cases} mutated files",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        float("nan"),
        "-",
        ", ".join(f"{k} {v}" for k, v in sorted(tally.items())) + (f"; first bad: {bad[0]}" if bad else ""),
    )


CASES: dict[str, Callable[[Path], FaultRow]] = {
    "undistortable_corners": undistortable_corners,
    "pymavlink_first": pymavlink_imported_first,
    "udp_flood": udp_flood,
    "forged_clock": forged_clock,
    "impostor_heartbeat": impostor_heartbeat,
    "foreign_sender": foreign_sender_udpout,
    "signing": signing_forgery_and_replay,
    "full_disk": full_disk_and_sighup,
    "huge_images": huge_images,
    "folder_vanishes": folder_vanishes,
    "port_in_use": port_in_use,
    "send_after_stop": send_after_stop,
    "config_fuzz": config_fuzz,
}
FAST_CASES = ("impostor_heartbeat", "foreign_sender", "signing", "folder_vanishes", "port_in_use", "send_after_stop")


def _run_case(name: str) -> FaultRow:
    """One case in a fresh temporary folder (an engine task: module level, so it pickles)."""
    with tempfile.TemporaryDirectory(prefix=f"mavvo-fault-{name}-") as d:
        return CASES[name](Path(d))


def run_cases(names: Sequence[str], progress: Callable[[str], None] | None = None, jobs: int = 1) -> list[FaultRow]:
    """Run the named cases on the sweep engine (mavvo.fleet.engine, as make draws and mavvo batch do),
    ``jobs`` worker processes at once (1 by default: the cases measure the service's gaps and would
    disturb each other side by side). A case that raises, or whose worker dies twice, is a failed row
    with its reason; the rows come in the order of ``names``."""

    rows: dict[str, FaultRow] = {}

    def record(o: TaskOutcome) -> None:
        name = str(o.key)
        if o.error is not None:
            rows[name] = FaultRow(name, Outcome.FAILED, float("nan"), "-", f"the case itself failed: {o.error}")
        else:
            rows[name] = o.result
        if progress is not None:
            progress(f"{name}: {rows[name].outcome.value}")

    run_tasks(_run_case, [(n, n) for n in names], record, workers=jobs)
    return [rows[n] for n in names if n in rows]


def markdown_table(rows: Sequence[FaultRow]) -> str:
    out = ["| input | outcome | longest gap in estimates | lost | figures |", "|---|---|---:|---|---|"]
    for r in rows:
        gap = "-" if np.isnan(r.longest_gap_s) else f"{r.longest_gap_s:.2f} s"
        out.append(f"| {r.case} | {r.outcome.value} | {gap} | {r.data_lost} | {r.details} |")
    return "\n".join(out) + "\n"


_BEGIN, _END = "<!-- faults:begin -->", "<!-- faults:end -->"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m tools.faults.suite",
        description="Run the fault suite against the service on 127.0.0.1 and print the table.",
    )
    p.add_argument("cases", nargs="*", metavar="CASE", help=f"cases to run (default: all): {', '.join(CASES)}")
    p.add_argument(
        "--markdown",
        type=Path,
        default=None,
        metavar="FILE",
        help=f"also write the table into FILE between {_BEGIN} and {_END}",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=1,
        metavar="N",
        help="cases at once, each in its own worker process (default 1: side by side they disturb the gaps they measure)",
    )
    args = p.parse_args(argv)
    if args.jobs < 1:
        p.error(f"--jobs: expected 1 or more, got {args.jobs}")
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        p.error(f"unknown case(s) {', '.join(unknown)}; expected some of {', '.join(CASES)}")
    names = args.cases or list(CASES)
    t0 = time.monotonic()
    rows = run_cases(names, progress=lambda n: print(f"fault suite: {n}", file=sys.stderr, flush=True), jobs=args.jobs)
    table = markdown_table(rows)
    print(table)
    if args.markdown is not None:
        text = args.markdown.read_text()
        stamp = f"{time.strftime('%Y-%m-%d')}, {len(rows)} cases in {time.monotonic() - t0:.0f} s on {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}\n\n"
        head, _, rest = text.partition(_BEGIN)
        _, _, tail = rest.partition(_END)
        args.markdown.write_text(f"{head}{_BEGIN}\n{stamp}{table}{_END}{tail}")
    return 0 if all(r.outcome is not Outcome.FAILED for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
