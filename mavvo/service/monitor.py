"""What the service tells the ground station, gathered for ``mavvo monitor`` (pure: messages in, a
snapshot and its text out; the command owns the connection and the screen).

It reads what mavvo sends (component 197): HEARTBEAT ``system_status``, the NAMED_VALUE_FLOAT health
values (``VO_STATE``: :data:`mavvo.service.messages.STATE_CODES`, ``VO_QUAL``, ``VO_INLIER``,
``VO_LAT_MS``, ``VO_DRIFT``), STATUSTEXT, and the VISION_POSITION_ESTIMATEs themselves (their rate and
``reset_counter``); and from the flight controller, where it is forwarded, EKF_STATUS_REPORT
(ArduPilot) or ESTIMATOR_STATUS (PX4).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from mavvo.service.link import COMPONENT_ID
from mavvo.service.messages import STATE_CODES

__all__ = ["Monitor", "MonitorSnapshot", "TimelinePoint", "render"]

_STATE_OF_CODE = {code: state.value for state, code in STATE_CODES.items()}
_STATUS_NAMES = {3: "standby", 4: "active", 5: "critical", 6: "emergency"}
_TEXTS_KEPT = 6
_RATE_WINDOW_S = 2.0
_SILENT_AFTER_S = 3.0


@dataclass(frozen=True)
class TimelinePoint:
    """Health values at one moment (monitor time, seconds): for the plot."""

    t_s: float
    state_code: float
    quality: float
    inliers: float
    latency_ms: float
    drift_m: float


@dataclass(frozen=True)
class MonitorSnapshot:
    """The monitor's view at ``t_s`` (monitor time, seconds). NaN or None: not heard yet."""

    t_s: float
    heard: bool
    silent_s: float
    state: str | None
    system_status: str | None
    quality: float
    inliers: float
    latency_ms: float
    drift_m: float
    estimates_per_s: float
    resets: int
    texts: tuple[tuple[float, str], ...]
    ekf: str | None


@dataclass
class Monitor:
    """Feed it every message with :meth:`add`; read it with :meth:`snapshot`."""

    values: dict[str, float] = field(default_factory=dict)
    timeline: list[TimelinePoint] = field(default_factory=list)
    _system_status: str | None = None
    _last_heard_s: float = -math.inf
    _estimates: deque[float] = field(default_factory=deque)
    _reset_counter: int | None = None
    _resets: int = 0
    _texts: deque[tuple[float, str]] = field(default_factory=lambda: deque(maxlen=_TEXTS_KEPT))
    _ekf: str | None = None

    def add(self, msg: Any, t_s: float) -> None:
        """One message (pymavlink), received at monitor time ``t_s``."""
        kind = msg.get_type()
        if kind == "EKF_STATUS_REPORT":
            self._ekf = f"ArduPilot EKF flags 0x{msg.flags:04x}, variances vel {msg.velocity_variance:.2f} pos {msg.pos_horiz_variance:.2f}"
            return
        if kind == "ESTIMATOR_STATUS":
            self._ekf = f"PX4 estimator flags 0x{msg.flags:04x}, test ratios vel {msg.vel_ratio:.2f} pos {msg.pos_horiz_ratio:.2f}"
            return
        if msg.get_srcComponent() != COMPONENT_ID:
            return
        self._last_heard_s = t_s
        if kind == "HEARTBEAT":
            self._system_status = _STATUS_NAMES.get(msg.system_status, str(msg.system_status))
        elif kind == "NAMED_VALUE_FLOAT":
            name = msg.name.decode() if isinstance(msg.name, bytes) else msg.name
            self.values[name.rstrip("\x00")] = float(msg.value)
            if name.startswith("VO_DRIFT"):  # the last of each second's values: a point of the timeline
                v = self.values
                self.timeline.append(
                    TimelinePoint(
                        t_s,
                        v.get("VO_STATE", math.nan),
                        v.get("VO_QUAL", math.nan),
                        v.get("VO_INLIER", math.nan),
                        v.get("VO_LAT_MS", math.nan),
                        v.get("VO_DRIFT", math.nan),
                    )
                )
        elif kind == "STATUSTEXT":
            text = msg.text.decode(errors="replace") if isinstance(msg.text, bytes) else msg.text
            self._texts.append((t_s, text.rstrip("\x00")))
        elif kind == "VISION_POSITION_ESTIMATE":
            self._estimates.append(t_s)
            if self._reset_counter is not None and msg.reset_counter != self._reset_counter:
                self._resets += 1
            self._reset_counter = msg.reset_counter

    def snapshot(self, t_s: float) -> MonitorSnapshot:
        while self._estimates and self._estimates[0] < t_s - _RATE_WINDOW_S:
            self._estimates.popleft()
        v = self.values
        code = v.get("VO_STATE")
        return MonitorSnapshot(
            t_s,
            math.isfinite(self._last_heard_s),
            t_s - self._last_heard_s,
            None if code is None else _STATE_OF_CODE.get(int(code), f"code {code:g}"),
            self._system_status,
            v.get("VO_QUAL", math.nan),
            v.get("VO_INLIER", math.nan),
            v.get("VO_LAT_MS", math.nan),
            v.get("VO_DRIFT", math.nan),
            len(self._estimates) / _RATE_WINDOW_S,
            self._resets,
            tuple(self._texts),
            self._ekf,
        )


def _num(x: float, fmt: str) -> str:
    return "-" if not math.isfinite(x) else format(x, fmt)


def render(s: MonitorSnapshot, source: str) -> str:
    """The snapshot as a screen of text (no colours: it also goes to logs)."""
    if not s.heard:
        return (
            f"mavvo monitor on {source}: nothing heard from mavvo (component {COMPONENT_ID}) yet after {s.t_s:.0f} s\n"
        )
    silent = f"   SILENT for {s.silent_s:.0f} s" if s.silent_s > _SILENT_AFTER_S else ""
    lines = [
        f"mavvo monitor on {source}   t {s.t_s:.0f} s{silent}",
        f"  state        {s.state or '-'}   (HEARTBEAT {s.system_status or '-'})",
        f"  quality      {_num(s.quality, '.0f')}   inliers {_num(s.inliers, '.0f')}",
        f"  estimates    {s.estimates_per_s:.1f} /s   resets {s.resets}",
        f"  latency      {_num(s.latency_ms, '.0f')} ms   drift {_num(s.drift_m, '.2f')} m (1 sigma since the origin)",
        f"  flight controller  {s.ekf or '(EKF status not forwarded)'}",
        "  messages:",
    ] + [f"    {t:6.1f} s  {text}" for t, text in s.texts]
    return "\n".join(lines) + "\n"
