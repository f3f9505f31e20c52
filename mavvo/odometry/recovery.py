"""Where tracking goes on after vision saw nothing for a while, and the long-term error it costs.

- A short outage (at most ``coast_max_s``: a plain patch of floor under a low camera, a moment of blur):
  the filter has coasted on, its horizontal acceleration from the tilt
  (:mod:`mavvo.odometry.tilt_motion`) and its height from the range, and the next keyframe starts
  where it got to. Nothing steps, so there is no reset; the position's uncertainty is the velocity's
  at the loss times the outage plus what the tilt leaves out, (1/2) a t^2.
- A longer one re-initialises (a reset): at the flight controller's own position when it sends one,
  else the last good pose moved on by its velocity for at most ``dead_reckon_max_s``, then held.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mavvo.odometry.filter import PoseFilter, wrap_angle
from mavvo.odometry.options import OdometryOptions
from mavvo.odometry.tilt_motion import TILT_RESIDUAL_M_S2

__all__ = ["Drift", "GoodPose", "coast_sigma_m", "heading_now_rad", "reinit_anchor", "velocity_sigma_m_s"]


def velocity_sigma_m_s(flt: PoseFilter) -> float:
    """The filter's velocity uncertainty, 1 sigma per axis (m/s)."""
    return math.sqrt(max(float(np.trace(flt.velocity_covariance)) / 3.0, 0.0))


@dataclass(frozen=True)
class GoodPose:
    """The last frame whose pose was accepted (NED, m, m/s, rad): where tracking goes on from."""

    t_s: float
    p_ned_m: np.ndarray
    v_ned_m_s: np.ndarray
    v_sigma_m_s: float  # 1 sigma per axis of the filter's velocity then
    yaw_rad: float
    fc_yaw_rad: float

    @classmethod
    def of(cls, flt: PoseFilter, t_s: float, fc_yaw_rad: float) -> GoodPose:
        """The filter's state at ``t_s``, with the flight controller's yaw then."""
        return cls(t_s, flt.position_ned_m, flt.velocity_ned_m_s, velocity_sigma_m_s(flt), flt.yaw_rad, fc_yaw_rad)


@dataclass
class Drift:
    """The long-term error since the origin (see :mod:`mavvo.odometry.pipeline`)."""

    anchor_var_m2: float = 0.0  # summed variances of the anchors
    flown_m: float = 0.0  # distance flown since the last anchor
    anchor_p_ned_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    last_p_ned_m: np.ndarray | None = None

    def sigma_m(self, p_ned_m: np.ndarray, per_m: float, heading_rad: float) -> float:
        away = float(np.linalg.norm(p_ned_m[:2] - self.anchor_p_ned_m[:2]))
        return math.sqrt(self.anchor_var_m2 + (per_m * self.flown_m) ** 2 + (heading_rad * away) ** 2)


def coast_sigma_m(good: GoodPose, t_s: float) -> float:
    """1 sigma per horizontal axis of a position coasted from ``good`` to ``t_s``: sigma_v t + a t^2 / 2."""
    dt = max(t_s - good.t_s, 0.0)
    return good.v_sigma_m_s * dt + 0.5 * TILT_RESIDUAL_M_S2 * dt**2


def heading_now_rad(good: GoodPose, fc_yaw_rad: float) -> float:
    """Vision's heading at ``good`` moved on by the flight controller's turn since (its yaw's drift is
    slow; the filter's yaw rate, coasted, is not)."""
    if math.isfinite(fc_yaw_rad) and math.isfinite(good.fc_yaw_rad):
        return wrap_angle(good.yaw_rad + wrap_angle(fc_yaw_rad - good.fc_yaw_rad))
    return good.yaw_rad


def reinit_anchor(
    good: GoodPose, t_s: float, fc_p_ned_m: np.ndarray | None, v_sigma_m_s: float, options: OdometryOptions
) -> tuple[np.ndarray, float, str]:
    """Where re-initialised tracking starts, its 1 sigma and what it came from: the flight controller's
    position when it sends one (the stream's sigma: no step for its EKF), else ``good`` moved on by its
    velocity for at most ``dead_reckon_max_s``, then held (the velocity's error, ``v_sigma_m_s``, times
    the time, then ``max_speed_m_s`` times the rest)."""
    if fc_p_ned_m is not None:
        return fc_p_ned_m.copy(), options.position_sigma_m, "the flight controller's position"
    dt = max(t_s - good.t_s, 0.0)
    reckon = min(dt, options.dead_reckon_max_s)
    p = good.p_ned_m + good.v_ned_m_s * reckon
    sigma = options.position_sigma_m + v_sigma_m_s * reckon + options.max_speed_m_s * (dt - reckon)
    how = f"the last good pose of {dt:.2f} s ago" + (
        f", moved on by its velocity for {reckon:.2f} s" if reckon > 0 else ""
    )
    return p, sigma, how
