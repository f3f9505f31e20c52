"""The flight controller's boot clock on the host clock.

Two clocks meet here. The host clock (``t_host_s``: ``time.monotonic`` on a drone, the simulation clock
in the simulator) stamps camera exposures, message arrivals and every estimate mavvo sends. The flight
controller's boot clock (``t_fc_s``, ATTITUDE.time_boot_ms / 1000) stamps its measurements. The offset
``t_fc_s - t_host_s`` comes from two kinds of evidence (:class:`ClockSync`):

- arrivals: a message cannot arrive before it was measured, so ``t_fc - t_arrival`` is a lower bound on
  the offset, reached by the fastest message (the minimum-latency filter). The bound keeps the fastest of
  each half second over ``sync_window_s`` and follows the clocks' rate difference (a fitted slope);
- TIMESYNC round trips: an answer puts the offset between ``t_fc - t_arrival`` and ``t_fc - t_sent``
  (widened by ``timesync_early_s``: ArduPilot stamps the estimated arrival of the request's first byte,
  PX4 the moment it handles it); the midpoint of the shortest round trip in the window is the estimate
  where it lies above the arrival bound. Answers leave the window by age.

Neither moves on one say-so (an unsigned link lets anyone send a 26-byte TIMESYNC or ATTITUDE): once
``sync_warmup_samples`` arrivals have set the bound, a message stamped more than ``clock_step_max_s``
ahead of it is held as a suspect and used only if the next one agrees (a faster path; a jump ahead
of more than ``clock_step_min_s`` starts the bound afresh); a TIMESYNC answer that disagrees with the
bound is refused. Both are counted. But a genuine clock does step back: an autopilot starved of CPU, or
a stalled USB or serial link, falls behind and never makes the time up. Then every arrival sits below
the bound; a TIMESYNC answer that rules the old offset out confirms the step at once (a slower link
would show in its round trip instead), and from a flight controller that answers no TIMESYNC,
``clock_step_confirm_s`` of it does. ATTITUDE samples from before the step are dropped, and the step is
reported (``steps``). A reboot (the boot clock going back) is the
link's to detect.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from mavvo.types import StrEnum

__all__ = ["ClockStep", "ClockSync", "Evidence"]

_MAX_LATENCY_S = 0.1  # the fastest message in a sync window took at most this long to arrive
_BUCKET_S = 0.5  # the arrival bound keeps the fastest message of each half second
_DRIFT_FIT_MIN_S = 10.0  # the clocks' rate difference is fitted once the kept maxima span this long
_DRIFT_MAX = 1e-3  # a fitted rate difference beyond 1000 ppm is not a crystal's: clamped
_NO_TIMESYNC_S = 3.0  # no TIMESYNC answer for this long: arrivals alone may confirm a step back


class Evidence(StrEnum):
    """What one arrival or TIMESYNC answer did to the clock estimate."""

    USED = "used"
    REFUSED = "refused"  # implausible: held back, counted
    STEPPED = "stepped"  # it confirmed a step of the flight controller's clock: the estimate moved


@dataclass(frozen=True)
class ClockStep:
    """The flight controller's clock moved against the host's: ``step_s`` (negative: it fell behind, as a
    stalled autopilot's does) at host time ``t_host_s``, holding for its samples from ``t_fc_from_s`` on.
    ``evidence``: ``timesync`` (an answer with a short round trip) or ``arrivals`` (they alone, for
    ``step_confirm_s``, from a flight controller that does not answer TIMESYNC; or a forward step, which
    two messages in a row confirm)."""

    t_host_s: float
    step_s: float
    t_fc_from_s: float
    evidence: str


class ClockSync:
    """The offset ``t_fc_s - t_host_s`` from message arrivals and TIMESYNC round trips (see the module
    docstring), on the latest evidence's host time. Not thread-safe: :class:`FlightControllerState`
    holds the lock.

    The arrival bound keeps the largest ``t_fc - t_arrival`` of each half second over ``window_s`` and
    follows the clocks' rate difference: ``bound(t) = max_i(v_i + rate (t - t_i))`` with ``rate`` the
    least-squares slope of those maxima (a crystal's tens of ppm; a software autopilot that loses time
    under load, hundreds).
    """

    def __init__(
        self,
        window_s: float = 30.0,
        step_max_s: float = 0.005,
        warmup_samples: int = 50,
        step_min_s: float = 0.02,
        step_confirm_s: float = 1.0,
        timesync_early_s: float = 0.02,
    ) -> None:
        self.window_s = window_s
        self.step_max_s = step_max_s
        self.warmup_samples = warmup_samples
        self.step_min_s = step_min_s
        self.step_confirm_s = step_confirm_s
        self.timesync_early_s = timesync_early_s
        self.steps: list[ClockStep] = []
        self.reset()

    def reset(self) -> None:
        """Forget everything (the flight controller rebooted)."""
        self._buckets: deque[tuple[int, float, float]] = deque()  # (index, t_arrival, max of t_fc - t_arrival)
        self._rate = 0.0  # d(offset)/dt, fitted
        self._syncs: deque[tuple[float, float, float]] = deque()  # accepted answers: (t_arrival, rtt, offset)
        self._answers: deque[tuple[float, float, float, float]] = deque()  # recent answers: (t_arrival, lo, hi, rtt)
        self._arrivals = 0
        self._suspect: tuple[float, float] | None = None  # (t_arrival, value) of a message ahead of the bound
        self._behind: tuple[float, float, float] | None = None  # (since, t_fc of the first, max value) below it
        self._t_last: float | None = None  # host time of the latest evidence: the estimate is for then

    # ------------------------------------------------------------------ the bound

    def _bound_at(self, t: float) -> float | None:
        if not self._buckets:
            return None
        return max(v + self._rate * (t - tb) for _, tb, v in self._buckets)

    def _push(self, t: float, value: float) -> None:
        k = math.floor(t / _BUCKET_S)
        b = self._buckets
        if b and b[-1][0] >= k:
            if value > b[-1][2]:
                b[-1] = (b[-1][0], t, value)
            return
        b.append((k, t, value))
        while b[0][1] < t - self.window_s:
            b.popleft()
        if b[-1][1] - b[0][1] >= _DRIFT_FIT_MIN_S:  # a bucket closed: fit the rate over the closed ones
            closed = list(b)[:-1]
            ts, vs = [x[1] for x in closed], [x[2] for x in closed]
            tm, vm = sum(ts) / len(ts), sum(vs) / len(vs)
            slope = sum((a - tm) * (c - vm) for a, c in zip(ts, vs)) / sum((a - tm) ** 2 for a in ts)
            self._rate = min(max(slope, -_DRIFT_MAX), _DRIFT_MAX)

    def _step_to(self, t: float, old: float, new: float, t_fc_from: float, evidence: str) -> None:
        """The clock stepped: the bound starts again from ``new`` at ``t`` (the rate carries over)."""
        self._buckets.clear()
        self._push(t, new)
        self._syncs.clear()
        self._behind = self._suspect = None
        self.steps.append(ClockStep(t, new - old, t_fc_from, evidence))

    # ------------------------------------------------------------------ evidence

    def add_arrival(self, t_fc_s: float, t_arrival_host_s: float) -> Evidence:
        """A message measured at ``t_fc_s`` arrived at ``t_arrival_host_s``. REFUSED for a single message
        stamped implausibly far ahead of every earlier one; STEPPED when it confirmed a step."""
        t, value = t_arrival_host_s, t_fc_s - t_arrival_host_s
        self._t_last = t
        bound = self._bound_at(t)
        warm = bound is not None and self._arrivals >= self.warmup_samples
        self._arrivals += 1
        if warm and value > bound + self.step_max_s:  # ahead of every earlier message
            s = self._suspect
            if s is None or t - s[0] > 1.0 or abs(value - s[1]) > self.step_max_s:
                self._suspect = (t, value)
                self._arrivals -= 1
                return Evidence.REFUSED
            self._suspect = self._behind = None
            if value - bound > self.step_min_s:  # the clock jumped ahead: what came before says nothing now
                self._step_to(t, bound, value, s[1] + s[0], "arrivals")
                return Evidence.STEPPED
            self._push(t, value)  # a faster path
            return Evidence.USED
        self._suspect = None
        if warm and value < bound - self.step_min_s:  # below the bound: a slow message, a backlog, or a step
            since, fc_from, top = self._behind or (t, t_fc_s, value)
            self._behind = (since, fc_from, max(top, value))
            return self._confirm_behind(t, bound)
        self._behind = None  # a message as fast as ever: the clock has not stepped
        self._push(t, value)
        return Evidence.USED

    def _confirm_behind(self, t: float, bound: float) -> Evidence:
        """Every arrival since ``_behind[0]`` sat well below the bound. A TIMESYNC answer since then
        that rules the old bound out and allows the new level confirms a step at once; without
        TIMESYNC answers for ``_NO_TIMESYNC_S``, persistence for ``step_confirm_s`` does. (A slower
        link looks the same to arrivals; only a short round trip tells the two apart.)"""
        since, fc_from, level = self._behind  # type: ignore[misc]
        tol = self.step_max_s
        for t_a, lo, hi, _ in self._answers:
            # An answer from just before the first late arrival counts: after a stall the flight controller
            # may answer the request it found waiting before it sends anything else.
            if t_a < since - self.step_confirm_s or hi + tol >= bound:
                continue  # older, or it allows the old bound
            if lo - tol <= level + _MAX_LATENCY_S and level <= hi + tol:  # and it allows the new level
                self._step_to(t, bound, max(level, lo), fc_from, "timesync")
                return Evidence.STEPPED
        quiet = not self._answers or self._answers[-1][0] < t - _NO_TIMESYNC_S
        if quiet and t - since >= self.step_confirm_s:
            self._step_to(t, bound, level, fc_from, "arrivals")
            return Evidence.STEPPED
        return Evidence.USED

    def add_timesync(self, t_sent_host_s: float, t_fc_s: float, t_arrival_host_s: float) -> Evidence:
        """A TIMESYNC request sent at ``t_sent_host_s`` was answered with the flight controller's time
        ``t_fc_s`` and the answer arrived at ``t_arrival_host_s``. The answer puts the offset in
        ``[t_fc - t_arrival, t_fc - t_sent + timesync_early_s]`` (the flight controller stamps a moment
        between the two, ArduPilot up to ``timesync_early_s`` before the request's arrival). REFUSED
        when that disagrees with the arrivals' bound (kept as evidence of a step); STEPPED when it
        confirmed one."""
        t = t_arrival_host_s
        rtt = t - t_sent_host_s
        if rtt < 0:
            return Evidence.REFUSED
        self._t_last = t
        lo, hi = t_fc_s - t, t_fc_s - t_sent_host_s + self.timesync_early_s
        self._answers.append((t, lo, hi, rtt))
        while self._answers[0][0] < t - 2 * _NO_TIMESYNC_S:
            self._answers.popleft()
        bound = self._bound_at(t)
        stepped = bound is not None and self._behind is not None and self._confirm_behind(t, bound) is Evidence.STEPPED
        bound = self._bound_at(t)
        # The true offset is at least the bound and at most the bound plus the fastest message's latency.
        tol = self.step_max_s
        if bound is not None and not (lo - tol <= bound + _MAX_LATENCY_S and bound - tol <= hi):
            return Evidence.STEPPED if stepped else Evidence.REFUSED
        self._syncs.append((t, rtt, t_fc_s - (t_sent_host_s + 0.5 * rtt)))
        return Evidence.STEPPED if stepped else Evidence.USED

    # ------------------------------------------------------------------ the estimate

    @property
    def doubts_offset(self) -> bool:
        """Every arrival lately sat well below the bound: a step back, or a slower link."""
        return self._behind is not None

    def offset_s(self) -> float | None:
        """The estimate at the latest evidence's time, or None before any."""
        t = self._t_last
        if t is None:
            return None
        bound = self._bound_at(t)
        sync = self._best_sync(t)
        if sync is None:
            return bound
        offset = sync[2] + self._rate * (t - sync[0])
        return offset if bound is None else max(offset, bound)

    def _best_sync(self, t: float) -> tuple[float, float, float] | None:
        """The accepted answer with the shortest round trip within the window (older ones leave by age)."""
        while self._syncs and self._syncs[0][0] < t - self.window_s:
            self._syncs.popleft()
        return min(self._syncs, key=lambda s: s[1], default=None)

    def round_trip_s(self) -> float | None:
        """The shortest TIMESYNC round trip in the window (the offset's error is at most half of it)."""
        best = None if self._t_last is None else self._best_sync(self._t_last)
        return None if best is None else best[1]
