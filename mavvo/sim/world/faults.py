"""Faults the simulator injects, from a scenario or on demand.

Flight controller: ``link_silence`` (nothing sent), ``stall`` (nothing arrives, then everything sent
meanwhile at once: a buffered link), ``clock_step`` (the process stops: nothing sent or read, and its
boot clock stands still, so it runs the duration behind afterwards), ``reboot`` (down for the duration,
then the boot clock restarts at zero and streams stay off until requested again), ``nan_attitude``,
``stale_attitude`` (the last ATTITUDE repeated unchanged), ``corrupt_bytes`` (every message on the wire
has a byte flipped, so its checksum fails, and garbage bytes come between messages).
Camera: ``frames_missing`` (no frames), ``dark_frames`` (5% exposure), ``textureless_frames``
(a uniform grey image with sensor noise).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from mavvo.options import bounded

FaultKind = Literal[
    "link_silence",
    "stall",
    "clock_step",
    "reboot",
    "nan_attitude",
    "stale_attitude",
    "corrupt_bytes",
    "frames_missing",
    "dark_frames",
    "textureless_frames",
]


@dataclass(frozen=True)
class FaultSpec:
    """One fault over [start_s, start_s + duration_s) of simulated time."""

    kind: FaultKind = bounded("link_silence", "what goes wrong")
    start_s: float = bounded(0.0, "when, seconds from the start", ge=0)
    duration_s: float = bounded(1.0, "how long (a reboot: how long the flight controller is down)", gt=0)

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s


class FaultSchedule:
    """The faults of one run; ``inject`` adds one on demand. Thread-safe enough for one writer:
    the list is replaced, never mutated in place."""

    def __init__(self, faults: tuple[FaultSpec, ...] = ()) -> None:
        self._faults = tuple(faults)

    @property
    def faults(self) -> tuple[FaultSpec, ...]:
        return self._faults

    def active(self, kind: FaultKind, t_s: float) -> bool:
        return any(f.kind == kind and f.start_s <= t_s < f.end_s for f in self._faults)

    def reboots_ending(self, after_s: float, until_s: float) -> list[FaultSpec]:
        """Reboots whose down time ends in (after_s, until_s], in time order."""
        return sorted(
            (f for f in self._faults if f.kind == "reboot" and after_s < f.end_s <= until_s), key=lambda f: f.end_s
        )
