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
import enum
import hashlib
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
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from mavvo.cli import main as cli
from mavvo.service.daemon import Daemon
from mavvo.service.link import Link
from mavvo.service.link_options import LinkOptions
from mavvo.service.mavlink import mavutil
from mavvo.service.timing import MonotonicClock
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.service_run import SimRun, run_daemon_in_sim
from tools.faults.config_fuzz import mutated_config

__all__ = ["Outcome", "FaultRow", "CASES", "FAST_CASES", "run_cases", "markdown_table", "main"]

_GAP_OK_S = 1.0
_SIGNING_EPOCH_UNIX_S = 1_420_070_400  # MAVLink signing timestamps count 10 us units from 2015-01-01


class Outcome(enum.Enum):
    SURVIVED = "survived"
    RESTARTED = "restarted"
    REFUSED = "refused"
    FAILED = "failed"


@dataclass(frozen=True)
class FaultRow:
    """One case of the suite: the input, what came of it, the longest gap in estimates (seconds, NaN
    where no estimates are involved), what was lost, and the figures behind it."""

    case: str
    outcome: Outcome
    longest_gap_s: float
    data_lost: str
    details: str


# ---------------------------------------------------------------------------------------------- helpers


def _gaps(run: SimRun) -> float:
    """The longest gap between consecutive estimates the flight controller received (exposure times)."""
    t = np.array([m.usec for m in run.vision_messages], dtype=float) * 1e-6
    return float(np.max(np.diff(t))) if len(t) >= 2 else float("inf")


def _flow_outcome(run: SimRun, gap_s: float) -> Outcome:
    return Outcome.SURVIVED if len(run.vision_messages) > 20 and gap_s <= _GAP_OK_S else Outcome.FAILED


def _lost(counters: dict[str, int], *keys: str) -> str:
    parts = [f"{k} {counters[k]}" for k in keys if counters.get(k)]
    return ", ".join(parts) or "nothing"


def _hover(duration_s: float):
    return replace(load_scenario("hover"), duration_s=duration_s)


def _attitude(mav, boot_ms: int, roll: float = 0.0) -> bytes:
    m = mavutil().mavlink
    return bytes(m.MAVLink_attitude_message(boot_ms, roll, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav))


def _heartbeat(mav) -> bytes:
    m = mavutil().mavlink
    return bytes(
        m.MAVLink_heartbeat_message(
            m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, m.MAV_STATE_ACTIVE, 3
        ).pack(mav)
    )


def _mavvo(*args: str, preexec: Callable[[], None] | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "mavvo", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=preexec,
    )


class _Lines:
    """A subprocess's stderr, collected line by line on a thread."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self._t = threading.Thread(target=lambda: self.lines.extend(iter(proc.stderr.readline, "")), daemon=True)  # type: ignore[union-attr]
        self._t.start()

        self.peak_rss_mb = float("nan")

    def _exited(self) -> bool:
        """Whether the process has ended, without reaping it (so :meth:`finish` gets its resource use)."""
        return os.waitid(os.P_PID, self.proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None

    def wait_for(self, text: str, timeout_s: float = 60.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(text in line for line in self.lines):
                return True
            if self._exited():
                self._t.join(5)
                return any(text in line for line in self.lines)
            time.sleep(0.05)
        return False

    def finish(self, timeout_s: float = 60.0) -> tuple[int, str, str]:
        """Wait for the end (killing it after ``timeout_s``): (exit code, stdout, stderr); the peak
        resident memory of this process alone goes to ``peak_rss_mb``."""
        deadline = time.monotonic() + timeout_s
        while self.proc.returncode is None:  # (send_signal may have reaped it already: then no resource use)
            pid, status, usage = os.wait4(self.proc.pid, os.WNOHANG)
            if pid:
                self.proc.returncode = os.waitstatus_to_exitcode(status)
                self.peak_rss_mb = usage.ru_maxrss / 1024
                break
            if time.monotonic() > deadline:
                self.proc.kill()
                deadline = float("inf")
            time.sleep(0.05)
        out = self.proc.stdout.read() if self.proc.stdout is not None else ""
        self._t.join(10)
        return self.proc.returncode, out, "".join(self.lines)


def _image_folder(folder: Path, n: int, period_s: float, huge: Sequence[int] = ()) -> None:
    """``n`` small random frames listed in timestamps.txt; the frames at ``huge`` are 20000 x 20000."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    lines = []
    for i in range(n):
        name = f"{i:04d}.png"
        if i in huge:
            cv2.imwrite(str(folder / name), np.zeros((20000, 20000), np.uint8), [cv2.IMWRITE_PNG_COMPRESSION, 9])
        else:
            cv2.imwrite(str(folder / name), rng.integers(0, 255, (48, 64), dtype=np.uint8))
        lines.append(f"{i * period_s:.3f} {name}")
    (folder / "timestamps.txt").write_text("\n".join(lines) + "\n")


def _run_config(tmp: Path, text: str) -> Path:
    cfg = tmp / "mavvo.yaml"
    cfg.write_text(text)
    return cfg


# ---------------------------------------------------------------------------------------------- the cases


def undistortable_corners(tmp: Path) -> FaultRow:
    """A strongly distorted lens (k1 0.3, k2 -0.8) whose image corners have no bearing: before, one
    such frame killed the odometry until the process restarted."""
    sc = load_scenario("figure_eight")
    sc = replace(sc, camera=replace(sc.camera, distortion=(0.3, -0.8, 0.0, 0.0)), duration_s=20.0)
    run = run_daemon_in_sim(sc)
    gap = _gaps(run)
    c = run.daemon.counters
    return FaultRow(
        "lens with undistortable corners (k1 0.3, k2 -0.8)",
        _flow_outcome(run, gap),
        gap,
        _lost(c, "odometry_errors", "bad_frames"),
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
        _lost(s["counters"], "errors", "link_send_dropped"),
        f"{s['estimates_received']} estimates received as MAVLink 2",
    )


def udp_flood(tmp: Path) -> FaultRow:
    """20 000 garbage datagrams a second for 10 s at the port the service listens on."""
    sent = Counter[str]()

    def flood(daemon: Daemon, address: tuple[str, int]) -> None:
        rng = np.random.default_rng(3)
        garbage = [bytes(rng.integers(0, 256, 64, dtype=np.uint8)) for _ in range(200)]
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setblocking(False)
        time.sleep(5.0)  # the flight controller is chosen and estimates flow by then
        t0 = time.monotonic()
        while (t := time.monotonic() - t0) < 10.0 and not daemon.stop_event.is_set():
            for g in garbage:  # 200 per 10 ms
                try:
                    s.sendto(g, address)
                    sent["datagrams"] += 1
                except OSError:
                    sent["refused"] += 1
            time.sleep(max(0.0, 0.01 * (int(t / 0.01) + 1) - (time.monotonic() - t0)))
        s.close()

    run = run_daemon_in_sim(_hover(20.0), realtime=True, service_listens=True, during=flood)
    gap = _gaps(run)
    c = run.daemon.counters
    return FaultRow(
        "20k garbage datagrams/s for 10 s on the service's UDP port",
        _flow_outcome(run, gap),
        gap,
        _lost(c, "link_stale_dropped", "skipped_attitude_stale", "skipped_attitude_missing"),
        f"{sent['datagrams']} sent, {c.get('link_bad_data', 0)} read as bad data, {run.received.get('HEARTBEAT', 0)} HEARTBEATs sent",
    )


def forged_clock(tmp: Path) -> FaultRow:
    """A forged TIMESYNC answer, an ATTITUDE stamped 1 s ahead and one 5 ms ahead, from another sender."""

    def forge(daemon: Daemon, address: tuple[str, int]) -> None:
        m = mavutil().mavlink
        mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        time.sleep(6.0)
        boot_ms = int(daemon.clock.now_s() * 1000)  # about the flight controller's boot clock in the simulator
        now_ns = int(daemon.clock.now_s() * 1e9)
        s.sendto(bytes(m.MAVLink_timesync_message(now_ns + 10**9, now_ns - 10**6).pack(mav)), address)
        s.sendto(_attitude(mav, boot_ms + 1000, roll=0.9), address)
        s.sendto(_attitude(mav, boot_ms + 5, roll=0.9), address)
        s.close()

    run = run_daemon_in_sim(_hover(16.0), realtime=True, service_listens=True, during=forge)
    gap = _gaps(run)
    c = run.daemon.counters
    return FaultRow(
        "forged TIMESYNC answer; ATTITUDE stamped 1 s and 5 ms ahead",
        _flow_outcome(run, gap),
        gap,
        _lost(c, "fc_attitude_implausible", "fc_timesync_implausible", "skipped_attitude_wait"),
        "dropped by the sender filter (the flight controller's address is pinned); the plausibility checks behind it are tested alone",
    )


def impostor_heartbeat(tmp: Path) -> FaultRow:
    """HEARTBEATs from another system id before (and while) the real flight controller's come (before:
    the first one was followed for the whole run, 0 of 700 genuine ATTITUDE accepted)."""
    seen: dict[str, int | None] = {}

    def impostor(daemon: Daemon, address: tuple[str, int]) -> None:
        mav = mavutil().mavlink.MAVLink(None, srcSystem=42, srcComponent=1)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        daemon.link.connected.wait(30)  # the service's socket exists
        sent = 0
        while daemon.link.fc_component_id is None and not daemon.stop_event.is_set():
            s.sendto(_heartbeat(mav), address)
            sent += 1
            time.sleep(0.01)
        s.close()
        seen["system"], seen["sent"] = daemon.link.fc_system_id, sent

    run = run_daemon_in_sim(_hover(8.0), service_listens=True, during=impostor)  # lockstep
    gap = _gaps(run)
    c = run.daemon.counters
    ok = _flow_outcome(run, gap) is Outcome.SURVIVED and seen.get("system") == 1 and (seen.get("sent") or 0) > 0
    return FaultRow(
        "HEARTBEATs from another system id before the flight controller's",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        gap,
        _lost(c, "skipped_attitude_missing"),
        f"{seen.get('sent')} impostor HEARTBEATs; followed system {seen.get('system')}; {c.get('fc_attitude', 0)} ATTITUDE accepted",
    )


def foreign_sender_udpout(tmp: Path) -> FaultRow:
    """``udpout``: datagrams from another sender than the flight controller (before: accepted from anyone)."""
    seen: dict[str, object] = {}

    def stranger(daemon: Daemon, address: tuple[str, int]) -> None:
        mav = mavutil().mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        seen["bound_to"] = address[0]
        sent = 0
        for i in range(2000):
            sent += s.sendto(b"\x00garbage" if i % 2 else _attitude(mav, 10**6 + i, roll=0.9), address) > 0
        seen["sent"] = sent
        s.close()

    run = run_daemon_in_sim(_hover(10.0), during=stranger)
    gap = _gaps(run)
    c = run.daemon.counters
    ok = (
        _flow_outcome(run, gap) is Outcome.SURVIVED
        and c.get("link_bad_data", 0) == 0
        and seen.get("bound_to") == "127.0.0.1"
        and seen.get("sent") == 2000
    )
    return FaultRow(
        "udpout: 2000 datagrams from a stranger",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        gap,
        _lost(c, "link_bad_data", "fc_attitude_implausible"),
        f"{seen.get('sent')} sent to {seen.get('bound_to')}, none read (the socket is connected to the flight controller)",
    )


def signing_forgery_and_replay(tmp: Path) -> FaultRow:
    """Signing on: one frame with a wrong signature and a huge timestamp, then a genuine frame from
    another link id 5 s old with a boot time 60 s back (before: genuine traffic refused for 3.3 s; the
    replay faked a reboot)."""
    key_file = tmp / "signing.key"
    key_file.write_text("a passphrase\n")
    key_file.chmod(0o600)
    key = hashlib.sha256(b"a passphrase").digest()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    got: list[int] = []

    class Listener:
        def on_attitude(self, t_fc_ms, *args, **kw):
            got.append(t_fc_ms)

        def __getattr__(self, name):
            return lambda *a, **k: None

    link = Link(
        LinkOptions(url=f"udpin:127.0.0.1:{port}", signing_key_file=str(key_file), fc_system_id=1),
        MonotonicClock(),
        Listener(),
    )
    stop = threading.Event()
    t = threading.Thread(target=link.run, args=(stop,), daemon=True)
    t.start()

    def signer(link_id: int, timestamp: int):
        mav = mavutil().mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id, mav.signing.timestamp = (
            key,
            True,
            link_id,
            timestamp,
        )
        return mav

    fc = signer(0, int((time.time() - _SIGNING_EPOCH_UNIX_S) * 100_000))
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        link.connected.wait(30)
        s.sendto(_heartbeat(fc), ("127.0.0.1", port))
        boot_ms = 100_000
        genuine = 0
        for i in range(40):
            if i == 20:
                forged = bytearray(_attitude(fc, boot_ms + 5))
                forged[-12:-6] = (2**47).to_bytes(6, "little")  # far ahead; the signature no longer matches
                s.sendto(bytes(forged), ("127.0.0.1", port))
            boot_ms += 10
            s.sendto(_attitude(fc, boot_ms), ("127.0.0.1", port))
            genuine += 1
        s.sendto(_attitude(signer(1, fc.signing.timestamp - 500_000), boot_ms - 60_000), ("127.0.0.1", port))
        boot_ms += 10
        s.sendto(_attitude(fc, boot_ms), ("127.0.0.1", port))
        genuine += 1
        deadline = time.monotonic() + 30
        while len(got) < genuine and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        s.close()
        stop.set()
        t.join(10)
    c = link.counters
    ok = len(got) == genuine and c["signature_bad"] == 1 and c["signature_replayed"] == 1 and c["reboots"] == 0
    return FaultRow(
        "signing: a forged frame with a huge timestamp; a replay from another link id",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        float("nan"),
        f"{genuine - len(got)} of {genuine} genuine frames",
        f"signature_bad {c['signature_bad']}, signature_replayed {c['signature_replayed']}, reboots {c['reboots']}",
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
    cfg = _run_config(
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

    fc = _Lines(_mavvo("sim", "--fc-only", "--scenario", "hover", "--mavlink", f"udpin:127.0.0.1:{port}"))
    try:
        fc.wait_for("simulated flight controller on", 60)
        lines = _Lines(_mavvo("run", "--config", str(cfg), preexec=limit))
        hup = lines.wait_for("-> tracking", 120)
        if hup:
            lines.proc.send_signal(signal.SIGHUP)
        stopped = lines.wait_for("recording stopped", 120)
        lines.wait_for("health:", 30)
        sent_at_stop = _estimates_sent(lines.lines)
        time.sleep(2.0)  # vision goes on after the recording stopped
        lines.proc.send_signal(signal.SIGTERM)
        code, _, err = lines.finish(120)
    finally:
        fc.proc.send_signal(signal.SIGTERM)
        fc.finish(60)
    sent = _estimates_sent(err.splitlines())
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


def _estimates_sent(lines: Sequence[str]) -> int:
    """``estimates_sent`` of the last health line in a ``mavvo run`` log."""
    for line in reversed(lines):
        if m := re.search(r"estimates_sent (\d+)", line):
            return int(m.group(1))
    return 0


def huge_images(tmp: Path) -> FaultRow:
    """Three 20000 x 20000 image files in an image-folder source (before: 149 MB -> 1263 MB, no
    estimates for 11 s)."""
    folder = tmp / "frames"
    _image_folder(folder, 40, 0.1, huge=(10, 20, 30))
    cfg = _run_config(
        tmp, f"camera: {{source: '{folder}'}}\nlink: {{url: 'udpout:127.0.0.1:9'}}\nservice: {{state_file: ''}}\n"
    )
    lines = _Lines(_mavvo("run", "--config", str(cfg)))
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
    _image_folder(folder, 60, 0.1)
    cfg = _run_config(
        tmp,
        f"camera: {{source: '{folder}', lost_after_s: 2.0, reconnect_max_s: 0.5}}\nlink: {{url: 'udpout:127.0.0.1:9'}}\n"
        "service: {health_log_interval_s: 0.2, state_file: ''}\n",
    )
    lines = _Lines(_mavvo("run", "--config", str(cfg)))
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
    _image_folder(folder, 300, 0.1)
    cfg = _run_config(
        tmp, f"camera: {{source: '{folder}'}}\nlink: {{url: 'udpin:127.0.0.1:{port}'}}\nservice: {{state_file: ''}}\n"
    )
    first = _Lines(_mavvo("run", "--config", str(cfg)))
    try:
        first.wait_for("mavvo running", 60)
        code, _, err = _Lines(_mavvo("run", "--config", str(cfg))).finish(60)
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


def run_cases(names: Sequence[str], progress: Callable[[str], None] | None = None) -> list[FaultRow]:
    """Run the named cases, each in a fresh temporary folder."""
    rows = []
    for name in names:
        if progress is not None:
            progress(name)
        with tempfile.TemporaryDirectory(prefix=f"mavvo-fault-{name}-") as d:
            rows.append(CASES[name](Path(d)))
    return rows


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
    args = p.parse_args(argv)
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        p.error(f"unknown case(s) {', '.join(unknown)}; expected some of {', '.join(CASES)}")
    names = args.cases or list(CASES)
    t0 = time.monotonic()
    rows = run_cases(names, progress=lambda n: print(f"fault suite: {n} ...", file=sys.stderr, flush=True))
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
