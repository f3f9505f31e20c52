"""Clocks, the flight controller's boot clock on the host clock, and roll/pitch at each exposure.

Two clocks meet here. The host clock (``t_host_s``: ``time.monotonic`` on a drone, the simulation clock
in the simulator) stamps camera exposures, message arrivals and every estimate mavvo sends. The flight
controller's boot clock (``t_fc_s``, ATTITUDE.time_boot_ms / 1000) stamps its measurements; the offset
between the two is :mod:`mavvo.service.clock_sync`'s.

:class:`FlightControllerState` keeps the recent ATTITUDE samples (and the latest rangefinder and
height) and pairs a frame with roll/pitch/yaw interpolated at its exposure time (slerp between the two
samples around it). A frame is paired only between two samples that bracket it at most
``max_attitude_gap_s`` apart (inclusive); otherwise it waits for a newer sample or is skipped and
counted, never paired with a wrong attitude. The interpolation's own uncertainty, which grows with the
gap (``attitude_accel_rad_s2``), goes with the pairing: a slow stream (a telemetry log's 2 Hz) pairs
every frame and reports it degraded. Only this module reads a
clock, and the clock is injected.
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol

from mavvo.geometry.frames import interpolate_euler321
from mavvo.options import bounded
from mavvo.service.clock_sync import ClockStep, ClockSync, Evidence

__all__ = [
    "Clock",
    "MonotonicClock",
    "TimingOptions",
    "Pairing",
    "FlightControllerState",
    "wait_for_pairing",
]


class Clock(Protocol):
    """The host clock: seconds, monotonic. ``realtime`` is False for a simulated clock that moves only
    when the simulation moves it (lockstep): then waiting on it would never end, and waits are bounded
    by the data instead (see :func:`wait_for_pairing`)."""

    realtime: bool

    def now_s(self) -> float: ...


class MonotonicClock:
    """``time.monotonic``: the clock a drone's estimates are stamped with."""

    realtime = True

    def now_s(self) -> float:
        return time.monotonic()


@dataclass(frozen=True)
class TimingOptions:
    """Pairing frames with the flight controller's attitude."""

    max_attitude_gap_s: float = bounded(
        0.05, "longest gap between the two ATTITUDE samples around an exposure (inclusive)", gt=0, le=1
    )
    attitude_accel_rad_s2: float = bounded(
        1.0,
        "angular acceleration assumed between two ATTITUDE samples: sizes the uncertainty of roll/pitch interpolated between them (at the middle of a 0.5 s gap: 1.8 deg)",
        gt=0,
        le=100,
    )
    attitude_wait_s: float = bounded(
        0.1, "how long after an exposure to wait for the ATTITUDE that follows it", gt=0, le=1
    )
    range_max_age_s: float = bounded(
        0.2, "the rangefinder reading nearest the exposure is used if it is at most this far from it", gt=0, le=10
    )
    height_max_age_s: float = bounded(
        0.5, "the height reading nearest the exposure is used if it is at most this far from it", gt=0, le=10
    )
    sync_window_s: float = bounded(30.0, "window of the clock-offset filters (tracks clock drift)", gt=0, le=3600)
    clock_step_max_s: float = bounded(
        0.005,
        "an ATTITUDE stamped this much ahead of every earlier one is used only if the next one agrees (a single forged or broken stamp is refused)",
        gt=0,
        le=1,
    )
    clock_step_min_s: float = bounded(
        0.02,
        "every arrival this far below the clock bound: the flight controller's clock may have stepped back (a stalled autopilot), or the link slowed",
        gt=0,
        le=1,
    )
    clock_step_confirm_s: float = bounded(
        1.0,
        "a step back is confirmed by a TIMESYNC answer that rules out the old offset, or, from a flight controller that does not answer TIMESYNC, when it lasts this long",
        gt=0,
        le=10,
    )
    timesync_early_s: float = bounded(
        0.02,
        "how far before the request's arrival a TIMESYNC answer may be stamped (ArduPilot stamps the estimated arrival of its first byte from the port's baud rate)",
        ge=0,
        le=0.5,
    )
    sync_warmup_samples: int = bounded(
        50, "ATTITUDE arrivals that set the clock bound before the step check starts", ge=1, le=10000
    )
    history_s: float = bounded(2.0, "ATTITUDE history kept for pairing", gt=0, le=60)
    local_position_max_age_s: float = bounded(
        0.5,
        "the flight controller's LOCAL_POSITION_NED older than this at the exposure is not used to anchor",
        gt=0,
        le=10,
    )
    yaw_settle_window_s: float = bounded(
        1.5, "the flight controller's yaw counts as settled once, over this long, ...", gt=0, le=60
    )
    yaw_settle_rate_deg_s: float = bounded(
        0.1,
        "... it has moved against its own gyro (yaw minus integrated yaw rate, fitted slope) slower than this; an EKF's yaw converging after boot moves faster",
        gt=0,
        le=10,
    )


def _euler_yaw_rate(roll_rad: float, pitch_rad: float, body_rates_rad_s: tuple[float, float, float] | None) -> float:
    """d(yaw)/dt of Euler 3-2-1 angles from body rates (p, q, r): (q sin(roll) + r cos(roll)) / cos(pitch);
    NaN without rates."""
    if body_rates_rad_s is None:
        return math.nan
    _, q, r = body_rates_rad_s
    return (q * math.sin(roll_rad) + r * math.cos(roll_rad)) / math.cos(pitch_rad)


_READINGS_KEPT = 64  # rangefinder and height readings kept: seconds of them at usual rates
_GAP_SLACK_S = 1e-6  # time_boot_ms / 1000 is not exact in binary: 1.05 - 1.0 > 0.05
_WAIT_STEP_S = 0.02  # real time: the longest single wait for an ATTITUDE before looking again
_LOCKSTEP_LOOK_S = 0.002  # lockstep: how often (real time) a waiting worker looks whether the clock moved


@dataclass(frozen=True)
class Pairing:
    """The flight controller's state at one exposure.

    ``status``: ``paired`` (roll/pitch valid), ``wait`` (no ATTITUDE after the exposure yet), ``stale``
    (the samples around the exposure are too far apart: the stream stalled or was spoiled) or
    ``missing`` (no samples or no clock offset at all).
    """

    status: Literal["paired", "wait", "stale", "missing"]
    fc_version: int = 0  # how many flight-controller updates the state had absorbed (a replay resumes here)
    roll_rad: float = math.nan
    pitch_rad: float = math.nan
    yaw_rad: float = math.nan
    range_m: float | None = None
    height_m: float | None = None
    fc_position_ned_m: tuple[float, float, float] | None = None  # the flight controller's own estimate at the exposure
    yaw_settled: bool = False  # the flight controller's yaw has stopped converging (see FlightControllerState)
    attitude_gap_s: float = 0.0  # between the two ATTITUDE samples around the exposure (0: one fell on it)
    interpolation_sigma_rad: float = 0.0  # roll/pitch error the interpolation may add (see FlightControllerState.pair)
    fc_armed: bool | None = None  # the flight controller's last HEARTBEAT before the exposure said armed (None: none)


class FlightControllerState:
    """What the flight controller said recently, on both clocks; thread-safe (the link thread writes,
    the worker reads). Counters: ``attitude``, ``attitude_rejected`` (non-finite or not newer),
    ``attitude_implausible`` and ``timesync_implausible`` (refused by the clock's plausibility checks),
    ``timesync`` (answers accepted), ``clock_steps``, ``reboots``.

    Its own position estimate (LOCAL_POSITION_NED, the EKF's belief) is kept to anchor the odometry
    where the flight controller thinks the vehicle is. Its yaw counts as settled once ``yaw - integral
    of its rate`` (from the body rates ATTITUDE carries) has a fitted slope under ``yaw_settle_rate_deg_s`` over ``yaw_settle_window_s``: an
    EKF's yaw still converging after boot moves against its own gyro; without yawspeed the yaw is
    trusted.

    Each update carries the arrival time the link stamped once for its message (``t_arrival_host_s``;
    None: now on the clock), so a recorded flight replays with the same stamps. ``version`` counts the
    updates absorbed; each :class:`Pairing` says which version it saw, so a replay can pair a frame after
    exactly the same updates as the flight did.
    """

    def __init__(self, clock: Clock, options: TimingOptions = TimingOptions()) -> None:
        self.clock = clock
        self.options = options
        self.counters: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._new_data = threading.Condition(self._lock)
        self._sync = ClockSync(
            options.sync_window_s,
            options.clock_step_max_s,
            options.sync_warmup_samples,
            options.clock_step_min_s,
            options.clock_step_confirm_s,
            options.timesync_early_s,
        )
        self._steps_told = 0  # clock steps handed out by take_clock_steps
        self._t_fc: list[float] = []  # ATTITUDE times, increasing
        self._rpy: list[tuple[float, float, float]] = []
        # Recent readings, (t_fc_s, metres; None: no reading): a frame paired late (a slow ATTITUDE
        # stream) takes the one nearest its exposure, not the newest.
        self._range: deque[tuple[float, float | None]] = deque(maxlen=_READINGS_KEPT)
        self._height: deque[tuple[float, float | None]] = deque(maxlen=_READINGS_KEPT)
        # LOCAL_POSITION_NED samples (t_fc_s, p, v): a frame is anchored on the last one at or before its
        # exposure, moved on by its velocity, whatever arrived since (the same on every run of a recording).
        self._local: deque[tuple[float, tuple[float, float, float], tuple[float, float, float]]] = deque(
            maxlen=_READINGS_KEPT
        )
        self._yaw_drift: deque[tuple[float, float]] = deque()  # (t_fc_s, unwrapped yaw minus integrated yawspeed)
        self._yaw_prev: tuple[float, float, float] | None = None  # (t_fc_s, unwrapped yaw, yawspeed)
        self._yaw_samples = 0
        self._settled_at_fc_s: float | None = None  # the ATTITUDE time at which the yaw was judged settled
        self._ekf_good_since: float | None = None  # host time since which EKF_STATUS_REPORT says the yaw is good
        self._armed: deque[tuple[float, bool]] = deque(maxlen=_READINGS_KEPT)  # (arrival, armed) changes
        self.version = 0
        self._waiting_at: int | None = None  # the version a worker found nothing new at and waits on

    @property
    def yaw_settled(self) -> bool:
        """The flight controller's yaw has stopped converging (judged from the samples so far)."""
        return self._settled_at_fc_s is not None

    def _arrival(self, t_arrival_host_s: float | None) -> float:
        return self.clock.now_s() if t_arrival_host_s is None else t_arrival_host_s

    # ------------------------------------------------------------------ the link's side

    def on_attitude(
        self,
        t_fc_ms: int,
        roll_rad: float,
        pitch_rad: float,
        yaw_rad: float,
        t_arrival_host_s: float | None = None,
        body_rates_rad_s: tuple[float, float, float] | None = None,
    ) -> None:
        """An ATTITUDE message, just arrived (``body_rates_rad_s``: its rollspeed, pitchspeed,
        yawspeed). Non-finite roll/pitch and samples not newer than the last are dropped (counted): a
        repeated or spoiled stream must not be interpolated."""
        now = self._arrival(t_arrival_host_s)
        t = t_fc_ms * 1e-3
        with self._new_data:
            self._updated()
            evidence = self._sync.add_arrival(t, now)
            if evidence is Evidence.REFUSED:
                self.counters["attitude_implausible"] += 1
                return
            if evidence is Evidence.STEPPED:
                self._clock_stepped()
            if not (math.isfinite(roll_rad) and math.isfinite(pitch_rad)) or (self._t_fc and t <= self._t_fc[-1]):
                self.counters["attitude_rejected"] += 1
                return
            self.counters["attitude"] += 1
            self._watch_yaw(t, yaw_rad, _euler_yaw_rate(roll_rad, pitch_rad, body_rates_rad_s))
            self._t_fc.append(t)
            self._rpy.append((roll_rad, pitch_rad, yaw_rad if math.isfinite(yaw_rad) else math.nan))
            cut = bisect.bisect_left(self._t_fc, t - self.options.history_s)
            if cut > 64:  # trim in batches: list.pop(0) per sample would be quadratic
                del self._t_fc[:cut], self._rpy[:cut]

    def _watch_yaw(self, t: float, yaw: float, yawspeed: float) -> None:
        """Track ``yaw - integral(yawspeed)`` (unwrapped) and decide once whether the yaw has settled."""
        if self._settled_at_fc_s is not None or not math.isfinite(yaw):
            return
        if not math.isfinite(yawspeed):
            self._settled_at_fc_s = t  # nothing to judge it by: trust it, as the flight controller does
            return
        prev = self._yaw_prev
        if prev is None:
            unwrapped, drift = yaw, yaw
        else:
            t0, y0, w0 = prev
            unwrapped = y0 + math.remainder(yaw - y0, math.tau)
            drift = (
                self._yaw_drift[-1][1] + (unwrapped - y0) - 0.5 * (w0 + yawspeed) * (t - t0)
            )  # d = yaw - int(w dt), trapezoid
        self._yaw_prev = (t, unwrapped, yawspeed)
        self._yaw_drift.append((t, drift))
        window = self.options.yaw_settle_window_s
        while self._yaw_drift[0][0] < t - window:
            self._yaw_drift.popleft()
        self._yaw_samples += 1
        if self._yaw_drift[0][0] <= t - 0.9 * window and self._yaw_samples % 8 == 0:  # a fit every few samples
            ts = [a for a, _ in self._yaw_drift]
            ds = [b for _, b in self._yaw_drift]
            tm, dm = sum(ts) / len(ts), sum(ds) / len(ds)
            slope = sum((a - tm) * (b - dm) for a, b in zip(ts, ds)) / sum((a - tm) ** 2 for a in ts)  # least squares
            if abs(slope) <= math.radians(self.options.yaw_settle_rate_deg_s):
                self._settled_at_fc_s = t

    def on_local_position(
        self,
        t_fc_ms: int,
        p_ned_m: tuple[float, float, float],
        v_ned_m_s: tuple[float, float, float],
        t_arrival_host_s: float | None = None,
    ) -> None:
        """LOCAL_POSITION_NED: the flight controller's own estimate of its position and velocity."""
        with self._lock:
            self._updated()
            if all(math.isfinite(x) for x in (*p_ned_m, *v_ned_m_s)):
                t = t_fc_ms * 1e-3
                if not self._local or t > self._local[-1][0]:
                    self._local.append((t, tuple(p_ned_m), tuple(v_ned_m_s)))  # type: ignore[arg-type]

    def on_range(self, t_fc_ms: int, range_m: float | None, t_arrival_host_s: float | None = None) -> None:
        """A downward rangefinder reading (None: out of range or no target)."""
        with self._lock:
            self._updated()
            self._range.append((t_fc_ms * 1e-3, range_m if range_m is not None and math.isfinite(range_m) else None))

    def on_height(self, t_fc_ms: int, height_m: float, t_arrival_host_s: float | None = None) -> None:
        """The vehicle's height above home (take-off), metres, positive up."""
        with self._lock:
            self._updated()
            if math.isfinite(height_m):
                self._height.append((t_fc_ms * 1e-3, height_m))

    def on_armed(self, armed: bool, t_arrival_host_s: float | None = None) -> None:
        """The flight controller's HEARTBEAT: armed or not."""
        now = self._arrival(t_arrival_host_s)
        with self._lock:
            self._updated()
            if not self._armed or self._armed[-1][1] != armed:
                self._armed.append((now, armed))

    def on_ekf_status(self, attitude_good: bool, compass_ratio: float, t_arrival_host_s: float | None = None) -> None:
        """EKF_STATUS_REPORT: the autopilot's own word on its yaw. ArduPilot sets the attitude flag only
        once its yaw is aligned; ``compass_ratio`` is its compass innovation test ratio (< 1: inside its
        gate). Both holding for ``yaw_settle_window_s`` settles the yaw as well as the gyro test does:
        in flight a disturbed compass keeps moving the yaw against the gyro, and the wait would run to
        ``service.heading_wait_max_s``."""
        now = self._arrival(t_arrival_host_s)
        with self._lock:
            self._updated()
            if not (attitude_good and compass_ratio < 1.0):
                self._ekf_good_since = None
                return
            if self._ekf_good_since is None:
                self._ekf_good_since = now
            elif self._settled_at_fc_s is None and now - self._ekf_good_since >= self.options.yaw_settle_window_s:
                offset = self._sync.offset_s()
                if offset is not None:
                    self._settled_at_fc_s = now + offset  # on the flight controller's clock, as the gyro test's

    def on_timesync(self, t_sent_host_s: float, t_fc_s: float, t_arrival_host_s: float | None = None) -> None:
        """The answer to a TIMESYNC request that was sent at ``t_sent_host_s``."""
        now = self._arrival(t_arrival_host_s)
        with self._lock:
            self._updated()
            evidence = self._sync.add_timesync(t_sent_host_s, t_fc_s, now)
            self.counters["timesync_implausible" if evidence is Evidence.REFUSED else "timesync"] += 1
            if evidence is Evidence.STEPPED:
                self._clock_stepped()

    def _clock_stepped(self) -> None:
        """Under the lock: the clock offset moved. Samples from before the step sit on the old relation:
        an exposure mapped with the new offset must not be paired with them."""
        self.counters["clock_steps"] += 1
        step = self._sync.steps[-1]
        cut = bisect.bisect_left(self._t_fc, step.t_fc_from_s)
        if step.step_s < 0:
            del self._t_fc[:cut], self._rpy[:cut]

    def wants_timesync(self) -> bool:
        """Whether every arrival lately says the clock may have stepped: a TIMESYNC answer would settle it."""
        with self._lock:
            return self._sync.doubts_offset

    def take_clock_steps(self) -> list[ClockStep]:
        """The clock steps not handed out before (for the operator)."""
        with self._lock:
            steps = self._sync.steps[self._steps_told :]
            self._steps_told = len(self._sync.steps)
            return steps

    def on_reboot(self) -> None:
        """The boot clock went back: the flight controller restarted; forget its old clock and samples."""
        with self._lock:
            self._updated()
            self.counters["reboots"] += 1
            self._sync.reset()
            self._t_fc.clear()
            self._rpy.clear()
            self._range.clear()
            self._height.clear()
            self._local.clear()
            self._yaw_drift.clear()
            self._yaw_prev = None
            self._settled_at_fc_s = None
            self._ekf_good_since = None

    # ------------------------------------------------------------------ the worker's side

    def pair(self, t_exposure_host_s: float) -> Pairing:
        """The flight controller's state at an exposure (see :class:`Pairing`)."""
        with self._lock:
            return self._pair_locked(t_exposure_host_s)

    def _pair_locked(self, t_exposure_host_s: float) -> Pairing:
        v = self.version
        offset = self._sync.offset_s()
        if offset is None or not self._t_fc:
            return Pairing("missing", v)
        t = t_exposure_host_s + offset
        i = bisect.bisect_left(self._t_fc, t)
        if i == len(self._t_fc):
            return Pairing("wait", v)
        gap_s = sigma_rad = 0.0
        if self._t_fc[i] == t:
            roll, pitch, yaw = self._rpy[i]
        else:
            # Inclusive, to the boot clock's millisecond: samples exactly max_attitude_gap_s apart pair.
            if i == 0 or self._t_fc[i] - self._t_fc[i - 1] > self.options.max_attitude_gap_s + _GAP_SLACK_S:
                return Pairing("stale", v)
            t0, t1 = self._t_fc[i - 1], self._t_fc[i]
            (r0, p0, y0), (r1, p1, y1) = self._rpy[i - 1], self._rpy[i]
            known_yaw = math.isfinite(y0) and math.isfinite(y1)  # else roll/pitch as if yaw stood still
            roll, pitch, yaw = interpolate_euler321(
                (r0, p0, y0 if known_yaw else 0.0), (r1, p1, y1 if known_yaw else 0.0), (t - t0) / (t1 - t0)
            )
            yaw = yaw if known_yaw else math.nan
            gap_s = t1 - t0
            # Error of interpolating at constant rate when the rate changes at up to a: a/2 (t - t0)(t1 - t).
            sigma_rad = 0.5 * self.options.attitude_accel_rad_s2 * (t - t0) * (t1 - t)
        # Only what was sent before the ATTITUDE that completed the pairing counts: the flight controller
        # sends in time order, so all of it has been read by now, on every run alike (a reading sent
        # after it may or may not have arrived yet).
        t_limit = self._t_fc[i]
        range_m = _nearest(self._range, t, self.options.range_max_age_s, t_limit)
        height_m = _nearest(self._height, t, self.options.height_max_age_s, t_limit)
        fc_p = None
        local = None  # the last sample at or before the exposure; none before it: the first after
        for r in self._local:
            if r[0] >= t_limit or (local is not None and r[0] > t):
                break
            local = r
        if local is not None and abs(t - local[0]) <= self.options.local_position_max_age_s:
            t_l, p_l, v_l = local
            fc_p = (
                p_l[0] + v_l[0] * (t - t_l),
                p_l[1] + v_l[1] * (t - t_l),
                p_l[2] + v_l[2] * (t - t_l),
            )  # moved on to the exposure
        # Settled as of the exposure, not of whatever has arrived by now: the same on every run.
        settled = self._settled_at_fc_s is not None and self._settled_at_fc_s <= t
        # Armed as the last HEARTBEAT that arrived before the exposure said (arrivals are in order).
        armed = next((a for t_a, a in reversed(self._armed) if t_a <= t_exposure_host_s), None)
        return Pairing("paired", v, roll, pitch, yaw, range_m, height_m, fc_p, settled, gap_s, sigma_rad, armed)

    def clock_offset_s(self) -> float | None:
        """The current estimate of ``t_fc_s - t_host_s`` (None before the flight controller is heard)."""
        with self._lock:
            return self._sync.offset_s()

    def attitude_rate_hz(self) -> float | None:
        """The ATTITUDE rate over the kept history (its samples' own clock), or None with too few."""
        with self._lock:
            if len(self._t_fc) < 3 or self._t_fc[-1] <= self._t_fc[0]:
                return None
            return (len(self._t_fc) - 1) / (self._t_fc[-1] - self._t_fc[0])

    def _updated(self) -> None:
        """Under the lock: one more update absorbed (``version``); a worker waiting for data looks again."""
        self.version += 1
        self._new_data.notify_all()

    def wait_for_new_data(self, timeout_s: float, seen_version: int) -> None:
        """Block until the state has changed since ``seen_version`` or ``timeout_s`` of real time
        passes; returns at once when it already has. Meanwhile :meth:`waiting_for_data` is true."""
        with self._new_data:
            if self.version != seen_version:
                return
            self._waiting_at = seen_version
            try:
                self._new_data.wait(timeout_s)
            finally:
                self._waiting_at = None

    def waiting_for_data(self) -> bool:
        """Whether a worker is blocked in :meth:`wait_for_new_data` and nothing has changed since it
        looked: it can go on only when the flight controller sends more, or the clock moves on."""
        with self._lock:
            return self._waiting_at is not None and self._waiting_at == self.version


def _nearest(readings: deque[tuple[float, float | None]], t: float, max_age_s: float, t_limit: float) -> float | None:
    """The reading nearest ``t`` (before or after) among those stamped before ``t_limit``, or None when
    none is within ``max_age_s``."""
    best = min((r for r in readings if r[0] < t_limit), key=lambda r: abs(r[0] - t), default=None)
    return best[1] if best is not None and abs(best[0] - t) <= max_age_s else None


def wait_for_pairing(
    state: FlightControllerState, t_exposure_host_s: float, ended: Callable[[], bool] = lambda: False
) -> Pairing:
    """Pair an exposure, waiting for the ATTITUDE that follows it until ``attitude_wait_s`` after the
    exposure on the host clock, or until ``ended()`` says no more input will come (the service stops;
    on a lockstep clock, the frames ended); a frame still waiting then is ``stale``.

    The same rule on a lockstep clock: it stands still while the worker waits, and the driver moves it
    on once :meth:`FlightControllerState.waiting_for_data` says the worker cannot go on without more
    input; the worker looks at the clock again every few milliseconds of real time. What comes of a
    frame then depends on the simulated times alone, not on how fast a thread got to it.
    """
    deadline = t_exposure_host_s + state.options.attitude_wait_s
    while True:
        final = ended()  # asked first: whatever came before the end is then in the pairing below
        p = state.pair(t_exposure_host_s)
        if p.status != "wait":
            return p
        if final:
            return Pairing("stale", p.fc_version)
        left = deadline - state.clock.now_s()
        if left <= 0:
            return Pairing("stale", p.fc_version)
        state.wait_for_new_data(min(left, _WAIT_STEP_S) if state.clock.realtime else _LOCKSTEP_LOOK_S, p.fc_version)
