"""What a multirotor's tilt says about its acceleration, for the filter to coast on while vision sees nothing.

A multirotor's thrust lies along its body's z axis. Holding its weight, the thrust per unit mass is
g / b_z and the horizontal acceleration

    a_h = -g b_h / b_z          (b: the body's z axis in the level frame, from roll and pitch)

so the flight controller's roll and pitch give the horizontal acceleration. What they leave out: rotor
drag (a few tenths of m/s^2 at 1 m/s on a small quad), the attitude's trim error (0.17 m/s^2 per degree)
and its noise, and the vertical acceleration's share of the thrust (a climb at 2 m/s^2 makes a_h 20%
larger than this says). Over the seconds of a short outage that is centimetres to decimetres, where a
constant velocity runs on past a vehicle that stops.

The trim error is a bias, the same in the body's level frame for minutes, and a coast integrates it
twice (0.5 deg: 0.09 m/s^2, 0.17 m over 2 s). While vision tracks, :class:`TiltMotion` estimates it
with the horizontal velocity (docs/odometry.md, Coasting).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["GRAVITY_M_S2", "TILT_RESIDUAL_M_S2", "TiltMotion", "tilt_acceleration_lvl_m_s2"]

GRAVITY_M_S2 = 9.80665
# What the tilt's acceleration misses, 1 sigma: rotor drag and the attitude's trim error (see above).
TILT_RESIDUAL_M_S2 = 0.3
# TiltMotion's model. Its acceleration's error as white noise, (m/s^2)^2 per Hz: the velocity may wander
# 0.03 m/s in a second. Larger lets vision's position noise into the velocity a coast starts from;
# smaller follows the simulator's exact tilt closer but not a real quad's rotor drag, which is not white
# (what each gave: docs/odometry.md, States, "A biased attitude").
ACCEL_PSD_M2_S3 = 1e-3
# The bias's random walk, (m/s^2)^2 per second (0.003 m/s^2 in a second: a trim that changes over
# minutes), and its sigma before vision has measured it (1 deg of trim).
BIAS_PSD_M2_S5 = 1e-5
BIAS_SIGMA0_M_S2 = 0.17
VELOCITY_SIGMA0_M_S = 1.0
# A position further than this (squared Mahalanobis, 2 dof: 1 in 10^6 by chance) from the prediction
# is a new keyframe's jump, not motion: the position starts again there, velocity and bias kept.
_GATE_CHI2 = 27.6


def tilt_acceleration_lvl_m_s2(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """(3,) horizontal acceleration in the level frame (heading of the body; z 0), m/s^2: with the
    body's z axis b = rot_y(pitch) rot_x(roll) e_z = (cos r sin p, -sin r, cos r cos p),
    -g b_h / b_z = (-g tan p, g tan r / cos p)."""
    return np.array([*_tilt_acceleration_xy(roll_rad, pitch_rad), 0.0])


def _tilt_acceleration_xy(roll_rad: float, pitch_rad: float) -> tuple[float, float]:
    return -GRAVITY_M_S2 * math.tan(pitch_rad), GRAVITY_M_S2 * math.tan(roll_rad) / math.cos(pitch_rad)


class TiltMotion:
    """The horizontal motion the tilt drives, measured by vision's positions: a Kalman filter of each
    NED axis's

        x = [p, v, b]    (position m, velocity m/s, the tilt's acceleration bias m/s^2)

    driven by the tilt's acceleration a (the trapezoid of a step's two ends, turned into NED):

        p' = p + v dt + (a - b) dt^2 / 2,   v' = v + (a - b) dt,   b' = b

    The bias is the flight controller's trim error, fixed in the body's level frame: it turns with the
    heading. Both axes share one covariance (a position's covariance is taken as its mean variance on
    both), and a turn of the heading turns the bias's estimate but not the covariance: an approximation
    (the cross terms between the bias and the position or velocity would turn too, mixing the axes),
    exact while the heading holds.
    Unlike vision's constant-velocity filter it does not lag a braking, so a coast starts from its
    velocity; and a coast integrates the acceleration less the bias (:attr:`accel_ned_m_s2`).
    Scalar arithmetic: it runs on every frame, where numpy's per-call cost would be most of it.
    """

    def __init__(self) -> None:
        self._last_a_lvl: tuple[float, float] | None = None
        self._last_t_s: float | None = None
        self._yaw_rad = 0.0  # the heading the bias was last turned to
        self.accel_ned_m_s2 = np.zeros(3)  # the last step's mean acceleration, bias removed
        self._p = [0.0, 0.0]
        self._v = [0.0, 0.0]
        self._b = [0.0, 0.0]  # NED
        # P = [[pp, pv, pb], [pv, vv, vb], [pb, vb, bb]], one axis's
        self._pp, self._pv, self._pb = 0.0, 0.0, 0.0
        self._vv, self._vb, self._bb = VELOCITY_SIGMA0_M_S**2, 0.0, BIAS_SIGMA0_M_S2**2
        self._lost = True  # the next position starts the position again

    @property
    def v_ne_m_s(self) -> np.ndarray:
        """(2,) horizontal velocity, NED, m/s."""
        return np.array(self._v)

    @property
    def bias_lvl_m_s2(self) -> np.ndarray:
        """(2,) the tilt's acceleration bias in the level frame (forward, right), m/s^2."""
        c, s = math.cos(self._yaw_rad), math.sin(self._yaw_rad)
        bn, be = self._b
        return np.array([c * bn + s * be, -s * bn + c * be])

    def step(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        """A frame at ``t_s`` with this attitude (the heading turns the level frame into NED)."""
        dt = 0.0 if self._last_t_s is None else t_s - self._last_t_s
        a = _tilt_acceleration_xy(roll_rad, pitch_rad)
        last = a if self._last_a_lvl is None else self._last_a_lvl
        ax, ay = 0.5 * (a[0] + last[0]), 0.5 * (a[1] + last[1])  # the step's mean: the trapezoid of its ends
        self._last_a_lvl, self._last_t_s = a, t_s
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        turn = yaw_rad - self._yaw_rad
        if turn:
            ct, st = math.cos(turn), math.sin(turn)
            bn, be = self._b
            self._b = [ct * bn - st * be, st * bn + ct * be]
            self._yaw_rad = yaw_rad
        an, ae = c * ax - s * ay - self._b[0], s * ax + c * ay - self._b[1]
        self.accel_ned_m_s2 = np.array([an, ae, 0.0])
        if dt <= 0.0:
            return
        h = 0.5 * dt * dt
        p, v = self._p, self._v
        self._p = [p[0] + v[0] * dt + an * h, p[1] + v[1] * dt + ae * h]
        self._v = [v[0] + an * dt, v[1] + ae * dt]
        # P = F P F' + Q, F = [[1, dt, -dt^2/2], [0, 1, -dt], [0, 0, 1]]; Q: white acceleration noise
        # q on (p, v) ([[dt^3/3, dt^2/2], [dt^2/2, dt]] q) and the bias's random walk.
        pp, pv, pb, vv, vb, bb = self._pp, self._pv, self._pb, self._vv, self._vb, self._bb
        a0, a1, a2 = pp + dt * pv - h * pb, pv + dt * vv - h * vb, pb + dt * vb - h * bb  # row 0 of F P
        b1, b2 = vv - dt * vb, vb - dt * bb  # row 1 of F P from its diagonal on
        q = ACCEL_PSD_M2_S3
        self._pp = a0 + dt * a1 - h * a2 + q * dt**3 / 3.0
        self._pv = a1 - dt * a2 + q * h
        self._pb = a2
        self._vv = b1 - dt * b2 + q * dt
        self._vb = b2
        self._bb = bb + BIAS_PSD_M2_S5 * dt

    def lost(self) -> None:
        """Vision's positions stopped (or will jump): the next one starts the position again."""
        self._lost = True

    def measured(self, p_ne_m: np.ndarray, cov_ne_m2: np.ndarray) -> None:
        """Vision's horizontal position at the last step ((2,) NED, m) and its covariance ((2,2), m^2)."""
        r = 0.5 * float(cov_ne_m2[0, 0] + cov_ne_m2[1, 1])
        zn, ze = float(p_ne_m[0]), float(p_ne_m[1])
        yn, ye = zn - self._p[0], ze - self._p[1]  # innovation y = z - H x, H = [1 0 0]
        S = self._pp + r  # S = H P H' + R
        if self._lost or (yn * yn + ye * ye) / S > _GATE_CHI2:
            self._lost = False
            self._p = [zn, ze]
            self._pp, self._pv, self._pb = r, 0.0, 0.0
            return
        k0, k1, k2 = self._pp / S, self._pv / S, self._pb / S  # K = P H' S^-1
        self._p = [self._p[0] + k0 * yn, self._p[1] + k0 * ye]  # x = x + K y
        self._v = [self._v[0] + k1 * yn, self._v[1] + k1 * ye]
        self._b = [self._b[0] + k2 * yn, self._b[1] + k2 * ye]
        pp, pv, pb = self._pp, self._pv, self._pb  # P = P - K H P (row 0 of P: pp, pv, pb)
        self._pp, self._pv, self._pb = pp - k0 * pp, pv - k0 * pv, pb - k0 * pb
        self._vv, self._vb, self._bb = self._vv - k1 * pv, self._vb - k1 * pb, self._bb - k2 * pb
