"""Estimates to the flight controller: VISION_POSITION_ESTIMATE at most ``output.max_rate_hz``, with
VISION_SPEED_ESTIMATE and ODOMETRY where asked, nothing while vision has failed (ODOMETRY once says
so), every message bound to arrive while it is still news (``output.max_age_s``)."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable

from mavvo.service import messages
from mavvo.service.latency import LatencyTracker
from mavvo.service.link import Link
from mavvo.service.operator import OperatorReports
from mavvo.service.settings import OutputOptions
from mavvo.service.state_file import ResetCounterFile
from mavvo.types import PoseEstimate

__all__ = ["Publisher"]


class Publisher:
    """Sends each estimate the worker makes (worker thread only).

    Args:
        output: ``output`` settings.
        link: the MAVLink connection.
        reports: told every estimate's state.
        counters: the service's counters (estimates_sent, not_sent_*, resets).
        latency: each sent estimate's capture-to-send latency is added, from ``latency_s(t_exposure_s)``.
        reset_file: where each new ``reset_counter`` is kept.
        on_estimate: called with every estimate (replay's quality timeline); it must be quick.
    """

    def __init__(
        self,
        output: OutputOptions,
        link: Link,
        reports: OperatorReports,
        counters: Counter[str],
        latency: LatencyTracker,
        latency_s: Callable[[float], float],
        reset_file: ResetCounterFile,
        on_estimate: Callable[[PoseEstimate], None] | None = None,
    ) -> None:
        self.output, self.link, self.reports, self.counters = output, link, reports, counters
        self.latency, self.latency_s, self.reset_file, self.on_estimate = latency, latency_s, reset_file, on_estimate
        self.last_estimate: PoseEstimate | None = None
        self._last_sent_t_s = -math.inf
        self._reset_counter: int | None = None
        self._odometry_ok = False  # the last ODOMETRY sent had a quality >= 1

    def publish(self, est: PoseEstimate) -> None:
        self.last_estimate = est
        if self.on_estimate is not None:
            self.on_estimate(est)
        self.reports.set_state(est.diagnostics.state, est.diagnostics.reason)
        if self._reset_counter is not None and est.reset_counter != self._reset_counter:
            self.counters["resets"] += 1
            self.reset_file.save(est.reset_counter)
        self._reset_counter = est.reset_counter
        out = self.output
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
            self.latency.add(self.latency_s(est.t_exposure_s))
            if out.speed_estimate:
                self.link.send("VISION_SPEED_ESTIMATE", messages.vision_speed_estimate(est), send_by_s=send_by_s)
            if out.odometry:
                self.link.send("ODOMETRY", self._odometry(est), send_by_s=send_by_s)
                self._odometry_ok = True
            self.counters["estimates_sent"] += 1

    def _odometry(self, est: PoseEstimate) -> dict[str, object]:
        out = self.output
        return messages.odometry(est, messages.autopilot_of(self.link.autopilot, out.autopilot), out.estimator_type)
