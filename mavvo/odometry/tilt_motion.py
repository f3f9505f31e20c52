"""What a multirotor's tilt says about its acceleration, for the filter to coast on while vision sees nothing.

A multirotor's thrust lies along its body's z axis. Holding its weight, the thrust per unit mass is
g / b_z and the horizontal acceleration

    a_h = -g b_h / b_z          (b: the body's z axis in the level frame, from roll and pitch)

so the flight controller's roll and pitch give the horizontal acceleration. What they leave out: rotor
drag (a few tenths of m/s^2 at 1 m/s on a small quad), the attitude's trim error (0.17 m/s^2 per degree)
and its noise, and the vertical acceleration's share of the thrust (a climb at 2 m/s^2 makes a_h 20%
larger than this says). Over the seconds of a short outage that is centimetres to decimetres, where a
constant velocity runs on past a vehicle that stops.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.frames import R_lvl_body, rot_z

__all__ = ["GRAVITY_M_S2", "TILT_RESIDUAL_M_S2", "VELOCITY_PULL_S", "TiltMotion", "tilt_acceleration_lvl_m_s2"]

GRAVITY_M_S2 = 9.80665
# What the tilt's acceleration misses, 1 sigma: rotor drag and the attitude's trim error (see above).
TILT_RESIDUAL_M_S2 = 0.3
# TiltMotion's pull toward vision's velocity: long against a braking (the filter's lag), short against
# what the tilt misses (0.3 m/s^2 for 1 s: 0.3 m/s).
VELOCITY_PULL_S = 1.0


def tilt_acceleration_lvl_m_s2(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """(3,) horizontal acceleration in the level frame (heading of the body; z 0), m/s^2."""
    b = R_lvl_body(roll_rad, pitch_rad)[:, 2]
    return np.array([-GRAVITY_M_S2 * b[0] / b[2], -GRAVITY_M_S2 * b[1] / b[2], 0.0])


class TiltMotion:
    """What the tilt says between frames: the mean acceleration over each step (the trapezoid of its two
    ends, NED) and the horizontal velocity where vision's filter lags: the acceleration integrated,
    pulled toward vision's velocity with the time constant VELOCITY_PULL_S (a complementary filter: the
    quick changes from the tilt, the level from vision). A constant-velocity filter runs ahead of a
    vehicle braking into a stop, which a coast from its velocity carries on (docs/odometry.md)."""

    def __init__(self) -> None:
        self._last_a_lvl: np.ndarray | None = None
        self._last_t_s: float | None = None
        self._dt_s = 0.0
        self.accel_ned_m_s2 = np.zeros(3)
        self.v_ne_m_s = np.zeros(2)

    def step(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        """A frame at ``t_s`` with this attitude (the heading turns the level frame into NED)."""
        self._dt_s = 0.0 if self._last_t_s is None else t_s - self._last_t_s
        a = tilt_acceleration_lvl_m_s2(roll_rad, pitch_rad)
        mean = a if self._last_a_lvl is None else 0.5 * (a + self._last_a_lvl)
        self._last_a_lvl, self._last_t_s = a, t_s
        self.accel_ned_m_s2 = rot_z(yaw_rad) @ mean
        self.v_ne_m_s = self.v_ne_m_s + self.accel_ned_m_s2[:2] * self._dt_s

    def pull(self, v_ned_m_s: np.ndarray) -> None:
        """Pull the velocity toward vision's (3,) over the last step."""
        self.v_ne_m_s = self.v_ne_m_s + (v_ned_m_s[:2] - self.v_ne_m_s) * min(self._dt_s / VELOCITY_PULL_S, 1.0)
