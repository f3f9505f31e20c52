"""What the fault suite's cases share: the row each returns and its outcome, a hovering flight, MAVLink
bytes an attacker would send, ``mavvo`` run as a process with its output followed."""

from __future__ import annotations

import enum
import os
import re
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from mavvo.service.mavlink import mavutil
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.service_run import SimRun

__all__ = [
    "FaultRow",
    "GAP_OK_S",
    "Lines",
    "Outcome",
    "SIGNING_EPOCH_UNIX_S",
    "attitude_bytes",
    "estimates_sent",
    "flow_outcome",
    "heartbeat_bytes",
    "hover",
    "image_folder",
    "longest_gap_s",
    "lost",
    "run_config",
    "run_mavvo",
]

GAP_OK_S = 1.0
SIGNING_EPOCH_UNIX_S = 1_420_070_400  # MAVLink signing timestamps count 10 us units from 2015-01-01


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


def longest_gap_s(run: SimRun) -> float:
    """The longest gap between consecutive estimates the flight controller received (exposure times)."""
    t = np.array([m.usec for m in run.vision_messages], dtype=float) * 1e-6
    return float(np.max(np.diff(t))) if len(t) >= 2 else float("inf")


def flow_outcome(run: SimRun, gap_s: float) -> Outcome:
    return Outcome.SURVIVED if len(run.vision_messages) > 20 and gap_s <= GAP_OK_S else Outcome.FAILED


def lost(counters: dict[str, int], *keys: str) -> str:
    parts = [f"{k} {counters[k]}" for k in keys if counters.get(k)]
    return ", ".join(parts) or "nothing"


def hover(duration_s: float):
    return replace(load_scenario("hover"), duration_s=duration_s)


def attitude_bytes(mav, boot_ms: int, roll: float = 0.0) -> bytes:
    m = mavutil().mavlink
    return bytes(m.MAVLink_attitude_message(boot_ms, roll, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav))


def heartbeat_bytes(mav) -> bytes:
    m = mavutil().mavlink
    return bytes(
        m.MAVLink_heartbeat_message(
            m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, m.MAV_STATE_ACTIVE, 3
        ).pack(mav)
    )


def run_mavvo(*args: str, preexec: Callable[[], None] | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "mavvo", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=preexec,
    )


class Lines:
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


def image_folder(folder: Path, n: int, period_s: float, huge: Sequence[int] = ()) -> None:
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


def run_config(tmp: Path, text: str) -> Path:
    cfg = tmp / "mavvo.yaml"
    cfg.write_text(text)
    return cfg


# ---------------------------------------------------------------------------------------------- the cases


def estimates_sent(lines: Sequence[str]) -> int:
    """``estimates_sent`` of the last health line in a ``mavvo run`` log."""
    for line in reversed(lines):
        if m := re.search(r"estimates_sent (\d+)", line):
            return int(m.group(1))
    return 0
