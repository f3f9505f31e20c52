"""Roll, pitch and yaw from a data set's IMU alone: what a flight controller's attitude estimate gives.

Two steps, both over the whole recording (a replay has it all before the first frame):

1. :func:`imu_start`: which way is down at the start, and the gyro's bias, by least squares over the
   recording. Gyro integration from a start attitude R0 with bias b carries every specific force into
   the level frame; their sum plus gravity is the velocity. A wrong tilt or bias makes gravity leak
   into the horizontal, and the velocity it makes grows as t (tilt) or t^2 (bias), while a vehicle
   flying within a site keeps its velocity near a constant. So R0's tilt, b and that constant v0 are
   the ones that keep the integrated velocity smallest. This needs no rest at the start; where the
   IMU is at rest (its first or last second) its own means are exact and are used instead.
2. :func:`imu_attitude`: Mahony's filter with integral feedback, started from that attitude and bias,
   with small gains (in turns the accelerometer is not gravity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavvo.geometry.frames import R_from_euler321, euler321_from_R, skew
from mavvo.geometry.refine import tilt_rotation

__all__ = ["ImuStart", "imu_attitude", "imu_start", "level_from_up", "tilt_error_deg"]

# Gains (rad/s and rad/s^2 per rad of tilt error): the accelerometer's pull toward its "up" and how fast
# the gyro-bias estimate follows the pull that persists. Small, as in a turn the accelerometer is not
# gravity (0.3 gave 3.4 deg median error in a figure eight at 0.7 m/s^2, 0.02 gave 0.4 deg); small gains
# need an exact start bias (a residual bias r tilts the estimate by about r / kp), which imu_start gives.
ATTITUDE_KP = 0.02
ATTITUDE_KI = 0.001
ATTITUDE_RATE_HZ = 100.0
GRAVITY_M_S2 = 9.81
_REST_GYRO_STD = 0.02  # rad/s: a gyro this steady over a second is at rest (in flight, rotors shake it)
# The least squares of imu_start: horizons over which it is solved in turn, so that each starts from a
# tilt and bias good enough to linearise about (a 0.1 rad/s bias turns 0.5 rad in the first 5 s), the
# Gauss-Newton steps per horizon, and the rate of the velocities it fits.
_HORIZONS_S = (5.0, 15.0, 45.0, 135.0)
_STEPS_PER_HORIZON = 2
_FIT_RATE_HZ = 10.0


@dataclass(frozen=True)
class ImuStart:
    """The IMU's state at its first sample, from :func:`imu_start`.

    ``specific_force_imu_m_s2``: (3,) what the accelerometer would read at rest there (gravity's
    reaction: "up" in the IMU frame, 9.81 m/s^2 long); ``gyro_bias_rad_s``: (3,) IMU frame."""

    specific_force_imu_m_s2: np.ndarray
    gyro_bias_rad_s: np.ndarray


def _skew_many(w: np.ndarray) -> np.ndarray:
    """(N,3,3) cross-product matrices [w]x of (N,3) vectors."""
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    return K - K.transpose(0, 2, 1)


def _exp_many(w: np.ndarray) -> np.ndarray:
    """(N,3,3) rotation matrices exp([w]x) of (N,3) rotation vectors (Rodrigues)."""
    th = np.linalg.norm(w, axis=1)
    small = th < 1e-9
    th_safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0, np.sin(th_safe) / th_safe)
    c = np.where(small, 0.5, (1.0 - np.cos(th_safe)) / th_safe**2)
    K = _skew_many(w)
    return np.eye(3) + a[:, None, None] * K + c[:, None, None] * (K @ K)


def _exp(w: np.ndarray) -> np.ndarray:
    """exp([w]x) of one rotation vector (3,): the filter's per-sample step, where a batch of one costs more."""
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-9:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def _integrate(R0: np.ndarray, gyro: np.ndarray, dt: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,3,3) R_lvl_imu at every sample: R_i = R_{i-1} exp((gyro_i - b) dt_i), R_0 = R0.
    The running product as a Hillis-Steele scan: log2(N) batched products instead of N small ones."""
    R = np.empty((len(gyro), 3, 3))
    R[0] = np.eye(3)
    R[1:] = _exp_many((gyro[1:] - b) * dt[:, None])
    k = 1
    while k < len(R):
        R[k:] = R[:-k] @ R[k:]
        k *= 2
    return R0 @ R


def level_from_up(up_imu: np.ndarray, x_imu: np.ndarray | None = None) -> np.ndarray:
    """A R_lvl_imu whose level z points against ``up_imu`` and whose level x is ``x_imu`` made level
    (when given and not vertical; else any)."""
    z = -up_imu / np.linalg.norm(up_imu)
    x = (
        x_imu
        if x_imu is not None and abs(x_imu @ z) < 0.99 * np.linalg.norm(x_imu)
        else np.eye(3)[int(np.argmin(np.abs(z)))]
    )
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z]).T


def _rest_gyro_mean(t: np.ndarray, gyro: np.ndarray, at_end: bool) -> np.ndarray | None:
    """The mean gyro (rad/s, (3,)) over the first (or last) second when the IMU is at rest then (every
    axis's std under _REST_GYRO_STD), else None. At rest it is the bias, on all three axes."""
    w = t >= t[-1] - 1.0 if at_end else t <= t[0] + 1.0
    return gyro[w].mean(axis=0) if float(np.max(gyro[w].std(axis=0))) < _REST_GYRO_STD else None


def _fit(
    t: np.ndarray, gyro: np.ndarray, f: np.ndarray, R0: np.ndarray, b: np.ndarray, fit_bias: bool
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`imu_start`'s least squares from (R0, b), the bias held when not ``fit_bias``: the fitted
    R0 and b."""
    g = np.array([0.0, 0.0, GRAVITY_M_S2])
    horizons = [h for h in _HORIZONS_S if t[0] + h < t[-1]] + [t[-1] - t[0]]
    for horizon in horizons:
        n = int(np.searchsorted(t, t[0] + horizon, side="right"))
        dt = np.diff(t[:n])
        fit = np.arange(0, n, max(int(round((n - 1) / max(horizon * _FIT_RATE_HZ, 1.0))), 1))
        for _ in range(_STEPS_PER_HORIZON):
            R = _integrate(R0, gyro[:n], dt, b)
            fw = np.einsum("nij,nj->ni", R, f[:n])
            A = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(R[1:] * dt[:, None, None], axis=0)])
            Fx = _skew_many(fw)  # phi x fw = -[fw]x phi
            dv = np.concatenate([np.zeros((1, 3)), np.cumsum((fw[:-1] + g) * dt[:, None], axis=0)])
            J_theta = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(-Fx[:-1] * dt[:, None, None], axis=0)])
            J_b = np.concatenate([np.zeros((1, 3, 3)), np.cumsum((Fx @ A)[:-1] * dt[:, None, None], axis=0)])
            horizontal = R0.T[:, :2]  # the level x and y axes in the IMU frame: the bias the fit can see
            J = [np.broadcast_to(np.eye(3), (len(fit), 3, 3)), J_theta[fit, :, :2]]
            J += [J_b[fit] @ horizontal] if fit_bias else []
            x = np.linalg.lstsq(np.concatenate(J, axis=2).reshape(3 * len(fit), -1), -dv[fit].ravel(), rcond=None)[0]
            R0 = tilt_rotation(x[3:5]) @ R0
            b = b + horizontal @ x[5:7] if fit_bias else b
    return R0, b


def imu_start(imu: np.ndarray) -> ImuStart:
    """Down and the gyro bias at the start of (M,7) IMU rows (t_ns, gyro xyz rad/s, accel xyz m/s^2);
    see the module docstring. The first guess of down is the first second's mean specific force.

    Each Gauss-Newton step linearises about the current (R0, b): with the level-frame rotation error
    phi_i of sample i,

        phi_i = dtheta - A_i db,       A_i = sum_{j<=i} R_j dt_j     (a bias error turns R_j by -R_j db dt_j)
        v_i = v0 + sum_{j<i} (R_j f_j + g) dt_j + sum_{j<i} phi_j x (R_j f_j) dt_j

    and solves for (v0, dtheta_x, dtheta_y, db_x, db_y) making the v_i at _FIT_RATE_HZ smallest (level
    axes at the start; a turn about the vertical moves no gravity, so neither dtheta_z nor the bias
    about the vertical can be seen).

    Where the IMU is at rest, its own means are exact and the fit does less: at rest in the first
    second (a flight controller's boot calibration), down and the bias are that second's means and
    nothing is fitted; at rest in the last second only (a recording that starts moving and lands), the
    bias is that second's mean and only the tilt is fitted; at rest in neither, everything above is,
    with the bias about the vertical from the first second's mean (its yaw drifts by what that
    second turned). A steady turn about the vertical looks like rest to an IMU: that is where this
    can be fooled."""
    t = imu[:, 0] * 1e-9
    gyro, f = imu[:, 1:4], imu[:, 4:7]
    first = t <= t[0] + 1.0
    R0 = level_from_up(f[first].mean(axis=0))
    b = _rest_gyro_mean(t, gyro, at_end=False)
    if b is None:
        b_end = _rest_gyro_mean(t, gyro, at_end=True)
        b = gyro[first].mean(axis=0) if b_end is None else b_end
        R0, b = _fit(t, gyro, f, R0, b, fit_bias=b_end is None)
    return ImuStart(R0.T @ np.array([0.0, 0.0, -GRAVITY_M_S2]), b)


def imu_attitude(imu: np.ndarray, R_imu_body: np.ndarray, start: ImuStart) -> np.ndarray:
    """(N,4) t_s, roll, pitch, yaw of the body from (M,7) IMU rows (t_ns, gyro xyz rad/s, accel xyz
    m/s^2), at ATTITUDE_RATE_HZ: Mahony's filter with integral feedback, what a flight controller's
    attitude estimate does without a magnetometer. Started from :func:`imu_start`'s down and gyro bias
    (yaw 0 there), it integrates the gyro less b, pulled toward the accelerometer's gravity:

        e = u_meas x u_est          (measured and estimated "up" in the IMU frame)
        w = gyro - b + kp e         (the rate integrated)
        db/dt = -ki e               (the bias: what the correction keeps having to add)
    """
    t = imu[:, 0] * 1e-9
    R = level_from_up(start.specific_force_imu_m_s2, R_imu_body[:, 0])  # R_lvl_imu at the start
    b = np.asarray(start.gyro_bias_rad_s, dtype=float).copy()
    out = []
    next_t = t[0]
    up = np.array([0.0, 0.0, -1.0])
    for i in range(1, len(t)):
        dt = t[i] - t[i - 1]
        u_meas = imu[i, 4:7] / max(np.linalg.norm(imu[i, 4:7]), 1e-9)
        e = np.cross(u_meas, R.T @ up)
        b -= ATTITUDE_KI * e * dt
        R = R @ _exp((imu[i, 1:4] - b + ATTITUDE_KP * e) * dt)
        if t[i] >= next_t:
            U, _, Vt = np.linalg.svd(R)
            R = U @ Vt
            out.append((t[i], *euler321_from_R(R @ R_imu_body)))
            next_t = t[i] + 1.0 / ATTITUDE_RATE_HZ
    return np.array(out)


def tilt_error_deg(attitude: np.ndarray, t_truth_s: np.ndarray, R_lvl_body_truth: np.ndarray) -> dict[str, float]:
    """How far the roll/pitch given to mavvo are from the truth: the angle between the true and the
    estimated "down" in the body frame (yaw does not count), at each attitude sample (nearest truth);
    median and 95th percentile, degrees."""
    idx = np.clip(np.searchsorted(t_truth_s, attitude[:, 0]), 0, len(t_truth_s) - 1)
    down_true = R_lvl_body_truth[idx, 2, :]  # third row: the level frame's z in body coordinates
    down_est = np.array([R_from_euler321(r, p, y)[2, :] for _, r, p, y in attitude])
    err = np.degrees(np.arccos(np.clip(np.sum(down_true * down_est, axis=1), -1.0, 1.0)))
    return {"median": round(float(np.median(err)), 3), "p95": round(float(np.percentile(err, 95)), 3)}
