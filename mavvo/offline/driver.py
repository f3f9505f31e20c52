"""Replay: a logged flight fed to the mavvo daemon through a simulated flight controller and camera.

The daemon runs its normal code path (MAVLink 2 over UDP on 127.0.0.1, frames through the frame-source
interface) on a lockstep clock, as fast as it can, and the same way every time:

- each message the flight controller sent is delivered at the host time it arrived in flight (the
  clock is moved there first, so the link stamps it exactly as it did), and the next one only after
  the link has absorbed it;
- each frame is handed over once the daemon's flight-controller state has reached the version the
  frame was paired at in flight (:attr:`mavvo.service.timing.Pairing.fc_version`), or, for logs without one,
  once no message of the log arrived later than the frame's release time; the next message waits
  until the worker has finished the frame.

So a complete mavvo recording replays with the pairings it had in flight and gives the same
estimates bit for bit; flight-controller logs and datasets (:mod:`mavvo.offline.fc_logs`, :mod:`mavvo.offline.euroc`) become a
message list and a frame list and take the same path.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from mavvo.errors import ConfigError, MavvoError
from mavvo.evaluation.metrics import PoseSeries
from mavvo.evaluation.report import vision_estimates
from mavvo.service.camera import InjectedSource
from mavvo.service.daemon import Daemon
from mavvo.service.link import us_to_s
from mavvo.service.mavlink import mavutil
from mavvo.service.progress import DaemonSummary
from mavvo.service.settings import ServiceConfig
from mavvo.service.tlog import payload
from mavvo.sim.flight_controller.autopilot import RECORDED_TYPES, Received
from mavvo.sim.world.clock import LockstepClock
from mavvo.types import PoseEstimate, ScaleSource, StateReason, VisionState

log = logging.getLogger(__name__)

_HANDSHAKE_S = 2.0  # real time to wait for the daemon to absorb one message before calling it lost
_FRAME_S = 60.0  # real time to wait for the worker to finish one frame before giving up
_PROGRESS_EVERY_S = 5.0


@dataclass(frozen=True)
class ReplayFrame:
    """One frame to hand to the daemon: host-clock exposure, when to hand it over, how to load it."""

    seq: int
    t_exposure_s: float
    t_release_s: float  # at the latest once no message arrived later than this (host seconds)
    after_version: int | None  # as soon as the flight-controller state reached this version (recordings)
    load: Callable[[], np.ndarray]  # (H,W) uint8 grey


@dataclass
class ReplayInput:
    """What a replay feeds the daemon, whatever the source."""

    kind: str  # recording, tlog, dataflash, ulog, euroc
    source: str
    config: ServiceConfig
    messages: list[tuple[int, bytes]]  # from the flight controller: (host arrival, microseconds; MAVLink frame)
    frames: list[ReplayFrame]
    reference: PoseSeries | None = None  # ground truth or the flight controller's own position, host clock
    reference_label: str = ""
    expected_vpe: list[bytes] | None = None  # a recording's VISION_POSITION_ESTIMATE payloads, in order
    notes: dict[str, Any] = field(default_factory=dict)  # facts worth reporting (e.g. the time offset used)
    problems: list[str] = field(default_factory=list)  # bad input found while loading: the exit is non-zero
    warnings: list[str] = field(
        default_factory=list
    )  # what the result lacks (no reference, a guessed height): told, exit 0


@dataclass(frozen=True)
class QualityRow:
    """One estimate's quality, for the timeline."""

    t_exposure_s: float
    state: VisionState
    reason: StateReason
    quality: int
    tracks: int
    inliers: int
    inlier_ratio: float
    parallax_px: float
    residual_rms_px: float
    scale_source: ScaleSource
    keyframe: bool
    reset_counter: int
    attitude_gap_s: float  # between the ATTITUDE samples the frame's roll/pitch came from
    attitude_sigma_deg: float  # roll/pitch uncertainty, the flight controller's and the interpolation's


@dataclass
class ReplayResult:
    """How a replay went."""

    daemon: DaemonSummary
    estimates: PoseSeries  # the VISION_POSITION_ESTIMATEs the flight controller received, at usec
    vpe_payloads: list[bytes]
    quality: list[QualityRow]
    received: dict[str, int]
    statustexts: list[str]
    frames_replayed: int
    messages_lost: int
    wall_s: float
    duration_s: float
    stopped: bool  # interrupted before the end


class ReplayFlightController:
    """The simulated flight controller's socket, sending recorded bytes and keeping what the daemon sends."""

    def __init__(self) -> None:
        self._conn = mavutil().mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
        self.received: list[Received] = []

    @property
    def url_for_client(self) -> str:
        host, port = self._conn.port.getsockname()[:2]
        return f"udpout:{host}:{port}"

    def poll(self, t_s: float) -> int:
        """Read what the daemon sent (non-blocking); returns how many messages came."""
        n = 0
        while (msg := self._conn.recv_msg()) is not None:
            n += 1
            kind = msg.get_type()
            if kind in RECORDED_TYPES:
                self.received.append(Received(t_s, kind, msg, bytes(msg.get_msgbuf())))
        return n

    def has_client(self) -> bool:
        return bool(self._conn.clients)  # udpin answers whoever has sent

    def send(self, frame: bytes) -> None:
        self._conn.write(frame)

    def close(self) -> None:
        self._conn.close()


def image_loader(path: Path) -> Callable[[], np.ndarray]:
    """Loads ``path`` as a grey 8-bit image when called (a frame is read only when it is handed over)."""

    def load() -> np.ndarray:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ConfigError(f"{path}: cannot read the frame (missing or not an image)")
        return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)

    return load


def empty_result() -> ReplayResult:
    """The result of a replay that had nothing to replay (the input's problems say why)."""
    return ReplayResult(
        DaemonSummary({}, VisionState.STANDBY, None),
        PoseSeries(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))),
        [],
        [],
        {},
        [],
        0,
        0,
        0.0,
        0.0,
        False,
    )


_TAIL_S = 0.5  # flight-controller messages replayed after the last frame (under the service's 1 s of no estimate)


def _wait(pred: Callable[[], bool], timeout_s: float, stop: threading.Event) -> bool:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if stop.is_set() or time.monotonic() > deadline:
            return pred()
        time.sleep(0.0001)
    return True


class _Driver:
    """Feeds messages and frames in the order described in the module docstring (its own thread)."""

    def __init__(
        self,
        inp: ReplayInput,
        daemon: Daemon,
        fc: ReplayFlightController,
        source: InjectedSource,
        clock: LockstepClock,
        progress: Callable[[int, int], None] | None,
    ) -> None:
        self.inp, self.daemon, self.fc, self.source, self.clock = inp, daemon, fc, source, clock
        self.progress = progress
        self.sent = 0
        self.lost = 0
        self.frames = 0
        self.error: BaseException | None = None
        self._rx0 = 0

    def run(self) -> None:
        try:
            self._run()
        except BaseException as e:  # reported by replay() in the calling thread
            self.error = e
            self.daemon.request_stop()
        finally:
            self.source.end()

    def _run(self) -> None:
        stop = self.daemon.stop_event
        if not _wait(lambda: self._poll() >= 0 and self.fc.has_client(), 10.0, stop):
            if not stop.is_set():
                raise MavvoError("replay: the daemon never connected to the replay flight controller")
            return
        self._rx0 = self.daemon.progress().messages_received
        msgs = self.inp.messages
        i = 0
        next_progress = time.monotonic() + _PROGRESS_EVERY_S
        for k, fr in enumerate(self.inp.frames):
            while i < len(msgs) and not stop.is_set():
                if fr.after_version is not None and self.daemon.progress().fc_state_version >= fr.after_version:
                    break
                if msgs[i][0] > round(fr.t_release_s * 1e6):  # as the link rounds its stamps
                    break
                self._send(*msgs[i])
                i += 1
            if stop.is_set():
                return
            self.source.push(fr.load(), fr.t_exposure_s, fr.seq)
            self.frames += 1
            if not self.daemon.wait_progress(lambda p: p.idle_after(self.frames), _FRAME_S):
                if stop.is_set():
                    return
                raise MavvoError(f"replay: the daemon did not finish frame {fr.seq} within {_FRAME_S:.0f} s")
            self._poll()
            if self.progress is not None and time.monotonic() >= next_progress:
                next_progress = time.monotonic() + _PROGRESS_EVERY_S
                self.progress(k + 1, len(self.inp.frames))
        # After the last frame, only a short tail: a log that runs on (EuRoC's IMU for minutes after the
        # camera stopped) would have the service report no frames, fail, and log health for nothing.
        end_us = round((self.inp.frames[-1].t_release_s + _TAIL_S) * 1e6) if self.inp.frames else None
        while i < len(msgs) and not stop.is_set() and (end_us is None or msgs[i][0] <= end_us):
            self._send(*msgs[i])
            i += 1

    def _send(self, t_us: int, frame: bytes) -> None:
        self.clock.advance_to(us_to_s(t_us))
        self.fc.send(frame)
        self.sent += 1
        target = self._rx0 + self.sent - self.lost
        if not self.daemon.wait_progress(lambda p: p.messages_received >= target, _HANDSHAKE_S):
            self.lost += 1  # e.g. the link was reconnecting after a silence in the log
        if self.sent % 64 == 0:
            self._poll()

    def _poll(self) -> int:
        return self.fc.poll(self.clock.now_s())


def replay_config(config: ServiceConfig, url: str) -> ServiceConfig:
    """``config`` as the replay runs it: the link to the replay flight controller, no recording."""
    return dataclasses.replace(
        config,
        link=dataclasses.replace(config.link, url=url, signing_key_file=""),
        camera=dataclasses.replace(config.camera, source="replay"),
        record=dataclasses.replace(config.record, dir=""),
        service=dataclasses.replace(config.service, state_file=""),
    )


def replay(inp: ReplayInput, progress: Callable[[int, int], None] | None = None) -> ReplayResult:
    """Run ``inp`` through the daemon (see the module docstring) until it ends or the daemon is
    stopped (SIGINT/SIGTERM when called from the main thread)."""
    clock = LockstepClock()
    if inp.messages:
        clock.advance_to(us_to_s(inp.messages[0][0]))  # before the link starts: no false silence
    elif inp.frames:
        clock.advance_to(inp.frames[0].t_exposure_s)
    fc = ReplayFlightController()
    source = InjectedSource()
    quality: list[QualityRow] = []

    def on_estimate(e: PoseEstimate) -> None:
        d = e.diagnostics
        quality.append(
            QualityRow(
                e.t_exposure_s,
                d.state,
                d.reason,
                int(e.quality),
                d.tracks,
                d.inliers,
                d.inlier_ratio,
                d.parallax_px,
                d.residual_rms_px,
                d.scale_source,
                d.keyframe,
                e.reset_counter,
                d.attitude_gap_s,
                d.attitude_sigma_deg,
            )
        )

    wall0 = time.perf_counter()
    try:
        daemon = Daemon(
            replay_config(inp.config, fc.url_for_client), clock=clock, source=source, on_estimate=on_estimate
        )
        driver = _Driver(inp, daemon, fc, source, clock, progress)
        thread = threading.Thread(target=driver.run, name="mavvo-replay", daemon=True)
        thread.start()
        summary = daemon.run()
        daemon.stop_event.set()
        thread.join(5.0)
        fc.poll(clock.now_s())
    finally:
        fc.close()
    if driver.error is not None:
        raise driver.error
    wall = time.perf_counter() - wall0
    vpe = [r for r in fc.received if r.type == "VISION_POSITION_ESTIMATE"]
    received: dict[str, int] = {}
    for r in fc.received:
        received[r.type] = received.get(r.type, 0) + 1
    span = (inp.frames[-1].t_exposure_s - inp.frames[0].t_exposure_s) if inp.frames else 0.0
    return ReplayResult(
        summary,
        vision_estimates(fc.received, "usec"),
        [payload(r.raw) for r in vpe],
        quality,
        dict(sorted(received.items())),
        [r.msg.text for r in fc.received if r.type == "STATUSTEXT"],
        driver.frames,
        driver.lost,
        wall,
        span,
        driver.frames < len(inp.frames),
    )
