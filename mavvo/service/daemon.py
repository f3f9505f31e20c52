"""The service: link, camera and worker threads wired together, with a clean stop.

- The link thread (:class:`mavvo.service.link.Link`) owns the MAVLink connection and fills the flight
  controller's state (:class:`mavvo.service.timing.FlightControllerState`).
- The camera thread reads the frame source into a :class:`mavvo.service.camera.FrameQueue` (real time: the
  newest frames, older ones dropped and counted; lockstep simulation: every frame, in order).
- The worker pairs each frame with roll/pitch at its exposure, runs :meth:`mavvo.odometry.pipeline.Odometry.step`
  (the tracking of the next queued frame meanwhile on a helper thread, :mod:`mavvo.odometry.ahead`,
  unless ``service.track_ahead`` is off) and sends the estimate: VISION_POSITION_ESTIMATE (capped at
  ``output.max_rate_hz``), optionally VISION_SPEED_ESTIMATE and ODOMETRY, nothing while failed.
- The calling thread supervises: SIGTERM/SIGINT set the stop flag (a second one skips the drain;
  SIGHUP reopens the recording; handlers only set flags and are restored afterwards), systemd
  READY/WATCHDOG/STOPPING (WATCHDOG only while every thread's loop turns), STATUSTEXT on state changes
  (also "failed" when estimates stop coming: no attitude, no frames), NAMED_VALUE_FLOAT health,
  counters in the log every ``service.health_log_interval_s``.

Bad input from the flight controller or the camera never stops the service: it is logged, counted,
reported over MAVLink and skipped. A thread that dies, or a camera lost for ``camera.lost_after_s``,
ends the run with ``DaemonSummary.failure`` set (``mavvo run`` exits 1 for systemd to restart it). The
stop is bounded: the worker finishes its frame, the link sends what is queued, and every thread is
joined within ``service.shutdown_drain_s``.
"""

from __future__ import annotations

import json
import logging
import math
import signal
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from mavvo.errors import CameraEnded, CameraLost, FrameRefused
from mavvo.estimation.warmup import warm_kernels
from mavvo.odometry.ahead import TrackAhead
from mavvo.odometry.frontend import Tracks
from mavvo.odometry.pipeline import Odometry
from mavvo.service import messages, sdnotify
from mavvo.service.camera import FrameQueue, FrameSource, SourceFactory, open_source
from mavvo.service.latency import LatencyStats, LatencyTracker
from mavvo.service.link import Link, SystemStatus
from mavvo.service.recorder import Recorder, RecordingError
from mavvo.service.settings import ServiceConfig, config_yaml
from mavvo.service.timing import Clock, FlightControllerState, MonotonicClock, wait_for_pairing
from mavvo.types import Frame, PairedFrame, PoseEstimate, StateReason, VisionState

__all__ = ["Daemon", "DaemonSummary", "LockstepProgress"]

log = logging.getLogger(__name__)

_SUPERVISE_TICK_S = 0.1
_ARRIVALS_KEPT = 64
_UNPAIRED_TELL_S = 2.0  # frames unpaired for one cause this long: the operator is told which and what to change
_SAMPLES_PER_GAP = (
    1.5  # ATTITUDE at this many samples per max_attitude_gap_s is fast enough: stale frames then mean stalls
)
_UNPAIRED_CAUSES = {
    "skipped_attitude_stale": "ATTITUDE too sparse; raise link.attitude_rate_hz",
    "skipped_attitude_missing": "no ATTITUDE; check link.url",
    "skipped_attitude_wait": "ATTITUDE late; raise timing.attitude_wait_s",
    "waiting_for_heading": "waiting for the FC's yaw to settle",
}
_LOCKSTEP_POLL_S = 1e-4  # how often wait_progress looks (real time)
_NO_ESTIMATE_S = 1.0  # no estimate for this long (host clock): the operator is told vision failed
_ERROR_LOG_EVERY = 100  # after the first few, log one repeated error in this many
_STUCK_MIN_S = 2.0  # a thread whose loop has not turned for this long (at least) stops the watchdog's feeding
_PAUSE_SLICE_S = 0.25  # long waits are cut into slices, each a turn of the thread's loop
_THREADS = ("link", "camera", "worker")
_SYSTEM_STATUS = {
    VisionState.STANDBY: SystemStatus.STANDBY,
    VisionState.INITIALISING: SystemStatus.ACTIVE,
    VisionState.TRACKING: SystemStatus.ACTIVE,
    VisionState.DEGRADED: SystemStatus.CRITICAL,
    VisionState.FAILED: SystemStatus.CRITICAL,
}


def _snapshot(counter: Counter[str]) -> dict[str, int]:
    """A copy of a counter that another thread adds keys to. ``dict(counter)`` copies in one C call
    under the GIL; iterating the live counter could meet a new key and raise."""
    return dict(counter)


@dataclass(frozen=True)
class LockstepProgress:
    """How far the daemon has got, for a driver that runs it in lockstep (simulation, replay).

    Every count only grows. A driver hands the daemon one input, then waits with
    :meth:`Daemon.wait_progress` until the matching count has moved, so the daemon's threads see
    every input at the simulated moment it was meant for, whatever the machine's load.

    Attributes:
        messages_received: MAVLink messages the link has read and handed to the flight controller's
            state (good or bad).
        fc_state_version: updates the flight controller's state has absorbed; each frame's pairing
            records the version it saw (:attr:`mavvo.service.timing.Pairing.fc_version`).
        frames_done: frames the worker has finished, whatever came of them (estimate, skipped, error).
        frames_queued: frames the camera thread has handed to the worker.
        sends_pending: messages the worker queued for the link and the link has not yet written or
            dropped (this one goes up and down); 0 while the link is disconnected: what it holds then
            waits for the reconnect, which only a later tick of the clock brings (a driver that waited
            for it held the clock for its whole timeout on each frame of the back-off).
        messages_sent: MAVLink messages the link has written (its first tells a listening flight
            controller where the service is).
        datagrams_done: UDP datagrams the link has read and finished with, whatever they held (a
            message, a spoiled one, garbage); what a driver sending over UDP waits on.
        link_tick_s: the host clock at the last :meth:`Daemon.tick` the link has finished.
        waiting_for_attitude: the worker's frame waits for an ATTITUDE that has not been sent yet, and
            nothing has arrived since it looked (it goes on when more comes or the clock moves on).
    """

    messages_received: int
    fc_state_version: int
    frames_done: int
    frames_queued: int = 0
    sends_pending: int = 0
    messages_sent: int = 0
    datagrams_done: int = 0
    link_tick_s: float = -math.inf
    waiting_for_attitude: bool = False

    def idle_after(self, frames: int) -> bool:
        """The daemon can do nothing more with the first ``frames`` frames until it gets more input:
        each is finished, or the worker waits for an ATTITUDE (the frames behind it wait in the queue),
        and everything they sent is written."""
        return (self.frames_done >= frames or self.waiting_for_attitude) and self.sends_pending == 0


@dataclass(frozen=True)
class DaemonSummary:
    """How a run went: every counter, the last state, the capture-to-send latency, and why the
    service could not go on (``failure``; empty after a clean stop)."""

    counters: dict[str, int]
    state: VisionState
    latency: LatencyStats | None
    failure: str = ""

    @property
    def latency_ms(self) -> float | None:
        """The median capture-to-send latency."""
        return None if self.latency is None else self.latency.p50_ms


class Daemon:
    """mavvo's service (see the module docstring).

    Args:
        config: the service's settings.
        clock: the host clock (``time.monotonic`` by default; the simulator passes its own).
        source: the frame source; default: opened from ``config.camera.source``.
        schemes: extra ``camera.source`` schemes (the CLI registers ``sim:``).
        on_estimate: called on the worker thread with every estimate (replay's quality timeline); it
            must be quick.
        wall_clock: real time (``time.monotonic`` by default): the watchdog, bounded waits, and the
            processing time in a lockstep run's latency.

    With ``config.record.dir`` set, the run is recorded (:mod:`mavvo.service.recorder`).
    """

    def __init__(
        self,
        config: ServiceConfig,
        *,
        clock: Clock | None = None,
        source: FrameSource | None = None,
        schemes: dict[str, SourceFactory] | None = None,
        on_estimate: Callable[[PoseEstimate], None] | None = None,
        wall_clock: Clock | None = None,
    ) -> None:
        self.config = config
        self.clock = clock or MonotonicClock()
        self.on_estimate = on_estimate
        self.fc = FlightControllerState(self.clock, config.timing)
        self.source = source if source is not None else open_source(config.camera, self.clock, schemes, self.fc)
        self.counters: Counter[str] = Counter()
        self._pending_texts: deque[dict[str, object]] = deque()  # STATUSTEXTs other threads ask the supervisor to send
        try:
            self.recorder = self._open_recorder()
            self.link = Link(
                config.link,
                self.clock,
                self.fc,
                self._system_status,
                tap=self.recorder.mavlink if self.recorder else None,
            )
        except BaseException:
            self.source.close()
            if getattr(self, "recorder", None) is not None:
                self.recorder.close()
            raise
        self.frames = FrameQueue(config.camera.queue_size, drop_oldest=self.clock.realtime)
        self.stop_event = threading.Event()
        self.state = VisionState.STANDBY
        self.last_estimate: PoseEstimate | None = None
        self._camera_done = threading.Event()
        self._worker_done = threading.Event()
        self._reopen = threading.Event()  # SIGHUP: the recording's files are to be reopened
        self._force_stop = threading.Event()  # a second stop signal: no drain
        self._failure = ""  # why the service cannot go on (a thread died); empty while it can
        self.turns: Counter[str] = Counter()  # loop turns of the camera and worker threads (the link counts its own)
        self._turns_seen: dict[str, tuple[int, float]] = {}  # thread -> (turns, real time they last changed)
        self._wall = wall_clock or MonotonicClock()
        self._last_sent_t_s = -math.inf
        self._last_text_s = -math.inf
        self._pending_states: list[tuple[VisionState, StateReason]] = []  # changes not yet told (rate limit)
        self._next_health_s = -math.inf
        self._reset_counter: int | None = None
        self._errors_logged: Counter[str] = Counter()
        self.odometry = Odometry(
            config.camera.camera_model(),
            config.mounting.rotation(),
            config.odometry,
            reset_counter=self._first_reset_counter(),
        )
        # The odometry is looked up at each call: a test may put another in its place.
        self._ahead = TrackAhead(lambda image: self.odometry.track(image), thread=config.service.track_ahead)
        self._next_frame: Frame | None = None  # taken from the queue by the worker, its tracking started
        self._state_lock = threading.Lock()
        self._skipped_at_last_report = 0
        self._first_paired_s: float | None = None  # host time of the first paired frame: the heading wait starts there
        self._heading_wait_over = config.service.heading_wait_max_s <= 0
        self._odometry_ok = False  # the last ODOMETRY sent had a quality >= 1
        self.latency = LatencyTracker(self.link.baud)
        self._unpaired_history: deque[tuple[float, int, dict[str, int]]] = deque()  # (t, paired, unpaired causes)
        self._unpaired_told: str | None = None  # the cause told, until frames pair again
        self._arrival_s: dict[int, float] = {}  # frame seq -> host time the camera thread got it
        self._frame_in: tuple[float, float] = (0.0, 0.0)  # (host clock when it arrived, real time the worker took it)

    # ------------------------------------------------------------------ lockstep

    def progress(self) -> LockstepProgress:
        """The counts a lockstep driver waits on (thread-safe: each is read in one step)."""
        return LockstepProgress(
            self.link.counters["rx"],
            self.fc.version,
            self.counters["frames_done"],
            self.counters["frames_queued"],
            self.link.sends_pending() if self.link.connected.is_set() else 0,
            self.link.counters["sent"],
            self.link.datagrams_done,
            self.link.tick_clock_s,
            self.fc.waiting_for_data(),
        )

    def tick(self) -> None:
        """Lockstep: the driver has moved the host clock; the link does what time has made due (see
        :meth:`Link.tick`) and then reports the clock in ``progress().link_tick_s``."""
        self.link.tick()

    def wait_progress(self, done: Callable[[LockstepProgress], bool], timeout_s: float) -> bool:
        """Wait until ``done(self.progress())`` holds, at most ``timeout_s`` seconds of real time, or
        until the daemon stops. Returns whether it holds. For lockstep drivers, on their own thread; the
        bound is the driver's own monotonic clock, not the daemon's (which a test may have stopped)."""
        deadline = time.monotonic() + timeout_s
        while not done(self.progress()):
            if self.stop_event.is_set() or time.monotonic() > deadline:
                return done(self.progress())
            time.sleep(_LOCKSTEP_POLL_S)
        return True

    # ------------------------------------------------------------------ running

    def request_stop(self) -> None:
        """Ask the service to stop (thread- and signal-safe)."""
        self.stop_event.set()

    def request_reopen(self) -> None:
        """Close and reopen the recording's files (SIGHUP, as daemons do for log rotation); signal-safe."""
        self._reopen.set()

    def on_signal(self, signum: int, _frame: object) -> None:
        """SIGTERM/SIGINT: the first stops cleanly (bounded drain), a second skips the drain. SIGHUP:
        reopen the recording. Handlers only set flags; the supervisor acts on them."""
        if signum == signal.SIGHUP:
            self.request_reopen()
        elif self.stop_event.is_set():
            self._force_stop.set()
        else:
            self.request_stop()

    def _warm_kernels(self) -> None:
        """Load (or, on a cold cache, compile) the relative pose's kernels before READY=1, so the first
        frame is not held up by them and the watchdog is not asked to wait through a compilation."""
        sdnotify.notify("STATUS=loading the compiled kernels")
        t0 = self._wall.now_s()
        warm_kernels()
        took_s = self._wall.now_s() - t0
        if took_s > 5.0:
            log.warning(
                "compiled the kernels in %.0f s (a cold cache: the first start after an install or update; NUMBA_CACHE_DIR keeps them)",
                took_s,
            )
        else:
            log.info("kernels loaded in %.1f s", took_s)

    def run(self) -> DaemonSummary:
        """Run until stopped (signal, :meth:`request_stop`), until a finite source ends and its frames
        are processed, or until the service cannot go on (a thread died, the camera is lost: the
        summary's ``failure`` says which). Installs SIGTERM/SIGINT/SIGHUP handlers when called from
        the main thread."""
        previous = {}
        if threading.current_thread() is threading.main_thread():
            previous = {s: signal.signal(s, self.on_signal) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
        link_stop = threading.Event()
        threads = [
            threading.Thread(
                target=self._guarded, args=("link", self.link.run, link_stop), name="mavvo-link", daemon=True
            ),
            threading.Thread(
                target=self._guarded, args=("camera", self._camera_loop), name="mavvo-camera", daemon=True
            ),
            threading.Thread(
                target=self._guarded, args=("worker", self._worker_loop), name="mavvo-worker", daemon=True
            ),
        ]
        try:
            self._warm_kernels()
            for t in threads:
                t.start()
            m = self.config.mounting
            log.info(
                "mavvo running: link %s, camera %s; camera lever arm %s m: set VISO_POS_X/Y/Z (ArduPilot) or EKF2_EV_POS_X/Y/Z (PX4) to it",
                self.config.link.url,
                self.config.camera.source,
                list(m.lever_arm_m),
            )
            sdnotify.notify("READY=1")
            self._supervise()
        finally:
            sdnotify.notify("STOPPING=1")
            self.stop_event.set()
            deadline = self._wall.now_s() + self.config.service.shutdown_drain_s
            self._join(threads[1:], deadline)
            self._send_state_text(self.clock.now_s(), force=True)
            link_stop.set()  # after the worker: its last messages go out in the link's drain
            self._join(threads[:1], max(deadline, self._wall.now_s() + 0.1))
            self.source.close()
            if self.recorder is not None:
                self.recorder.close(drain=not self._force_stop.is_set())
            for s, h in previous.items():
                signal.signal(s, h)
        summary = self.summary()
        self._log_health(final=True)
        if summary.failure:
            log.error("mavvo cannot go on: %s", summary.failure)
        return summary

    def _join(self, threads: list[threading.Thread], deadline: float) -> None:
        """Join until ``deadline`` (real time), in slices, so that a second signal cuts the wait short."""
        for t in threads:
            while t.is_alive() and not self._force_stop.is_set():
                left = deadline - self._wall.now_s()
                if left <= 0:
                    break
                t.join(min(left, _PAUSE_SLICE_S))
        if self._force_stop.is_set():
            log.warning("second stop signal: not waiting for the drain")

    def _guarded(self, name: str, target: Callable[..., None], *args: object) -> None:
        """A thread's body: if it dies, the service stops and its run ends with ``failure`` set (the
        process exits non-zero and systemd restarts it)."""
        try:
            target(*args)
        except BaseException as e:  # noqa: BLE001 - whatever killed the thread, the service must not go on without it
            log.critical(
                "the %s thread died: %s: %s", name, type(e).__name__, e, exc_info=not isinstance(e, CameraLost)
            )
            with self._state_lock:
                self._failure = self._failure or f"the {name} thread stopped: {type(e).__name__}: {e}"
            self.stop_event.set()

    def _pause(self, name: str, seconds: float) -> None:
        """Wait (real time) for ``seconds`` or the stop, in slices that each count as a turn of thread
        ``name``'s loop: a thread that waits on purpose is not stuck."""
        end = self._wall.now_s() + seconds
        while not self.stop_event.is_set():
            self.turns[name] += 1
            left = end - self._wall.now_s()
            if left <= 0:
                return
            self.stop_event.wait(min(left, _PAUSE_SLICE_S))

    def stuck_threads(self, now_wall_s: float, limit_s: float) -> list[str]:
        """The threads whose loops have not turned for more than ``limit_s`` (real time) as of
        ``now_wall_s``; the camera thread of a finite source that ended is not stuck. Called by the
        supervisor on every tick; thread-safe reads."""
        turns = {"link": self.link.turns, "camera": self.turns["camera"], "worker": self.turns["worker"]}
        stuck = []
        for name in _THREADS:
            seen, t_seen = self._turns_seen.get(name, (-1, now_wall_s))
            if turns[name] != seen:
                self._turns_seen[name] = (turns[name], now_wall_s)
            elif now_wall_s - t_seen > limit_s and not (name == "camera" and self._camera_done.is_set()):
                stuck.append(name)
        return stuck

    def _supervise(self) -> None:
        watchdog_s = sdnotify.watchdog_interval_s()
        stuck_limit_s = max(2 * (watchdog_s or 0.0), _STUCK_MIN_S)
        next_ping = self._wall.now_s()
        next_log = self.clock.now_s() + self.config.service.health_log_interval_s
        told_stuck: list[str] = []
        while not self.stop_event.wait(_SUPERVISE_TICK_S):
            if self._worker_done.is_set():
                break  # the source ended and every frame was processed
            if self._reopen.is_set():
                self._reopen.clear()
                if self.recorder is not None:
                    self.recorder.reopen()
            stuck = self.stuck_threads(self._wall.now_s(), stuck_limit_s)
            if stuck != told_stuck:
                if stuck:
                    self.counters["threads_stuck"] += 1
                    log.error(
                        "no progress for %.0f s in the %s thread(s): systemd's watchdog is no longer fed",
                        stuck_limit_s,
                        ", ".join(stuck),
                    )
                told_stuck = stuck
            # Only a service whose every thread makes progress keeps systemd's watchdog fed.
            if watchdog_s is not None and self._wall.now_s() >= next_ping:
                if not stuck:
                    sdnotify.notify("WATCHDOG=1")
                next_ping = self._wall.now_s() + watchdog_s
            self._report(self.clock.now_s())
            if self.clock.now_s() >= next_log:
                self._log_health()
                next_log = self.clock.now_s() + self.config.service.health_log_interval_s

    def _camera_loop(self) -> None:
        opts = self.config.camera
        backoff = 0.1
        failing_since: float | None = None  # real time of the first error in a row
        try:
            while not self.stop_event.is_set():
                self.turns["camera"] += 1
                try:
                    frame = self.source.read(0.2)
                except CameraEnded as e:
                    log.info("%s", e)
                    return
                except CameraLost:
                    raise  # retried for camera.lost_after_s already: the service ends, systemd restarts it
                except FrameRefused as e:
                    self.counters["frames_refused"] += 1
                    self._log_error("camera", e)
                    continue
                except Exception as e:  # a source that failed, or a broken driver: wait and retry, for a while
                    now = self._wall.now_s()
                    failing_since = now if failing_since is None else failing_since
                    if now - failing_since > opts.lost_after_s:
                        raise CameraLost(
                            f"camera.source {opts.source}: failing for {now - failing_since:.0f} s (camera.lost_after_s): {e}"
                        ) from e
                    self.counters["camera_errors"] += 1
                    self._log_error("camera", e)
                    self._pause("camera", backoff)
                    backoff = min(2 * backoff, opts.reconnect_max_s)
                    continue
                backoff, failing_since = 0.1, None
                if frame is None:
                    continue
                h, w = frame.image.shape[:2]
                if w > opts.width_px or h > opts.height_px:  # kept out of the queue: it could only fail, slowly
                    self.counters["frames_refused"] += 1
                    self._log_error(
                        "camera",
                        FrameRefused(
                            f"frame {frame.seq} is {w}x{h} px, larger than camera.width_px x height_px = {opts.width_px}x{opts.height_px}; refused"
                        ),
                    )
                    continue
                if len(self._arrival_s) > _ARRIVALS_KEPT:  # frames dropped from the queue never come back
                    self._arrival_s.clear()
                self._arrival_s[frame.seq] = self.clock.now_s()
                self.frames.put(frame, self.stop_event)
                self.counters["frames_queued"] += 1
        finally:
            self._camera_done.set()

    def _no_more_input(self) -> bool:
        """The service stops, or (lockstep) the frames ended: nothing will move the clock again."""
        return self.stop_event.is_set() or (not self.clock.realtime and self._camera_done.is_set())

    def _worker_loop(self) -> None:
        try:
            while not self.stop_event.is_set():
                self.turns["worker"] += 1
                frame = self._next_frame or self.frames.get(0.1)  # a frame taken out early goes first
                self._next_frame = None
                if frame is None:
                    if self._camera_done.is_set() and self.frames.empty():
                        return
                    continue
                try:
                    self._process(frame)
                except Exception as e:  # a bug must not take the service down; it is counted and logged
                    self.counters["errors"] += 1
                    self._log_error("worker", e, traceback=True)
                finally:
                    self.counters["frames_done"] += 1
        finally:
            self._ahead.close()
            self._worker_done.set()

    # ------------------------------------------------------------------ one frame

    def _process(self, frame: Frame) -> None:
        self.counters["frames"] += 1
        self._frame_in = (self._arrival_s.pop(frame.seq, self.clock.now_s()), self._wall.now_s())
        p = wait_for_pairing(self.fc, frame.t_exposure_s, self._no_more_input)
        if self.recorder is not None:
            self.recorder.frame(frame, p, self.clock.now_s())
        if p.status != "paired":
            # Never paired with a wrong attitude; tracked all the same, so a short gap in the
            # flight controller's stream does not cost the track.
            self.counters[f"skipped_attitude_{p.status}"] += 1
            self._track_only(frame)
            return
        if not self._heading_ready(p.yaw_settled, frame.t_exposure_s):
            self.counters["waiting_for_heading"] += 1
            self._track_only(frame)
            return
        fc_p = None if p.fc_position_ned_m is None else np.asarray(p.fc_position_ned_m)
        # The flight controller's yaw steers the heading only while it is settled (not converging after
        # a boot or reboot); meanwhile vision's heading carries on alone.
        fc_yaw = p.yaw_rad if p.yaw_settled else math.nan
        paired = PairedFrame(
            frame.image,
            frame.t_exposure_s,
            frame.seq,
            p.roll_rad,
            p.pitch_rad,
            fc_yaw,
            p.range_m,
            p.height_m,
            fc_p,
            p.attitude_gap_s,
            p.interpolation_sigma_rad,
            p.fc_armed,
        )
        try:
            est = self.odometry.step(paired, self._tracks(frame))
        except ValueError as e:  # a malformed image (wrong size, not grey 8-bit)
            self.counters["bad_frames"] += 1
            self._log_error("frame", e)
            return
        except Exception as e:  # a bug in the odometry: counted, logged, and tracking starts afresh
            self.counters["odometry_errors"] += 1
            self._log_error("odometry", e, traceback=True)
            self.odometry.restart()
            return
        self.counters["paired"] += 1
        if est is not None:
            self._publish(est)

    def _latency_s(self, t_exposure_s: float) -> float:
        """Exposure to now; on a lockstep clock (which stands still while the worker computes, and runs
        ahead with the camera thread), to the frame's arrival plus the real time the worker took."""
        if self.clock.realtime:
            return self.clock.now_s() - t_exposure_s
        t_in, wall_in = self._frame_in
        return (t_in - t_exposure_s) + (self._wall.now_s() - wall_in)

    def _odometry(self, est: PoseEstimate) -> dict[str, object]:
        out = self.config.output
        return messages.odometry(est, messages.autopilot_of(self.link.autopilot, out.autopilot), out.estimator_type)

    def _track_only(self, frame: Frame) -> None:
        try:
            self._tracks(frame)
        except ValueError as e:
            self.counters["bad_frames"] += 1
            self._log_error("frame", e)

    def _tracks(self, frame: Frame) -> Tracks:
        """The frame's tracks; then the next queued frame, if one is there, is taken from the queue
        and starts being tracked on the helper thread while this one is estimated."""
        tracks = self._ahead.tracks(frame.image)
        self.counters["tracked_ahead"] = self._ahead.ahead
        if self._next_frame is None:
            self._next_frame = self.frames.get(0.0)  # returns at once: None when nothing waits
        if self._next_frame is not None:
            self._ahead.start(self._next_frame.image)
        return tracks

    def _heading_ready(self, yaw_settled: bool, t_s: float) -> bool:
        """The first estimate waits until the flight controller's yaw has settled (north is taken from
        it), at most ``service.heading_wait_max_s``; then the operator is told north may be off."""
        if self._heading_wait_over:
            return True
        if self._first_paired_s is None:
            self._first_paired_s = t_s
        if yaw_settled:
            self._heading_wait_over = True
        elif t_s - self._first_paired_s >= self.config.service.heading_wait_max_s:
            self._heading_wait_over = True
            log.warning(
                "the flight controller's yaw has not settled after %.0f s: starting with it; north may be off",
                self.config.service.heading_wait_max_s,
            )
            self.link.send(
                "STATUSTEXT",
                messages.statustext_line(
                    "mavvo: FC yaw unsettled, north may be off", severity=messages.MAV_SEVERITY_WARNING
                ),
            )
        return self._heading_wait_over

    def _open_recorder(self) -> Recorder | None:
        """The recording ``record.dir`` asks for; None without one, or when it cannot be started (the
        service flies without it: logged, and told over MAVLink once the link is up)."""
        if not self.config.record.dir:
            return None
        try:
            return Recorder(self.config.record, config_yaml(self.config), self.clock, on_stop=self._recording_stopped)
        except RecordingError as e:
            self.counters["record_failed"] += 1
            log.error("%s; running without recording", e)
            self._pending_texts.append(
                messages.statustext_line("mavvo: recording failed to start", severity=messages.MAV_SEVERITY_WARNING)
            )
            return None

    def _recording_stopped(self, reason: str) -> None:
        """The recorder's writer thread stopped on a disk problem: the operator is told (vision goes on)."""
        self._pending_texts.append(
            messages.statustext_line(f"mavvo: recording stopped: {reason}", severity=messages.MAV_SEVERITY_WARNING)
        )

    def _first_reset_counter(self) -> int:
        """A ``reset_counter`` the flight controller has not seen from this service: one past the
        last one kept in ``service.state_file`` (written back at once), else derived from the clock."""
        path = self.config.service.state_file
        if path:
            try:
                last = int(json.loads(Path(path).read_text(encoding="utf-8"))["reset_counter"])
            except FileNotFoundError:
                last = -1
            except (OSError, ValueError, KeyError, TypeError) as e:
                log.warning(
                    "service.state_file %s: cannot read the last reset_counter (%s); starting from the clock", path, e
                )
                last = int(self.clock.now_s() * 10)
            first = (last + 1) % 256
            self._save_reset_counter(first)
            return first
        # No state file: a real clock's tenths of a second since the host's boot differ between two
        # starts of the service; a simulated one starts at 0, so runs repeat.
        return int(self.clock.now_s() * 10) % 256 if self.clock.realtime else 0

    def _save_reset_counter(self, counter: int) -> None:
        path = Path(self.config.service.state_file)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text(json.dumps({"reset_counter": counter}) + "\n", encoding="utf-8")
            tmp.replace(path)
        except OSError as e:
            self.counters["state_file_errors"] += 1
            self._log_error("state_file", e)

    def _publish(self, est: PoseEstimate) -> None:
        self.last_estimate = est
        if self.on_estimate is not None:
            self.on_estimate(est)
        self._set_state(est.diagnostics.state, est.diagnostics.reason)
        if self._reset_counter is not None and est.reset_counter != self._reset_counter:
            self.counters["resets"] += 1
            if self.config.service.state_file:
                self._save_reset_counter(est.reset_counter)
        self._reset_counter = est.reset_counter
        out = self.config.output
        if est.quality < 0:
            self.counters["not_sent_failed"] += 1
            if out.odometry and self._odometry_ok:  # once: the estimator says it has failed
                self.link.send("ODOMETRY", self._odometry(est))
            self._odometry_ok = False
        elif est.t_exposure_s - self._last_sent_t_s < 1.0 / out.max_rate_hz - 1e-6:
            self.counters["not_sent_rate"] += 1
        else:
            self._last_sent_t_s = est.t_exposure_s
            send_by_s = (
                est.t_exposure_s + out.max_age_s
            )  # later, the flight controller would fuse the past as the present
            self.link.send("VISION_POSITION_ESTIMATE", messages.vision_position_estimate(est), send_by_s=send_by_s)
            self.latency.add(self._latency_s(est.t_exposure_s))
            if out.speed_estimate:
                self.link.send("VISION_SPEED_ESTIMATE", messages.vision_speed_estimate(est), send_by_s=send_by_s)
            if out.odometry:
                self.link.send("ODOMETRY", self._odometry(est), send_by_s=send_by_s)
                self._odometry_ok = True
            self.counters["estimates_sent"] += 1

    # ------------------------------------------------------------------ the operator's view

    def _set_state(self, state: VisionState, reason: StateReason) -> None:
        with self._state_lock:
            if state == self.state:
                return
            log.info("state %s -> %s%s", self.state, state, f" ({reason})" if reason else "")
            self.state = state
            self._pending_states.append((state, reason))

    def _send_state_text(self, now: float, *, force: bool = False) -> None:
        """The state changes not yet told, merged into one STATUSTEXT: at most one per
        ``output.statustext_min_interval_s``, or now when ``force`` (at shutdown, so that the ground
        station learns the last state even when it came within the interval)."""
        with self._state_lock:
            text = None
            if self._pending_states and (
                force or now - self._last_text_s >= self.config.output.statustext_min_interval_s
            ):
                text = messages.statustext_merged(self._pending_states)
                self._pending_states, self._last_text_s = [], now
        if text is not None:
            self.link.send("STATUSTEXT", text)

    def _report(self, now: float) -> None:
        """From the supervisor: notice when estimates stop coming, send the pending STATUSTEXT (rate
        limited) and the health values."""
        est = self.last_estimate
        counters = _snapshot(self.counters)
        skipped = sum(v for k, v in counters.items() if k.startswith("skipped_attitude"))
        for step in self.fc.take_clock_steps():
            log.warning("flight controller clock stepped %+.3f s (%s); re-synchronised", step.step_s, step.evidence)
            text = f"mavvo: FC clock stepped {step.step_s:+.2f} s; re-synced"
            self.link.send("STATUSTEXT", messages.statustext_line(text, severity=messages.MAV_SEVERITY_WARNING))
        self._tell_why_unpaired(now, counters)
        if est is not None and self.state != VisionState.FAILED and now - est.t_exposure_s > _NO_ESTIMATE_S:
            self._set_state(
                VisionState.FAILED,
                StateReason.NO_ATTITUDE if skipped > self._skipped_at_last_report else StateReason.NO_FRAMES,
            )
        self._skipped_at_last_report = skipped
        self._send_state_text(now)
        while self._pending_texts:  # from other threads (the recorder's): sent here, in order
            self.link.send("STATUSTEXT", self._pending_texts.popleft())
        if now >= self._next_health_s:
            period = 1.0 / self.config.output.health_rate_hz
            # On the period's grid, so the rate holds however coarse the supervisor's ticks are.
            self._next_health_s = self._next_health_s + period if now < self._next_health_s + period else now + period
            latency = self.latency.stats()
            fresh = est is not None and now - est.t_exposure_s <= _NO_ESTIMATE_S
            values = (
                ("VO_QUAL", est.quality if fresh else -1),
                ("VO_INLIER", est.diagnostics.inliers if fresh else 0),
                ("VO_STATE", messages.STATE_CODES[self.state]),
                ("VO_LAT_MS", latency.p50_ms if latency is not None else math.nan),
                ("VO_DRIFT", est.drift_m if est is not None else math.nan),
            )
            t_ms = int(now * 1000)
            for name, value in values:
                self.link.send("NAMED_VALUE_FLOAT", messages.named_value_float(t_ms, name, value))

    def _tell_why_unpaired(self, now: float, counters: dict[str, int]) -> None:
        """When no frame has paired for ``_UNPAIRED_TELL_S`` and one cause alone grew meanwhile, say
        which and the key to change (STATUSTEXT and log), once per cause until frames pair again."""
        snap = (now, counters.get("paired", 0), {k: counters.get(k, 0) for k in _UNPAIRED_CAUSES})
        history = self._unpaired_history
        history.append(snap)
        while len(history) > 1 and history[1][0] <= now - _UNPAIRED_TELL_S:
            history.popleft()
        t0, paired0, causes0 = history[0]
        if snap[1] != paired0:
            self._unpaired_told = None
            return
        grown = [k for k, v in snap[2].items() if v > causes0[k]]
        if now - t0 < _UNPAIRED_TELL_S or len(grown) != 1 or grown[0] == self._unpaired_told:
            return
        cause = self._unpaired_told = grown[0]
        text = short = _UNPAIRED_CAUSES[cause]
        if cause == "skipped_attitude_stale":
            rate = self.fc.attitude_rate_hz()
            gap_s = self.config.timing.max_attitude_gap_s
            if rate is not None and rate * gap_s >= _SAMPLES_PER_GAP:  # the rate would do: the stream stalls
                text = f"ATTITUDE arrives at {rate:.0f} Hz but stalls for more than timing.max_attitude_gap_s ({gap_s:g} s)"
                short = f"ATTITUDE stalls > {gap_s:g} s"
            elif rate is not None:
                want = max(self.config.camera.rate_hz, 2 * rate)
                text = f"ATTITUDE arrives at {rate:.0f} Hz; raise link.attitude_rate_hz to {want:.0f}"
                short = f"ATTITUDE {rate:.0f} Hz; link.attitude_rate_hz {want:.0f}"  # STATUSTEXT holds 50 characters
        log.warning("no frame paired for %.0f s: %s", now - t0, text)
        self.link.send(
            "STATUSTEXT", messages.statustext_line(f"mavvo: {short}", severity=messages.MAV_SEVERITY_WARNING)
        )

    # ------------------------------------------------------------------ health

    def _system_status(self) -> SystemStatus:
        return _SYSTEM_STATUS[self.state]

    def health(self) -> dict[str, int]:
        """Every counter of the service and its parts."""
        c = _snapshot(self.counters)
        c.update({f"link_{k}": v for k, v in _snapshot(self.link.counters).items()})
        c.update({f"fc_{k}": v for k, v in _snapshot(self.fc.counters).items()})
        c["frames_dropped"] = self.frames.dropped
        c["camera_reconnects"] = getattr(self.source, "reconnects", 0)
        if self.recorder is not None:
            c.update({f"record_{k}": v for k, v in _snapshot(self.recorder.counters).items()})
        return dict(sorted(c.items()))

    def summary(self) -> DaemonSummary:
        return DaemonSummary(self.health(), self.state, self.latency.stats(), self._failure)

    def _log_health(self, final: bool = False) -> None:
        h = self.health()
        latency = self.latency.stats()
        lat = "" if latency is None else f"; {latency.advice()}"
        keys = (
            "frames",
            "paired",
            "estimates_sent",
            "not_sent_failed",
            "resets",
            "frames_dropped",
            "bad_frames",
            "skipped_attitude_wait",
            "skipped_attitude_stale",
            "skipped_attitude_missing",
            "fc_attitude_rejected",
            "link_bad_data",
            "link_reconnects",
            "link_reboots",
            "camera_errors",
            "camera_reconnects",
            "errors",
            "record_frames",
            "record_dropped_frames",
            "record_dropped_messages",
        )
        counts = ", ".join(f"{k} {h[k]}" for k in keys if h.get(k))
        log.info("%s: state %s; %s%s", "final" if final else "health", self.state, counts or "nothing yet", lat)

    def _log_error(self, where: str, e: BaseException, traceback: bool = False) -> None:
        self._errors_logged[where] += 1
        n = self._errors_logged[where]
        if n <= 3 or n % _ERROR_LOG_EVERY == 0:
            log.warning("%s: %s (occurrence %d)", where, e, n, exc_info=traceback)
