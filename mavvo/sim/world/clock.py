"""Clocks for the simulator: lockstep (simulated time that advances only when told) and real time.

Both count seconds from the start of the simulation. The simulated flight controller and camera read
only this clock, and the daemon is given the same clock as its host clock, so a lockstep run is faster
than real time and repeats exactly.
"""

from __future__ import annotations

import threading
import time


class LockstepClock:
    """Simulated time; ``advance_to`` moves it forward, ``sleep_until`` moves it forward at once."""

    realtime = False

    def __init__(self) -> None:
        self._t_s = 0.0
        self._lock = threading.Lock()

    def now_s(self) -> float:
        return self._t_s

    def advance_to(self, t_s: float) -> None:
        with self._lock:
            if t_s > self._t_s:
                self._t_s = float(t_s)

    def sleep_until(self, t_s: float) -> None:
        self.advance_to(t_s)


class RealClock:
    """Host monotonic time since construction; ``sleep_until`` really sleeps."""

    realtime = True

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now_s(self) -> float:
        return time.monotonic() - self._t0

    def advance_to(self, t_s: float) -> None:
        """Real time advances by itself; nothing to do."""

    def sleep_until(self, t_s: float) -> None:
        dt = t_s - self.now_s()
        if dt > 0:
            time.sleep(dt)


Clock = LockstepClock | RealClock
