"""What a run of the service reports outward: the counts a lockstep driver waits on, and the summary
of a finished run."""

from __future__ import annotations

import math
from dataclasses import dataclass

from mavvo.service.latency import LatencyStats
from mavvo.types import VisionState

__all__ = ["DaemonSummary", "LockstepProgress"]


@dataclass(frozen=True)
class LockstepProgress:
    """How far the daemon has got, for a driver that runs it in lockstep (simulation, replay).

    Every count only grows. A driver hands the daemon one input, then waits with
    :meth:`mavvo.service.daemon.Daemon.wait_progress` until the matching count has moved, so the daemon's threads see
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
        link_tick_s: the host clock at the last :meth:`mavvo.service.daemon.Daemon.tick` the link has finished.
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
    """How a run went: every counter, the last state, the capture-to-send latency, why the service
    could not go on (``failure``; empty after a clean stop), and the odometry's CPU time."""

    counters: dict[str, int]
    state: VisionState
    latency: LatencyStats | None
    failure: str = ""
    odometry_cpu_s: float = 0.0  # CPU time of the worker thread in the odometry (tracking, pose, filter)

    @property
    def odometry_cpu_ms_per_frame(self) -> float | None:
        """The odometry's CPU time per frame it saw (paired, or only tracked), ms; None before a frame."""
        n = self.counters.get("frames", 0)
        return 1e3 * self.odometry_cpu_s / n if n else None

    @property
    def latency_ms(self) -> float | None:
        """The median capture-to-send latency."""
        return None if self.latency is None else self.latency.p50_ms
