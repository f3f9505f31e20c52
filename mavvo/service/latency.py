"""Capture-to-send latency: measured per estimate, summarised, and turned into each autopilot's delay
parameter.

Per estimate: from the exposure to the moment its message is handed to the link, on the host clock.
On a lockstep (simulated) clock the host clock stands still while the worker computes, so there it is
the time the frame reached the service on the simulated clock (exposure plus the simulated camera's
readout latency) plus the real processing time. The link's transfer time is added to the advice:
on a serial line the bytes of one VISION_POSITION_ESTIMATE over the baud rate (10 bits a byte).

ArduPilot re-times vision samples with the smallest lag it sees (its jitter correction), so the
advice for ``VISO_DELAY_MS`` is the low end (the minimum); PX4 uses ``EKF2_EV_DELAY`` as the delay of
every sample, so its advice is the median.
"""

from __future__ import annotations

import statistics
import threading
from collections import deque
from dataclasses import dataclass

__all__ = ["LatencyStats", "LatencyTracker", "VPE_FRAME_BYTES"]

# One VISION_POSITION_ESTIMATE on the wire: MAVLink 2 header 10, payload 116, checksum 2 (13 more signed).
VPE_FRAME_BYTES = 128
_WINDOW = 200


@dataclass(frozen=True)
class LatencyStats:
    """Capture-to-send over the last estimates, milliseconds, and the advice for each autopilot."""

    min_ms: float
    p50_ms: float
    p95_ms: float
    transfer_ms: float  # the link's share: bytes over baud on a serial line, 0 on a socket
    samples: int

    @property
    def ardupilot_delay_ms(self) -> int:
        """VISO_DELAY_MS: the low end, as ArduPilot re-times with the minimum lag, plus transfer."""
        return round(self.min_ms + self.transfer_ms)

    @property
    def px4_delay_ms(self) -> int:
        """EKF2_EV_DELAY: the median plus transfer."""
        return round(self.p50_ms + self.transfer_ms)

    def advice(self) -> str:
        return (
            f"capture-to-send min {self.min_ms:.0f} / p50 {self.p50_ms:.0f} / p95 {self.p95_ms:.0f} ms"
            + (f" + {self.transfer_ms:.1f} ms on the wire" if self.transfer_ms > 0 else "")
            + f": set VISO_DELAY_MS={self.ardupilot_delay_ms} (ArduPilot) or EKF2_EV_DELAY={self.px4_delay_ms} (PX4)"
        )


class LatencyTracker:
    """The last 200 latencies (thread-safe: the worker adds, the supervisor reads)."""

    def __init__(self, baud: int | None) -> None:
        self.transfer_ms = VPE_FRAME_BYTES * 10 / baud * 1e3 if baud else 0.0
        self._values_ms: deque[float] = deque(maxlen=_WINDOW)
        self._lock = threading.Lock()

    def add(self, latency_s: float) -> None:
        with self._lock:
            self._values_ms.append(latency_s * 1e3)

    def stats(self) -> LatencyStats | None:
        with self._lock:
            values = sorted(self._values_ms)
        if not values:
            return None
        p95 = values[min(len(values) - 1, int(round(0.95 * (len(values) - 1))))]
        return LatencyStats(values[0], statistics.median(values), p95, self.transfer_ms, len(values))
