"""What the operator sees of the service: state changes as STATUSTEXT (rate limited), the health values
as NAMED_VALUE_FLOAT, advice when frames stop pairing, and the health lines in the log. Everything here
is sent from the supervisor's thread; other threads only queue."""

from __future__ import annotations

import logging
import math
import threading
from collections import Counter, deque

from mavvo.service import messages
from mavvo.service.latency import LatencyTracker
from mavvo.service.link import Link, SystemStatus
from mavvo.service.settings import ServiceConfig
from mavvo.service.timing import FlightControllerState
from mavvo.types import PoseEstimate, StateReason, VisionState

__all__ = ["ErrorLog", "OperatorReports", "snapshot"]

log = logging.getLogger(__name__)

_UNPAIRED_TELL_S = 2.0  # frames unpaired for one cause this long: the operator is told which and what to change
# ATTITUDE at this many samples per max_attitude_gap_s is fast enough: stale frames then mean stalls.
_SAMPLES_PER_GAP = 1.5
_UNPAIRED_CAUSES = {
    "skipped_attitude_stale": "ATTITUDE too sparse; raise link.attitude_rate_hz",
    "skipped_attitude_missing": "no ATTITUDE; check link.url",
    "skipped_attitude_wait": "ATTITUDE late; raise timing.attitude_wait_s",
    "waiting_for_heading": "waiting for the FC's yaw to settle",
}
_NO_ESTIMATE_S = 1.0  # no estimate for this long (host clock): the operator is told vision failed
_ERROR_LOG_EVERY = 100  # after the first few, log one repeated error in this many
_SYSTEM_STATUS = {
    VisionState.STANDBY: SystemStatus.STANDBY,
    VisionState.INITIALISING: SystemStatus.ACTIVE,
    VisionState.TRACKING: SystemStatus.ACTIVE,
    VisionState.DEGRADED: SystemStatus.CRITICAL,
    VisionState.FAILED: SystemStatus.CRITICAL,
}
_HEALTH_LOG_KEYS = (
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


def snapshot(counter: Counter[str]) -> dict[str, int]:
    """A copy of a counter that another thread adds keys to. ``dict(counter)`` copies in one C call
    under the GIL; iterating the live counter could meet a new key and raise."""
    return dict(counter)


class ErrorLog:
    """Logs errors by where they happened: the first three of each, then one in ``_ERROR_LOG_EVERY``
    (a camera failing at 30 Hz must not fill the journal)."""

    def __init__(self) -> None:
        self._seen: Counter[str] = Counter()

    def __call__(self, where: str, e: BaseException, traceback: bool = False) -> None:
        self._seen[where] += 1
        n = self._seen[where]
        if n <= 3 or n % _ERROR_LOG_EVERY == 0:
            log.warning("%s: %s (occurrence %d)", where, e, n, exc_info=traceback)


class OperatorReports:
    """The service's state as the operator is told it.

    Args:
        config: the service's settings (``output``'s rates, the keys named in advice).
        link: where STATUSTEXT and NAMED_VALUE_FLOAT go.
        fc: the flight controller's state (its clock steps, its ATTITUDE rate).
        counters: the service's counters (read, never written).
        latency: the capture-to-send latency (VO_LAT_MS).
        pending_texts: STATUSTEXTs other threads queue (the recorder's); sent in order with each report.
    """

    def __init__(
        self,
        config: ServiceConfig,
        link: Link,
        fc: FlightControllerState,
        counters: Counter[str],
        latency: LatencyTracker,
        pending_texts: deque[dict[str, object]],
    ) -> None:
        self.config, self.link, self.fc, self.counters, self.latency = config, link, fc, counters, latency
        self.pending_texts = pending_texts
        self.state = VisionState.STANDBY
        self._lock = threading.Lock()
        self._pending_states: list[tuple[VisionState, StateReason]] = []  # changes not yet told (rate limit)
        self._last_text_s = -math.inf
        self._next_health_s = -math.inf
        self._skipped_at_last_report = 0
        self._unpaired_history: deque[tuple[float, int, dict[str, int]]] = deque()  # (t, paired, causes)
        self._unpaired_told: str | None = None  # the cause told, until frames pair again

    def system_status(self) -> SystemStatus:
        """The HEARTBEAT's system status for the current state."""
        return _SYSTEM_STATUS[self.state]

    def set_state(self, state: VisionState, reason: StateReason) -> None:
        """A state change (any thread): logged now, told with the next report."""
        with self._lock:
            if state == self.state:
                return
            log.info("state %s -> %s%s", self.state, state, f" ({reason})" if reason else "")
            self.state = state
            self._pending_states.append((state, reason))

    def send_state_text(self, now: float, *, force: bool = False) -> None:
        """The state changes not yet told, merged into one STATUSTEXT: at most one per
        ``output.statustext_min_interval_s``, or now when ``force`` (at shutdown, so that the ground
        station learns the last state even when it came within the interval)."""
        with self._lock:
            text = None
            if self._pending_states and (
                force or now - self._last_text_s >= self.config.output.statustext_min_interval_s
            ):
                text = messages.statustext_merged(self._pending_states)
                self._pending_states, self._last_text_s = [], now
        if text is not None:
            self.link.send("STATUSTEXT", text)

    def warn(self, text: str) -> None:
        """A warning STATUSTEXT, sent now (it must fit the message's 50 characters)."""
        self.link.send("STATUSTEXT", messages.statustext_line(text, severity=messages.MAV_SEVERITY_WARNING))

    def report(self, now: float, est: PoseEstimate | None) -> None:
        """From the supervisor: notice when estimates stop coming (``est`` the last one), send the
        pending STATUSTEXTs (rate limited) and the health values."""
        counters = snapshot(self.counters)
        skipped = sum(v for k, v in counters.items() if k.startswith("skipped_attitude"))
        for step in self.fc.take_clock_steps():
            log.warning("flight controller clock stepped %+.3f s (%s); re-synchronised", step.step_s, step.evidence)
            self.warn(f"mavvo: FC clock stepped {step.step_s:+.2f} s; re-synced")
        self._tell_why_unpaired(now, counters)
        if est is not None and self.state != VisionState.FAILED and now - est.t_exposure_s > _NO_ESTIMATE_S:
            self.set_state(
                VisionState.FAILED,
                StateReason.NO_ATTITUDE if skipped > self._skipped_at_last_report else StateReason.NO_FRAMES,
            )
        self._skipped_at_last_report = skipped
        self.send_state_text(now)
        while self.pending_texts:  # from other threads (the recorder's): sent here, in order
            self.link.send("STATUSTEXT", self.pending_texts.popleft())
        if now >= self._next_health_s:
            period = 1.0 / self.config.output.health_rate_hz
            # On the period's grid, so the rate holds however coarse the supervisor's ticks are.
            self._next_health_s = self._next_health_s + period if now < self._next_health_s + period else now + period
            self._send_health(now, est)

    def _send_health(self, now: float, est: PoseEstimate | None) -> None:
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
        self.warn(f"mavvo: {short}")

    def log_health(self, health: dict[str, int], final: bool = False) -> None:
        """The counters that matter, one line in the log (``final``: at the end of the run)."""
        latency = self.latency.stats()
        lat = "" if latency is None else f"; {latency.advice()}"
        counts = ", ".join(f"{k} {health[k]}" for k in _HEALTH_LOG_KEYS if health.get(k))
        log.info("%s: state %s; %s%s", "final" if final else "health", self.state, counts or "nothing yet", lat)
