"""The service: link, camera and worker threads wired together, with a clean stop. The daemon owns the
threads and their supervision; its parts each do one job: :mod:`~mavvo.service.pairing` (a frame with the
flight controller's state, the wait for a settled yaw), :mod:`~mavvo.service.publisher` (estimates to the
flight controller), :mod:`~mavvo.service.operator` (STATUSTEXT, health values, advice, log lines),
:mod:`~mavvo.service.state_file` (what survives a restart), :mod:`~mavvo.service.progress` (what a
lockstep driver and the caller see).

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

import logging
import signal
import threading
import time
from collections import Counter, deque
from typing import Callable

from mavvo.errors import CameraEnded, CameraLost, FrameRefused
from mavvo.estimation.warmup import warm_kernels
from mavvo.odometry.ahead import TrackAhead
from mavvo.odometry.frontend import Tracks
from mavvo.odometry.pipeline import Odometry
from mavvo.service import messages, sdnotify
from mavvo.service.camera import FrameQueue, FrameSource, SourceFactory, open_source
from mavvo.service.latency import LatencyTracker
from mavvo.service.link import Link
from mavvo.service.operator import ErrorLog, OperatorReports, snapshot
from mavvo.service.pairing import HeadingWait, paired_frame
from mavvo.service.progress import DaemonSummary, LockstepProgress
from mavvo.service.publisher import Publisher
from mavvo.service.recorder import Recorder, RecordingError
from mavvo.service.settings import ServiceConfig, config_yaml
from mavvo.service.state_file import ResetCounterFile
from mavvo.service.timing import Clock, FlightControllerState, MonotonicClock, wait_for_pairing
from mavvo.types import Frame, PoseEstimate, VisionState

__all__ = ["Daemon"]

log = logging.getLogger(__name__)

_SUPERVISE_TICK_S = 0.1
_ARRIVALS_KEPT = 64
_LOCKSTEP_POLL_S = 1e-4  # how often wait_progress looks (real time)
_STUCK_MIN_S = 2.0  # a thread whose loop has not turned for this long (at least) stops the watchdog's feeding
_PAUSE_SLICE_S = 0.25  # long waits are cut into slices, each a turn of the thread's loop
_THREADS = ("link", "camera", "worker")


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
        self.fc = FlightControllerState(self.clock, config.timing)
        self.source = source if source is not None else open_source(config.camera, self.clock, schemes, self.fc)
        self.counters: Counter[str] = Counter()
        self._log_error = ErrorLog()
        # STATUSTEXTs other threads (the recorder's) ask the supervisor to send; the operator's reports send them.
        self._texts: deque[dict[str, object]] = deque()
        self.recorder: Recorder | None = None
        try:
            self.recorder = self._open_recorder()
            self.link = Link(
                config.link,
                self.clock,
                self.fc,
                lambda: self.reports.system_status(),
                tap=self.recorder.mavlink if self.recorder else None,
            )
        except BaseException:
            self.source.close()
            if self.recorder is not None:
                self.recorder.close()
            raise
        self.latency = LatencyTracker(self.link.baud)
        self.reports = OperatorReports(config, self.link, self.fc, self.counters, self.latency, self._texts)
        self.frames = FrameQueue(config.camera.queue_size, drop_oldest=self.clock.realtime)
        self.stop_event = threading.Event()
        self._camera_done = threading.Event()
        self._worker_done = threading.Event()
        self._reopen = threading.Event()  # SIGHUP: the recording's files are to be reopened
        self._force_stop = threading.Event()  # a second stop signal: no drain
        self._failure = ""  # why the service cannot go on (a thread died); empty while it can
        self.turns: Counter[str] = Counter()  # loop turns of the camera and worker threads (the link counts its own)
        self._turns_seen: dict[str, tuple[int, float]] = {}  # thread -> (turns, real time they last changed)
        self._wall = wall_clock or MonotonicClock()
        reset_file = ResetCounterFile(config.service.state_file, self.clock, self._state_file_error)
        self.odometry = Odometry(
            config.camera.camera_model(),
            config.mounting.rotation(),
            config.odometry,
            reset_counter=reset_file.first(),
            readout_s=config.camera.readout_ms * 1e-3,
        )
        # The odometry is looked up at each call: a test may put another in its place.
        self._ahead = TrackAhead(lambda image: self.odometry.track(image), thread=config.service.track_ahead)
        self._next_frame: Frame | None = None  # taken from the queue by the worker, its tracking started
        self._failure_lock = threading.Lock()
        self._odometry_cpu_s = 0.0  # the worker thread's CPU time in the odometry (thread_time)
        self._heading_wait = HeadingWait(config.service.heading_wait_max_s, self.reports.warn)
        self.publisher = Publisher(
            config.output,
            self.link,
            self.reports,
            self.counters,
            self.latency,
            self._latency_s,
            reset_file,
            on_estimate,
        )
        self._arrival_s: dict[int, float] = {}  # frame seq -> host time the camera thread got it
        self._frame_in: tuple[float, float] = (0.0, 0.0)  # (host clock when it arrived, real time the worker took it)

    @property
    def state(self) -> VisionState:
        """The service's state, as the operator is told it."""
        return self.reports.state

    @property
    def last_estimate(self) -> PoseEstimate | None:
        return self.publisher.last_estimate

    def _state_file_error(self, e: OSError) -> None:
        self.counters["state_file_errors"] += 1
        self._log_error("state_file", e)

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
        log.info("loading the compiled kernels (compiled first where the cache has none: about a minute)")
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
            self.reports.send_state_text(self.clock.now_s(), force=True)
            link_stop.set()  # after the worker: its last messages go out in the link's drain
            self._join(threads[:1], max(deadline, self._wall.now_s() + 0.1))
            self.source.close()
            if self.recorder is not None:
                self.recorder.close(drain=not self._force_stop.is_set())
            for s, h in previous.items():
                signal.signal(s, h)
        summary = self.summary()
        self.reports.log_health(self.health(), final=True)
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
            with self._failure_lock:
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
            self.reports.report(self.clock.now_s(), self.last_estimate)
            if self.clock.now_s() >= next_log:
                self.reports.log_health(self.health())
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
        if not self._heading_wait.ready(p.yaw_settled, frame.t_exposure_s):
            self.counters["waiting_for_heading"] += 1
            self._track_only(frame)
            return
        cpu0 = time.thread_time()
        try:
            est = self.odometry.step(paired_frame(frame, p), self._tracks(frame))
        except ValueError as e:  # a malformed image (wrong size, not grey 8-bit)
            self.counters["bad_frames"] += 1
            self._log_error("frame", e)
            return
        except Exception as e:  # a bug in the odometry: counted, logged, and tracking starts afresh
            self.counters["odometry_errors"] += 1
            self._log_error("odometry", e, traceback=True)
            self.odometry.restart()
            return
        finally:
            self._odometry_cpu_s += time.thread_time() - cpu0
        self.counters["paired"] += 1
        if est is not None:
            self.publisher.publish(est)

    def _latency_s(self, t_exposure_s: float) -> float:
        """Exposure to now; on a lockstep clock (which stands still while the worker computes, and runs
        ahead with the camera thread), to the frame's arrival plus the real time the worker took."""
        if self.clock.realtime:
            return self.clock.now_s() - t_exposure_s
        t_in, wall_in = self._frame_in
        return (t_in - t_exposure_s) + (self._wall.now_s() - wall_in)

    def _track_only(self, frame: Frame) -> None:
        cpu0 = time.thread_time()
        try:
            self._tracks(frame)
        except ValueError as e:
            self.counters["bad_frames"] += 1
            self._log_error("frame", e)
        finally:
            self._odometry_cpu_s += time.thread_time() - cpu0

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
            self._texts.append(
                messages.statustext_line("mavvo: recording failed to start", severity=messages.MAV_SEVERITY_WARNING)
            )
            return None

    def _recording_stopped(self, reason: str) -> None:
        """The recorder's writer thread stopped on a disk problem: the operator is told (vision goes on)."""
        self._texts.append(
            messages.statustext_line(f"mavvo: recording stopped: {reason}", severity=messages.MAV_SEVERITY_WARNING)
        )

    # ------------------------------------------------------------------ health

    def health(self) -> dict[str, int]:
        """Every counter of the service and its parts."""
        c = snapshot(self.counters)
        c.update({f"link_{k}": v for k, v in snapshot(self.link.counters).items()})
        c.update({f"fc_{k}": v for k, v in snapshot(self.fc.counters).items()})
        c["frames_dropped"] = self.frames.dropped
        c["camera_reconnects"] = getattr(self.source, "reconnects", 0)
        if self.recorder is not None:
            c.update({f"record_{k}": v for k, v in snapshot(self.recorder.counters).items()})
        return dict(sorted(c.items()))

    def summary(self) -> DaemonSummary:
        return DaemonSummary(self.health(), self.state, self.latency.stats(), self._failure, self._odometry_cpu_s)
