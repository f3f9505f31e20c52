"""Vision's heading against the flight controller's yaw: how uncertain the chain of keyframes' relative
yaws has become, and when and how hard that yaw pulls it (``heading_source``; docs/odometry.md, Heading
over a faint floor).

    P += var(relative yaw)                    per keyframe committed (relative_yaw_var)
    K  = max(dt / heading_correction_time_s, P / (P + fc_yaw_sigma^2))
    yaw += K (yaw_fc - yaw);  P *= 1 - K      where the flight controller's yaw steers (steers, commit)
"""

from __future__ import annotations

import math

import numpy as np

from mavvo.estimation.relpose_types import RelposeFailure, UprightRelpose
from mavvo.geometry.refine import upright_yaw_variance
from mavvo.odometry.filter import wrap_angle
from mavvo.odometry.options import OdometryOptions

__all__ = ["HeadingChain", "relative_yaw_var"]

# The relative yaw's error over what its inliers' residuals alone explain (roll/pitch errors and outliers
# left in add to it): on indoor_hops' frames the median |error| / sigma was 1.4-2.2 (1 for a Gaussian
# is 0.67), so its 1 sigma is about 3 sigmas of the residuals.
_YAW_SIGMA_INFLATION = 3.0


def relative_yaw_var(rp: UprightRelpose, f1_lvl: np.ndarray, f2_lvl: np.ndarray) -> float:
    """Variance (rad^2) of the relative yaw ``rp`` measured from its inlier bearings ``f1_lvl``, ``f2_lvl``
    (N,3, corrected level frames), its residuals' RMS times _YAW_SIGMA_INFLATION as the bearing noise:
    with the translation's direction free where there is one (upright_yaw_variance); without one (a
    pure rotation), a turn about the vertical moves each bearing by its horizontal extent, so
    sigma = noise / sqrt(sum(fx^2 + fy^2))."""
    sigma = _YAW_SIGMA_INFLATION * rp.residual_rms_rad
    if not math.isfinite(sigma) or len(f2_lvl) == 0:
        return 0.0
    if rp.reason != RelposeFailure.PURE_ROTATION:
        var = upright_yaw_variance(rp.yaw_rad, rp.t_2_1, f1_lvl, f2_lvl, sigma)
        if math.isfinite(var):
            return var
    extent_sq = float(np.sum(f2_lvl[:, 0] ** 2 + f2_lvl[:, 1] ** 2))
    return sigma**2 / extent_sq if extent_sq > 0 else 0.0


class HeadingChain:
    """The uncertainty P (rad^2) of vision's chained heading, and the flight controller's pull on it."""

    def __init__(self, opt: OdometryOptions) -> None:
        self.source = opt.heading_source
        self.tau_s = opt.heading_correction_time_s
        self.fc_var = math.radians(opt.fc_yaw_sigma_deg) ** 2
        self.gate_rad = math.radians(opt.heading_gate_deg)
        self.gate_sigmas = opt.heading_gate_sigmas
        self.var = 0.0

    def restart(self, fc_yaw_rad: float) -> None:
        """A new chain, its north from the flight controller's yaw (its uncertainty) or none (NaN: 0)."""
        self.var = self.fc_var if math.isfinite(fc_yaw_rad) else 0.0

    def steers(self, fc_armed: bool | None, innovation_rad: float) -> bool:
        """Whether the flight controller's yaw, ``innovation_rad`` from vision's heading, may pull it now."""
        if self.source == "ground":
            # Disarmed, or not known (a log without HEARTBEAT); armed, only a compass that agrees, within
            # the fixed gate or the two headings' joint uncertainty (vision's grows while unheard).
            if fc_armed is not True:
                return True
            gate = max(self.gate_rad, self.gate_sigmas * math.sqrt(self.var + self.fc_var))
            return abs(innovation_rad) <= gate
        return self.source == "follow"

    def commit(
        self, yaw_rad: float, yaw_var_rad2: float, fc_yaw_rad: float, fc_armed: bool | None, dt_s: float
    ) -> float:
        """A new keyframe at vision's ``yaw_rad`` whose relative yaw had ``yaw_var_rad2``, ``dt_s`` after the
        last: the flight controller's pull on its heading, rad (0: none)."""
        self.var += yaw_var_rad2
        innovation = wrap_angle(fc_yaw_rad - yaw_rad)
        if self.tau_s <= 0 or not math.isfinite(fc_yaw_rad) or not self.steers(fc_armed, innovation):
            return 0.0
        # At least the time constant's share; more where vision's chained heading is less certain than
        # the flight controller's yaw (a Kalman gain: high over plain floors and for a forward camera).
        gain = max(min(1.0, dt_s / self.tau_s), self.var / (self.var + self.fc_var))
        self.var *= 1.0 - gain
        return gain * innovation
