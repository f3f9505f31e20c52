"""A small constant-velocity Kalman filter on NED position and yaw.

State (8): position x, y, z (m), velocity (m/s), yaw (rad, kept continuous, not wrapped) and yaw rate
(rad/s). Process noise is white acceleration (``accel_sigma_m_s2``) and white yaw acceleration.
Measurements are vision positions and yaws with a covariance from the odometry's quality, and the down
coordinate alone (a height above the ground from a rangefinder, :meth:`PoseFilter.update_down`). Before an
update, the innovation's squared Mahalanobis distance is compared with the chi-square quantile of
``gate_probability`` for as many degrees of freedom as the measurement has (4 for position and yaw,
1 for yaw alone): a jump beyond it is rejected. After ``max_rejections`` rejections in a row the
filter believes the measurements again and restarts at the latest one (keeping its velocity), so a
real change is followed instead of coasted past.

The predict and update steps are written out here (a dozen lines of numpy, the equations beside them)
rather than taken from filterpy: importing filterpy's KalmanFilter loads its whole package and
scipy.stats with it, 0.8 s of the service's 1.3 s of imports before its first estimate.
``tests/test_odometry_parts.py`` checks the steps against filterpy's.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from mavvo.options import bounded

__all__ = ["FilterOptions", "PoseFilter", "Update", "chi2_cdf", "chi2_quantile", "wrap_angle"]

_DIM_X, _DIM_Z = 8, 4
_H = np.zeros((_DIM_Z, _DIM_X))
_H[0, 0] = _H[1, 1] = _H[2, 2] = _H[3, 6] = 1.0
_PAIRS = ((0, 3), (1, 4), (2, 5), (6, 7))  # (value, rate) state pairs: north, east, down, yaw


class Update(enum.Enum):
    """What :meth:`PoseFilter.update` did with a measurement."""

    FUSED = "fused"
    REJECTED = "rejected"  #: beyond the gate
    RESTARTED = "restarted"  #: the gate rejected too many in a row: the filter restarted at this one


def chi2_cdf(x: float, dof: int) -> float:
    """P(X <= x) for X chi-square with ``dof`` (a positive integer) degrees of freedom, in closed form:
    even k: 1 - exp(-x/2) sum_{i<k/2} (x/2)^i / i!;  odd k: erf(sqrt(x/2)) - exp(-x/2) sum_{i<(k-1)/2}
    (x/2)^(i+1/2) / Gamma(i+3/2)."""
    if x <= 0:
        return 0.0
    h = 0.5 * x
    if dof % 2 == 0:
        return 1.0 - math.exp(-h) * sum(h**i / math.factorial(i) for i in range(dof // 2))
    return math.erf(math.sqrt(h)) - math.exp(-h) * sum(
        h ** (i + 0.5) / math.gamma(i + 1.5) for i in range((dof - 1) // 2)
    )


def chi2_quantile(probability: float, dof: int) -> float:
    """The x with chi2_cdf(x, dof) = probability (bisection to 1e-10 relative)."""
    lo, hi = 0.0, 1.0
    while chi2_cdf(hi, dof) < probability:
        hi *= 2.0
    while hi - lo > 1e-10 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2_cdf(mid, dof) < probability else (lo, mid)
    return 0.5 * (lo + hi)


def wrap_angle(a: float) -> float:
    """``a`` wrapped to [-pi, pi)."""
    return float((a + np.pi) % (2.0 * np.pi) - np.pi)


@dataclass(frozen=True)
class FilterOptions:
    """Settings of :class:`PoseFilter`."""

    accel_sigma_m_s2: float = bounded(3.0, "process noise: white acceleration, 1 sigma", gt=0, le=100)
    yaw_accel_sigma_rad_s2: float = bounded(2.0, "process noise: white yaw acceleration, 1 sigma", gt=0, le=100)
    initial_velocity_sigma_m_s: float = bounded(1.0, "velocity uncertainty at a (re)start", gt=0, le=100)
    initial_yaw_rate_sigma_rad_s: float = bounded(
        2.0, "yaw rate uncertainty at a start (a start mid-turn must not be gated away)", gt=0, le=20
    )
    gate_probability: float = bounded(
        0.999,
        "reject a measurement whose squared Mahalanobis distance exceeds the chi2 quantile of this probability (dof: the measurement's size)",
        gt=0,
        lt=1,
    )
    max_rejections: int = bounded(5, "after this many rejections in a row, restart at the measurement", ge=1, le=1000)
    tilt_acceleration: bool = bounded(
        True,
        "while vision sees nothing, coast on the horizontal acceleration the flight controller's roll and pitch give a multirotor (thrust along the body's z); off for a vehicle whose tilt does not drive it",
    )


class PoseFilter:
    """Constant-velocity filter (see the module docstring). Times are seconds on any one clock."""

    def __init__(self, options: FilterOptions | None = None) -> None:
        self.options = options or FilterOptions()
        self._x = np.zeros((_DIM_X, 1))  # state (column)
        self._P = np.eye(_DIM_X)  # its covariance
        self._t_s: float | None = None
        self.rejections = 0
        self._innovation: tuple[np.ndarray, np.ndarray] | None = None  # the last fused position's (y, S)
        # Gate per measurement size: position and yaw (4), yaw alone (1).
        self._gate = {k: chi2_quantile(self.options.gate_probability, k) for k in (1, _DIM_Z)}

    def reset(
        self,
        t_s: float,
        p_ned_m: np.ndarray,
        yaw_rad: float,
        *,
        v_ned_m_s: np.ndarray | None = None,
        yaw_rate_rad_s: float | None = None,
        pos_cov_m2: np.ndarray,
        yaw_sigma_rad: float,
    ) -> None:
        """Start at a pose (velocity and yaw rate zero, with their initial sigmas, unless given);
        ``pos_cov_m2`` (3,3) its position covariance."""
        x = np.zeros((_DIM_X, 1))
        x[0:3, 0] = p_ned_m
        if v_ned_m_s is not None:
            x[3:6, 0] = v_ned_m_s
        x[6, 0] = yaw_rad
        opt = self.options
        sw = opt.initial_yaw_rate_sigma_rad_s
        if yaw_rate_rad_s is not None:
            x[7, 0], sw = yaw_rate_rad_s, 0.1
        self._x = x
        self._P = np.diag([0.0] * 3 + [opt.initial_velocity_sigma_m_s**2] * 3 + [yaw_sigma_rad**2, sw**2])
        self._P[0:3, 0:3] = pos_cov_m2
        self._t_s = float(t_s)
        self.rejections = 0
        self._innovation = None

    def predict(self, t_s: float, accel_ned_m_s2: np.ndarray | None = None) -> None:
        """Move the state to ``t_s`` (no-op for a time at or before the current one), with a known
        acceleration (3,) m/s^2 over the step when given (the process noise is what it leaves out)."""
        if self._t_s is None:
            raise RuntimeError("PoseFilter.predict before reset")
        dt = float(t_s) - self._t_s
        if dt <= 0:
            return
        F = np.eye(_DIM_X)
        F[0, 3] = F[1, 4] = F[2, 5] = F[6, 7] = dt
        # White acceleration over dt on each (position, velocity) pair and on (yaw, yaw rate):
        # q = [[dt^4/4, dt^3/2], [dt^3/2, dt^2]] times the acceleration's variance.
        Q = np.zeros((_DIM_X, _DIM_X))
        for (i, j), var in zip(
            _PAIRS, (self.options.accel_sigma_m_s2**2,) * 3 + (self.options.yaw_accel_sigma_rad_s2**2,)
        ):
            Q[i, i], Q[i, j], Q[j, j] = var * dt**4 / 4, var * dt**3 / 2, var * dt**2
            Q[j, i] = Q[i, j]
        self._x = F @ self._x  # x = F x
        if accel_ned_m_s2 is not None:  # ... + B u, B = [dt^2/2, dt] per (position, velocity) pair
            self._x[0:3, 0] += 0.5 * dt**2 * accel_ned_m_s2
            self._x[3:6, 0] += dt * accel_ned_m_s2
        self._P = F @ self._P @ F.T + Q  # P = F P F' + Q
        self._t_s = float(t_s)

    def update(
        self, p_ned_m: np.ndarray | None, yaw_rad: float, *, pos_cov_m2: np.ndarray, yaw_sigma_rad: float
    ) -> Update:
        """Fuse a measurement taken at the current time (see :class:`Update`): a position with
        covariance ``pos_cov_m2`` (3,3) m^2, and a yaw.

        ``p_ned_m`` None measures the yaw only (vision saw a rotation but no translation).
        """
        x, P = self._x, self._P
        self._innovation = None
        rows = slice(0, 4) if p_ned_m is not None else slice(3, 4)
        H = _H[rows]
        z = np.empty((_DIM_Z, 1))
        if p_ned_m is not None:
            z[0:3, 0] = p_ned_m
        z[3, 0] = x[6, 0] + wrap_angle(yaw_rad - x[6, 0])
        z = z[rows]
        R = np.zeros((_DIM_Z, _DIM_Z))
        R[0:3, 0:3] = pos_cov_m2
        R[3, 3] = yaw_sigma_rad**2
        R = R[rows, rows]
        y = z - H @ x  # innovation y = z - H x
        S = H @ P @ H.T + R  # its covariance S = H P H' + R
        d2 = float((y.T @ np.linalg.solve(S, y))[0, 0])  # squared Mahalanobis distance y' S^-1 y
        if d2 > self._gate[len(z)]:
            self.rejections += 1
            if self.rejections < self.options.max_rejections:
                return Update.REJECTED
            p = x[0:3, 0] if p_ned_m is None else p_ned_m
            self.reset(
                self._t_s,
                p,
                z[-1, 0],
                v_ned_m_s=x[3:6, 0],
                yaw_rate_rad_s=float(x[7, 0]),
                pos_cov_m2=pos_cov_m2,
                yaw_sigma_rad=yaw_sigma_rad,
            )
            return Update.RESTARTED
        self.rejections = 0
        self._innovation = (y[0:3, 0].copy(), S[0:3, 0:3].copy()) if p_ned_m is not None else None
        K = np.linalg.solve(S, H @ P).T  # gain K = P H' S^-1 (S and P symmetric)
        self._x = x + K @ y  # x = x + K y
        I_KH = np.eye(_DIM_X) - K @ H
        self._P = (
            I_KH @ P @ I_KH.T + K @ R @ K.T
        )  # P = (I - K H) P (I - K H)' + K R K' (Joseph: stays symmetric, positive)
        return Update.FUSED

    def error_share_m(self, cov_m2: np.ndarray) -> np.ndarray:
        """(3,) m: the part of the last fused position's error expected to come from one of its
        independent sources, of covariance ``cov_m2`` (3,3): E[n | y] = R_n S^-1 y on the innovation's
        position part (zero when the last update fused no position)."""
        if self._innovation is None:
            return np.zeros(3)
        y, S = self._innovation
        return cov_m2 @ np.linalg.solve(S, y)

    def update_down(self, down_m: float, sigma_m: float, *, gated: bool = True) -> Update:
        """Fuse a measurement of the down coordinate alone (a height from a rangefinder), 1 sigma
        ``sigma_m``, gated with one degree of freedom unless ``gated`` is False. A rejection is only
        counted: what a run of them means (the ground moved, or the estimate drifted) is the caller's
        to decide."""
        x, P = self._x, self._P
        y = down_m - x[2, 0]  # innovation y = z - H x, H picking the down coordinate
        S = P[2, 2] + sigma_m**2  # S = H P H' + R
        if gated and y * y / S > self._gate[1]:
            return Update.REJECTED
        K = P[:, 2:3] / S  # K = P H' / S
        self._x = x + K * y  # x = x + K y
        I_KH = np.eye(_DIM_X)
        I_KH[:, 2] -= K[:, 0]  # I - K H
        self._P = I_KH @ P @ I_KH.T + (K @ K.T) * sigma_m**2  # Joseph form, as in update
        return Update.FUSED

    def shift_down(self, delta_m: float) -> None:
        """Move the down coordinate by ``delta_m`` (the reference it is measured from was corrected)."""
        self._x[2, 0] += delta_m

    def gate(self, dof: int) -> float:
        """The chi-square gate of a measurement with ``dof`` degrees of freedom."""
        return self._gate[dof] if dof in self._gate else chi2_quantile(self.options.gate_probability, dof)

    def set_down(self, down_m: float, sigma_m: float) -> None:
        """Put the down coordinate at ``down_m`` with 1 sigma ``sigma_m``, its cross terms dropped: a
        measured height that has outvoted the estimate for several frames in a row, where an update
        weighed against vision's tight down would move it by millimetres."""
        self._x[2, 0] = down_m
        self._P[2, :] = 0.0
        self._P[:, 2] = 0.0
        self._P[2, 2] = sigma_m**2

    def set_position_covariance(self, cov_m2: np.ndarray) -> None:
        """Replace the position's covariance (3,3) m^2, its cross terms with the rest dropped: after a
        coast, what is known of the position is what the coast says, not the white acceleration assumed."""
        self._P[0:3, :] = 0.0
        self._P[:, 0:3] = 0.0
        self._P[0:3, 0:3] = cov_m2

    def set_horizontal_velocity(self, v_ne_m_s: np.ndarray) -> None:
        """Replace the north and east velocity (2,) m/s, their covariance kept."""
        self._x[3:5, 0] = v_ne_m_s

    def commit_position_noise(self, cov_m2: np.ndarray) -> None:
        """Grow the position uncertainty by ``cov_m2`` (3,3): an error now fixed in the reference every
        later measurement is made from (a new keyframe), which no later measurement can average away."""
        self._P[0:3, 0:3] += cov_m2

    def shift_yaw(self, delta_rad: float) -> None:
        """Turn the yaw state by ``delta_rad`` (the world heading was corrected; nothing measured)."""
        self._x[6, 0] += delta_rad

    @property
    def position_ned_m(self) -> np.ndarray:
        return self._x[0:3, 0].copy()

    @property
    def velocity_ned_m_s(self) -> np.ndarray:
        return self._x[3:6, 0].copy()

    @property
    def yaw_rad(self) -> float:
        return wrap_angle(float(self._x[6, 0]))

    @property
    def position_covariance(self) -> np.ndarray:
        """(3,3) m^2."""
        return self._P[0:3, 0:3].copy()

    @property
    def velocity_covariance(self) -> np.ndarray:
        """(3,3) (m/s)^2."""
        return self._P[3:6, 3:6].copy()

    @property
    def yaw_variance(self) -> float:
        """rad^2."""
        return float(self._P[6, 6])
