"""A frame and the flight controller's state at its exposure, made into what the odometry takes; and
the wait for a settled yaw before the first estimate (north is taken from it)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from mavvo.service.timing import Pairing
from mavvo.types import Frame, PairedFrame

__all__ = ["HeadingWait", "paired_frame"]

log = logging.getLogger(__name__)


def paired_frame(frame: Frame, p: Pairing) -> PairedFrame:
    """``frame`` with the state ``p`` paired to it (``p.status`` must be "paired"). The flight
    controller's yaw steers the heading only while it is settled (not converging after a boot or
    reboot); meanwhile vision's heading carries on alone: NaN."""
    return PairedFrame(
        frame.image,
        frame.t_exposure_s,
        frame.seq,
        p.roll_rad,
        p.pitch_rad,
        p.yaw_rad if p.yaw_settled else math.nan,
        p.range_m,
        p.height_m,
        None if p.fc_position_ned_m is None else np.asarray(p.fc_position_ned_m),
        p.attitude_gap_s,
        p.interpolation_sigma_rad,
        p.fc_armed,
    )


class HeadingWait:
    """The first estimate waits until the flight controller's yaw has settled, at most ``max_s``
    (0: no wait) from the first paired frame; then ``warn`` tells the operator north may be off."""

    def __init__(self, max_s: float, warn: Callable[[str], None]) -> None:
        self.max_s, self.warn = max_s, warn
        self._over = max_s <= 0
        self._first_s: float | None = None  # exposure time of the first paired frame

    def ready(self, yaw_settled: bool, t_s: float) -> bool:
        """Whether a frame exposed at ``t_s`` may make an estimate."""
        if self._over:
            return True
        if self._first_s is None:
            self._first_s = t_s
        if yaw_settled:
            self._over = True
        elif t_s - self._first_s >= self.max_s:
            self._over = True
            log.warning(
                "the flight controller's yaw has not settled after %.0f s: starting with it; north may be off",
                self.max_s,
            )
            self.warn("mavvo: FC yaw unsettled, north may be off")
        return self._over
