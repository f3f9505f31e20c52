"""The simulated flight controller's position estimator: what an autopilot's EKF does with vision.

A small stand-in for ArduPilot's EKF3 with external navigation as its only horizontal source, close
enough to judge what mavvo sends the way the vehicle would:

- between vision samples it dead-reckons on the true velocity plus an IMU velocity error that walks
  randomly (``imu_drift_m_s_per_sqrt_s``), plus the correction it has learnt from vision;
- it fuses each VISION_POSITION_ESTIMATE as it comes, without alignment, with a fixed position gain
  and a small velocity gain (a second-order complementary filter: it follows vision within a few
  samples and learns the IMU's velocity error);
- the first vision sample, and every one whose ``reset_counter`` differs from the last, moves the
  estimate to the sent position at once, as EKF3 does on a reset: a stale pose sent with a new counter
  becomes a step the vehicle feels (recorded in :attr:`SimEstimator.steps`);
- vision is unhealthy 300 ms after the last sample (ArduPilot's timeout); the estimate dead-reckons on;
- a reboot loses the position (:meth:`SimEstimator.reboot`): none is reported until vision gives one;
- its yaw starts ``yaw_initial_error_deg`` off at boot and settles exponentially
  (``yaw_settle_time_s``), as an EKF's does while its yaw converges; once armed, it follows a disturbed
  compass as real ones do: an offset from the motors' current, a jump at the in-flight yaw alignment,
  a slow wander (all zero by default).

Horizontal only (x, y); height comes from the barometer. Positions are NED in the truth's frame: the
estimator starts at the truth's position at boot, as an EKF started at its origin would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mavvo.options import bounded

__all__ = ["EstimatorSpec", "SimEstimator", "Step"]

_VISION_TIMEOUT_S = 0.3  # ArduPilot calls external navigation unhealthy after this gap
_MOTOR_RAMP_S = 2.0  # from arming to the motors' full current: the compass offset ramps in over it


@dataclass(frozen=True)
class EstimatorSpec:
    """The simulated EKF (a scenario's ``flight_controller.estimator`` keys)."""

    imu_drift_m_s_per_sqrt_s: float = bounded(
        0.05, "random walk of the dead-reckoned velocity's error, m/s per sqrt(s)", ge=0, le=10
    )
    position_gain: float = bounded(0.3, "fraction of a vision sample's position innovation taken at once", gt=0, le=1)
    velocity_gain_per_s: float = bounded(
        1.0, "velocity correction learnt per metre of innovation and second", ge=0, le=100
    )
    yaw_initial_error_deg: float = bounded(
        -10.0, "the EKF's yaw error at boot (what it reports in ATTITUDE)", ge=-180, le=180
    )
    yaw_settle_time_s: float = bounded(5.0, "time constant with which that yaw error decays", gt=0, le=600)
    compass_motor_deg: float = bounded(
        0.0,
        "once armed, the motors' current turns the compass, and the yaw follows it: by this much, ramping in over the first 2 s",
        ge=-90,
        le=90,
    )
    compass_alignment_jump_deg: float = bounded(
        0.0, "the yaw jumps by this much at the EKF's in-flight yaw alignment ...", ge=-90, le=90
    )
    compass_alignment_after_s: float = bounded(10.0, "... this long after arming", ge=0)
    compass_wander_deg: float = bounded(
        0.0, "armed: the compass wanders slowly (a sinusoid of this amplitude ...)", ge=0, le=90
    )
    compass_wander_period_s: float = bounded(60.0, "... and this period)", gt=0)


@dataclass(frozen=True)
class Step:
    """A jump of the estimate caused by a reset (a new ``reset_counter``): when and how far."""

    t_s: float
    step_m: float
    reset_counter: int


class SimEstimator:
    """The flight controller's horizontal position estimate (see the module docstring).

    Args:
        spec: :class:`EstimatorSpec`.
        p0_ned_m: (2,) or (3,) the truth's position at the start (only x, y are used).
        rng: the flight controller's random generator (the IMU drift's draws).
    """

    def __init__(self, spec: EstimatorSpec, p0_ned_m: np.ndarray, rng: np.random.Generator) -> None:
        self.spec = spec
        self._rng = rng
        self._t_s = 0.0
        self._p = np.array(p0_ned_m[:2], dtype=float)
        self._v_err = np.zeros(2)  # the IMU's velocity error (unknown to the estimator)
        self._v_corr = np.zeros(2)  # the correction learnt from vision
        self._last_vision_s = -math.inf
        self._last_counter: int | None = None
        self.steps: list[Step] = []
        self.fused = 0
        self.has_position = True  # at boot the estimate starts at its origin, where the vehicle is

    def propagate(self, t_s: float, v_true_ned_m_s: np.ndarray) -> None:
        """Dead-reckon to ``t_s`` on the true velocity plus the IMU's error and the learnt correction."""
        dt = t_s - self._t_s
        if dt <= 0:
            return
        self._v_err += self._rng.normal(0.0, self.spec.imu_drift_m_s_per_sqrt_s * math.sqrt(dt), 2)
        self._p += (np.asarray(v_true_ned_m_s[:2], dtype=float) + self._v_err + self._v_corr) * dt
        self._t_s = t_s

    def reboot(self) -> None:
        """The flight controller restarted: its position is gone until the next vision sample."""
        self.has_position = False
        self._last_counter = None
        self._v_corr = np.zeros(2)

    def fuse_vision(self, t_s: float, x_m: float, y_m: float, reset_counter: int) -> None:
        """A VISION_POSITION_ESTIMATE arrived at ``t_s`` (after :meth:`propagate` to ``t_s``)."""
        z = np.array([x_m, y_m], dtype=float)
        if not np.all(np.isfinite(z)):
            return
        if self._last_counter is None or reset_counter != self._last_counter:
            if self._last_counter is not None:
                self.steps.append(Step(t_s, float(np.linalg.norm(z - self._p)), reset_counter))
            self._p = z  # EKF3 moves to the sent position on a reset
            self._last_counter = reset_counter
            self.has_position = True
        else:
            y = z - self._p  # innovation
            self._p += self.spec.position_gain * y
            self._v_corr += self.spec.velocity_gain_per_s * y * min(t_s - self._last_vision_s, _VISION_TIMEOUT_S)
        self._last_vision_s = t_s
        self.fused += 1

    @property
    def t_s(self) -> float:
        """The time the estimate is at."""
        return self._t_s

    def vision_healthy(self, t_s: float) -> bool:
        return t_s - self._last_vision_s <= _VISION_TIMEOUT_S

    @property
    def position_ne_m(self) -> np.ndarray:
        """(2,) the current north, east estimate."""
        return self._p.copy()

    def velocity_ne_m_s(self, v_true_ned_m_s: np.ndarray) -> np.ndarray:
        """(2,) the velocity the estimator believes in."""
        return np.asarray(v_true_ned_m_s[:2], dtype=float) + self._v_err + self._v_corr

    def yaw_error_rad(self, t_boot_s: float, t_armed_s: float | None = None) -> float:
        """The reported yaw minus the true yaw, ``t_boot_s`` after boot and ``t_armed_s`` after arming
        (None: disarmed, the motors off and the compass clean)."""
        sp = self.spec
        settling = sp.yaw_initial_error_deg * math.exp(-max(t_boot_s, 0.0) / sp.yaw_settle_time_s)
        compass = 0.0
        if t_armed_s is not None:
            compass = sp.compass_motor_deg * min(1.0, t_armed_s / _MOTOR_RAMP_S)
            compass += sp.compass_alignment_jump_deg if t_armed_s >= sp.compass_alignment_after_s else 0.0
            compass += sp.compass_wander_deg * math.sin(math.tau * t_armed_s / sp.compass_wander_period_s)
        return math.radians(settling + compass)
