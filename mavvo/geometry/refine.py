"""Least-squares refinement of two-view models on level-frame bearings.

- :func:`refine_upright`: Gauss-Newton on the upright manifold (yaw and the unit translation: 3
  degrees of freedom of E, 4 parameters with the scale of t fixed) on Sampson errors; optionally the
  roll and pitch of both views move too, held by a Gaussian prior of the IMU's sigma, and a Cauchy
  loss keeps far points from pulling.
- :func:`ground_similarity`: the ground-plane homography in closed form (weighted least squares).
- :func:`fit_rotation`: the pure rotation (no baseline) in closed form.

Conventions as in :mod:`mavvo.geometry.essential`: ``x_2 = R_2_1 @ x_1 + t_2_1``, ``R_2_1 = Rz(yaw)``. A tilt
correction ``d = (dx, dy)`` of a view is the small rotation ``exp([dx, dy, 0]x)`` applied to that
view's level bearings: ``f_corrected = tilt_rotation(d) @ f``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mavvo.geometry.residuals import sampson_sq_point
from mavvo.geometry.small_linalg import solve_spd
from mavvo.jit import kernel

__all__ = ["UprightFit", "tilt_rotation", "refine_upright", "upright_yaw_variance", "ground_similarity", "fit_rotation"]


@dataclass(frozen=True)
class UprightFit:
    """Result of :func:`refine_upright`.

    Attributes:
        yaw_rad: yaw of ``R_2_1`` between the (corrected) level frames.
        t_2_1: (3,) unit translation in the (corrected) level frame of view 2.
        tilt1_rad, tilt2_rad: (2,) tilt corrections of each view (zeros without the tilt prior).
        iterations: Gauss-Newton steps taken.
    """

    yaw_rad: float
    t_2_1: np.ndarray
    tilt1_rad: np.ndarray
    tilt2_rad: np.ndarray
    iterations: int


def tilt_rotation(d: np.ndarray) -> np.ndarray:
    """(3,3) rotation ``exp([dx, dy, 0]x)`` (Rodrigues) for a tilt correction d (2,) in radians."""
    return tilt_matrix(float(d[0]), float(d[1]))


def refine_upright(
    yaw_rad: float,
    t_2_1: np.ndarray,
    f1: np.ndarray,
    f2: np.ndarray,
    *,
    iterations: int = 5,
    tilt_sigma_rad: float | tuple[float, float] | None = None,
    noise_sigma_rad: float | None = None,
    tilt1_rad: np.ndarray | None = None,
    tilt2_rad: np.ndarray | None = None,
    robust_scale_rad: float | None = None,
) -> UprightFit:
    """Gauss-Newton on the Sampson errors of ``E = [t]x Rz(yaw)`` over the given correspondences.

    Args:
        yaw_rad, t_2_1: the starting pose (t of any non-zero length; it is normalised).
        f1, f2: (N, 3) unit level-frame bearings, all of them inliers (the caller selects them).
        iterations: maximum number of steps; stops early when the step is below 1e-8 (rad).
        tilt_sigma_rad: when given, the roll and pitch of each view may move as well, each with a
            Gaussian prior of this standard deviation (the IMU's; one for both views or one per view),
            centred on no correction. Needs ``noise_sigma_rad``.
        noise_sigma_rad: the bearing noise that weighs the data against the tilt prior.
        tilt1_rad, tilt2_rad: (2,) the corrections to start from (default none).
        robust_scale_rad: when given, a Cauchy loss of this scale, ``rho(r) = c^2 log(1 + r^2/c^2)``, by
            reweighting each step (IRLS): points far off the model count less.

    Returns:
        The refined :class:`UprightFit`. With fewer points than parameters it returns the start.
    """
    with_tilt = tilt_sigma_rad is not None
    if with_tilt and not (noise_sigma_rad and noise_sigma_rad > 0 and np.all(np.asarray(tilt_sigma_rad) > 0)):
        raise ValueError("tilt_sigma_rad and noise_sigma_rad: both must be positive to refine tilt")
    t = np.asarray(t_2_1, dtype=float) / np.linalg.norm(t_2_1)
    d = np.zeros(4)
    if tilt1_rad is not None:
        d[:2] = tilt1_rad
    if tilt2_rad is not None:
        d[2:] = tilt2_rad
    if len(f1) < (3 if not with_tilt else 1):
        return UprightFit(float(yaw_rad), t, d[:2], d[2:], 0)
    prior_w = np.zeros(4)
    if with_tilt:
        s1, s2 = (tilt_sigma_rad, tilt_sigma_rad) if np.isscalar(tilt_sigma_rad) else tilt_sigma_rad  # type: ignore[misc]
        prior_w[:] = (1.0 / s1, 1.0 / s1, 1.0 / s2, 1.0 / s2)  # type: ignore[operator]
    x = np.array([float(yaw_rad), *t, *d])  # (yaw, t, d1, d2): the kernel's state, updated in place
    steps = gauss_newton_upright(
        x,
        np.ascontiguousarray(f1, dtype=np.float64),
        np.ascontiguousarray(f2, dtype=np.float64),
        int(iterations),
        with_tilt,
        prior_w,
        1.0 / noise_sigma_rad if with_tilt else 1.0,
        robust_scale_rad or 0.0,  # type: ignore[operator]
    )
    return UprightFit(
        float(np.arctan2(np.sin(x[0]), np.cos(x[0]))), x[1:4].copy(), x[4:6].copy(), x[6:8].copy(), int(steps)
    )


@kernel
def upright_vector(yaw: float, t: np.ndarray) -> np.ndarray:
    """e (6,) = (E13, E21, E22, E23, E31, E32) of ``E = [t]x Rz(yaw)``."""
    return np.array(upright_tuple(yaw, t[0], t[1], t[2]))


@kernel(inline=True)
def upright_tuple(yaw: float, t0: float, t1: float, t2: float) -> tuple[float, float, float, float, float, float]:
    """:func:`upright_vector` as a tuple of scalars (for per-point loops)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return (t1, t2 * c, -t2 * s, -t0, -t1 * c + t0 * s, t1 * s + t0 * c)


@kernel(inline=True)
def rotate_row(R: np.ndarray, f: np.ndarray, i: int) -> tuple[float, float, float]:
    """``R @ f[i]`` for R (3, 3) and f (N, 3), as scalars."""
    x, y, z = f[i, 0], f[i, 1], f[i, 2]
    return (
        R[0, 0] * x + R[0, 1] * y + R[0, 2] * z,
        R[1, 0] * x + R[1, 1] * y + R[1, 2] * z,
        R[2, 0] * x + R[2, 1] * y + R[2, 2] * z,
    )


def upright_yaw_variance(yaw_rad: float, t_2_1: np.ndarray, f1: np.ndarray, f2: np.ndarray, sigma_rad: float) -> float:
    """Variance (rad^2) of the yaw of ``E = [t]x Rz(yaw)`` fitted to the inlier bearings ``f1``, ``f2``
    (N, 3, level frames, corrected) with Sampson errors of ``sigma_rad``, the translation's direction
    free: ``sigma^2 [(J^T J)^-1]_00`` over (yaw, t along its tangent basis).

    The translation is what makes it honest on a forward camera: there a turn and a sideways step move
    the far points alike, and the yaw alone (the points' horizontal extent) looks several times better
    determined than it is. NaN with fewer than 3 points, a zero translation or a singular system."""
    t = np.asarray(t_2_1, dtype=np.float64)
    nt = float(np.linalg.norm(t))
    if len(f1) < 3 or not nt > 0 or not math.isfinite(sigma_rad):
        return float("nan")
    x = np.array([float(yaw_rad), *(t / nt), 0.0, 0.0, 0.0, 0.0])
    eye = np.eye(3)
    J, _ = _upright_rows(
        x, eye, eye, np.ascontiguousarray(f1, dtype=np.float64), np.ascontiguousarray(f2, dtype=np.float64), 1.0, 0.0
    )
    A = J[:3] @ J[:3].T
    try:
        cov = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return float("nan")
    var = float(cov[0, 0]) * sigma_rad**2
    return var if math.isfinite(var) and var > 0 else float("nan")


@kernel
def tilt_matrix(dx: float, dy: float) -> np.ndarray:
    """(3, 3) ``exp([dx, dy, 0]x)`` (Rodrigues), as :func:`tilt_rotation`."""
    th = math.sqrt(dx * dx + dy * dy)
    K = np.array([[0.0, 0.0, dy], [0.0, 0.0, -dx], [-dy, dx, 0.0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / (th * th)) * (K @ K)


@kernel
def _tangent_basis(t0: float, t1: float, t2: float) -> tuple[float, float, float, float, float, float]:
    """Tangent basis of the unit t: b1 = t x helper (normalised), b2 = t x b1."""
    if abs(t0) < 0.9:
        b10, b11, b12 = 0.0, t2, -t1  # t x e_x
    else:
        b10, b11, b12 = -t2, 0.0, t0  # t x e_y
    nb = math.sqrt(b10 * b10 + b11 * b11 + b12 * b12)
    b10, b11, b12 = b10 / nb, b11 / nb, b12 / nb
    return b10, b11, b12, t1 * b12 - t2 * b11, t2 * b10 - t0 * b12, t0 * b11 - t1 * b10


# Reassociation and contraction only (no assumption on NaN or inf): the per-point loop then runs on
# several points at once; the rounding differs from the plain loop by a few ulp.
@kernel(fastmath={"reassoc", "contract", "nsz"})
def _upright_rows(
    x: np.ndarray, T1: np.ndarray, T2: np.ndarray, f1: np.ndarray, f2: np.ndarray, noise_w: float, robust_c: float
) -> tuple[np.ndarray, np.ndarray]:
    """The weighted Jacobian J (7, N) of the Sampson residuals at x = (yaw, t, d1, d2) with respect to
    (yaw, t along the tangent basis b1, b2, d1, d2), and the weighted residuals (N,): the rows of one
    Gauss-Newton step of :func:`gauss_newton_upright` (its caller drops the tilt rows when they are fixed).

    T1, T2: the tilt rotations of d1, d2; f1, f2 (N, 3) the level bearings. Weights: the Cauchy IRLS
    weight of ``robust_c`` (none when 0) times ``noise_w``."""
    yaw, t0, t1, t2 = x[0], x[1], x[2], x[3]
    cy, sy = math.cos(yaw), math.sin(yaw)
    b10, b11, b12, b20, b21, b22 = _tangent_basis(t0, t1, t2)
    # E = [t]x Rz: rows of Rz are (cy, -sy, 0), (sy, cy, 0), (0, 0, 1)
    E00, E01, E02 = -t2 * sy, -t2 * cy, t1
    E10, E11, E12 = t2 * cy, -t2 * sy, -t0
    E20, E21 = -t1 * cy + t0 * sy, t1 * sy + t0 * cy
    A00, A01, A02, A10, A11, A12, A20, A21, A22 = (
        T1[0, 0],
        T1[0, 1],
        T1[0, 2],
        T1[1, 0],
        T1[1, 1],
        T1[1, 2],
        T1[2, 0],
        T1[2, 1],
        T1[2, 2],
    )
    B00, B01, B02, B10, B11, B12, B20, B21, B22 = (
        T2[0, 0],
        T2[0, 1],
        T2[0, 2],
        T2[1, 0],
        T2[1, 1],
        T2[1, 2],
        T2[2, 0],
        T2[2, 1],
        T2[2, 2],
    )
    inv_c = 1.0 / robust_c if robust_c > 0.0 else 0.0  # 0: the Cauchy weight below is 1
    N = f1.shape[0]
    J = np.empty((7, N))
    res = np.empty(N)
    for i in range(N):
        x1, y1, z1 = f1[i, 0], f1[i, 1], f1[i, 2]
        x2, y2, z2 = f2[i, 0], f2[i, 1], f2[i, 2]
        p0 = A00 * x1 + A01 * y1 + A02 * z1  # f1c = T1 f1
        p1 = A10 * x1 + A11 * y1 + A12 * z1
        p2 = A20 * x1 + A21 * y1 + A22 * z1
        q0 = B00 * x2 + B01 * y2 + B02 * z2  # f2c = T2 f2
        q1 = B10 * x2 + B11 * y2 + B12 * z2
        q2 = B20 * x2 + B21 * y2 + B22 * z2
        g0, g1, g2 = cy * p0 - sy * p1, sy * p0 + cy * p1, p2  # g = Rz f1c
        a0 = E00 * p0 + E01 * p1 + E02 * p2  # E f1c = t x g
        a1 = E10 * p0 + E11 * p1 + E12 * p2
        a2 = E20 * p0 + E21 * p1
        c0 = E00 * q0 + E10 * q1 + E20 * q2  # E^T f2c
        c1 = E01 * q0 + E11 * q1 + E21 * q2
        c2 = E02 * q0 + E12 * q1
        n = q0 * a0 + q1 * a1 + q2 * a2  # f2c . (t x g)
        # Sampson scale: the tangent gradients of n at both bearings.
        den = max(a0 * a0 + a1 * a1 + a2 * a2 + c0 * c0 + c1 * c1 + c2 * c2 - 2.0 * n * n, 1e-30)
        inv_s = 1.0 / math.sqrt(den)
        # d n / d yaw = (t . g) f2_z - t_z (g . f2)   (d g / d yaw = e_z x g)
        tg = t0 * g0 + t1 * g1 + t2 * g2
        tq = t0 * q0 + t1 * q1 + t2 * q2
        j0 = tg * q2 - t2 * (g0 * q0 + g1 * q1 + g2 * q2)
        k0, k1, k2 = g1 * q2 - g2 * q1, g2 * q0 - g0 * q2, g0 * q1 - g1 * q0  # g x f2c: d n / d t
        j1 = k0 * b10 + k1 * b11 + k2 * b12
        j2 = k0 * b20 + k1 * b21 + k2 * b22
        w0, w1, w2 = q1 * t2 - q2 * t1, q2 * t0 - q0 * t2, q0 * t1 - q1 * t0  # f2c x t
        # d n / d d1: (Rz (e x f1c)) . (f2c x t) for e = e_x (0, -p2, p1) and e_y (p2, 0, -p0)
        ux0, ux1, ux2 = sy * p2, -cy * p2, p1
        uy0, uy1, uy2 = cy * p2, sy * p2, -p0
        j3 = ux0 * w0 + ux1 * w1 + ux2 * w2
        j4 = uy0 * w0 + uy1 * w1 + uy2 * w2
        # d n / d d2: (e x f2c) . E f1c
        j5 = -q2 * a1 + q1 * a2
        j6 = q2 * a0 - q0 * a2
        # The Sampson scale moves with the pose too: r = n / sqrt(den), so dr = (dn - n/(2 den) dden) / sqrt(den).
        # With unit t, g and f2c, den = 2 - (t.g)^2 - (t.f2c)^2 - 2 n^2. Held fixed instead, the steps
        # settle where sum n dn / den = 0, off the Sampson minimum by the n^2 dden terms (measurably
        # worse translations on the forward flight's pairs).
        h = n / (2.0 * den)
        j0 -= h * (-2.0 * tg * (g0 * t1 - g1 * t0) - 4.0 * n * j0)  # d(t.g)/d yaw = (g x t)_z
        j1 -= h * (
            -2.0 * tg * (b10 * g0 + b11 * g1 + b12 * g2) - 2.0 * tq * (b10 * q0 + b11 * q1 + b12 * q2) - 4.0 * n * j1
        )
        j2 -= h * (
            -2.0 * tg * (b20 * g0 + b21 * g1 + b22 * g2) - 2.0 * tq * (b20 * q0 + b21 * q1 + b22 * q2) - 4.0 * n * j2
        )
        j3 -= h * (-2.0 * tg * (t0 * ux0 + t1 * ux1 + t2 * ux2) - 4.0 * n * j3)
        j4 -= h * (-2.0 * tg * (t0 * uy0 + t1 * uy1 + t2 * uy2) - 4.0 * n * j4)
        j5 -= h * (-2.0 * tq * (t2 * q1 - t1 * q2) - 4.0 * n * j5)  # e_x x f2c = (0, -q2, q1)
        j6 -= h * (-2.0 * tq * (t0 * q2 - t2 * q0) - 4.0 * n * j6)  # e_y x f2c = (q2, 0, -q0)
        r = n * inv_s
        # Cauchy IRLS: weight 1 / (1 + r^2/c^2) on the squared residual, its root on the rows.
        rc = r * inv_c
        wgt = inv_s * noise_w / math.sqrt(1.0 + rc * rc)
        res[i] = r * noise_w / math.sqrt(1.0 + rc * rc)
        J[0, i], J[1, i], J[2, i], J[3, i], J[4, i], J[5, i], J[6, i] = (
            j0 * wgt,
            j1 * wgt,
            j2 * wgt,
            j3 * wgt,
            j4 * wgt,
            j5 * wgt,
            j6 * wgt,
        )
    return J, res


@kernel(fastmath={"reassoc", "contract", "nsz"})  # sums that may be reassociated (vectorised), nothing else
def _normal_equations(J: np.ndarray, res: np.ndarray, JtJ: np.ndarray, Jtr: np.ndarray) -> None:
    """J^T J (n, n) and J^T r (n,) of the first n rows of J (>= n, N) and r (N,), written in place."""
    n = JtJ.shape[0]
    for a in range(n):
        acc = 0.0
        for i in range(res.shape[0]):
            acc += J[a, i] * res[i]
        Jtr[a] = acc
        for b in range(a + 1):
            acc = 0.0
            for i in range(res.shape[0]):
                acc += J[a, i] * J[b, i]
            JtJ[a, b] = acc
            JtJ[b, a] = acc


@kernel
def gauss_newton_upright(
    x: np.ndarray,
    f1: np.ndarray,
    f2: np.ndarray,
    iterations: int,
    with_tilt: bool,
    prior_w: np.ndarray,
    noise_w: float,
    robust_c: float,
) -> int:
    """The steps of :func:`refine_upright` on x = (yaw, t (3), d1 (2), d2 (2)), updated in place; the
    number of steps taken; the rows of each step from :func:`_upright_rows`.

    A step is taken only where it lowers the cost (:func:`_upright_cost`), halved up to
    ``_MAX_HALVINGS`` times: with the roll/pitch free, a lateral translation over flat ground and a
    tilt explain the same flow to first order, and a full Gauss-Newton step along that valley
    overshot to the other pose a plane allows (the translation swapped with the ground's normal, a
    tilt of several sigmas), which the cost itself does not prefer: 10-25 cm sideways in a hover
    or a climb over flat ground."""
    n_params = 7 if with_tilt else 3
    steps = 0
    x0 = x.copy()
    cost = _upright_cost(x, f1, f2, with_tilt, prior_w, noise_w, robust_c)
    for it in range(1, iterations + 1):
        t0, t1, t2 = x[1], x[2], x[3]
        T1 = tilt_matrix(x[4], x[5])
        T2 = tilt_matrix(x[6], x[7])
        b10, b11, b12, b20, b21, b22 = _tangent_basis(t0, t1, t2)
        J, res = _upright_rows(x, T1, T2, f1, f2, noise_w if with_tilt else 1.0, robust_c)
        JtJ = np.empty((n_params, n_params))
        Jtr = np.empty(n_params)
        _normal_equations(J, res, JtJ, Jtr)
        if with_tilt:  # the prior rows: prior_w * d, Jacobian diag(prior_w)
            for a in range(4):
                JtJ[3 + a, 3 + a] += prior_w[a] * prior_w[a]
                Jtr[3 + a] += prior_w[a] * prior_w[a] * x[4 + a]
        trace = 0.0
        for a in range(n_params):
            trace += JtJ[a, a]
        for a in range(n_params):
            JtJ[a, a] += 1e-12 * trace
        if not solve_spd(JtJ, Jtr):
            break
        # delta = -Jtr, scaled by alpha until the cost goes down
        x0[:] = x
        alpha = 1.0
        lowered = False
        for _ in range(_MAX_HALVINGS + 1):
            x[0] = x0[0] - alpha * Jtr[0]
            u0 = t0 - alpha * (Jtr[1] * b10 + Jtr[2] * b20)
            u1 = t1 - alpha * (Jtr[1] * b11 + Jtr[2] * b21)
            u2 = t2 - alpha * (Jtr[1] * b12 + Jtr[2] * b22)
            nt = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
            x[1], x[2], x[3] = u0 / nt, u1 / nt, u2 / nt
            if with_tilt:
                for a in range(4):
                    x[4 + a] = x0[4 + a] - alpha * Jtr[3 + a]
            new_cost = _upright_cost(x, f1, f2, with_tilt, prior_w, noise_w, robust_c)
            if new_cost <= cost * (1.0 + 1e-9):  # equal to rounding: a converged step, taken
                lowered = True
                break
            alpha *= 0.5
        if not lowered:
            x[:] = x0  # no step lowers the cost: at the minimum (to rounding)
            break
        cost = new_cost
        steps = it
        biggest = 0.0
        for a in range(n_params):
            biggest = max(biggest, abs(alpha * Jtr[a]))
        if biggest < 1e-8:
            break
    return steps


_MAX_HALVINGS = 6


@kernel
def _upright_cost(
    x: np.ndarray, f1: np.ndarray, f2: np.ndarray, with_tilt: bool, prior_w: np.ndarray, noise_w: float, robust_c: float
) -> float:
    """The cost :func:`gauss_newton_upright` lowers at x: sum over points of the Cauchy loss
    c^2 log(1 + r^2/c^2) of the Sampson residual r (r^2 without ``robust_c``), times ``noise_w``^2
    with the tilts free, plus the prior's sum (prior_w d)^2."""
    T1 = tilt_matrix(x[4], x[5])
    T2 = tilt_matrix(x[6], x[7])
    e = upright_tuple(x[0], x[1], x[2], x[3])
    total = 0.0
    c_sq = robust_c * robust_c
    for i in range(f1.shape[0]):
        p0, p1, p2 = rotate_row(T1, f1, i)
        q0, q1, q2 = rotate_row(T2, f2, i)
        err_sq = sampson_sq_point(e, p0, p1, p2, q0, q1, q2)
        total += c_sq * math.log1p(err_sq / c_sq) if robust_c > 0.0 else err_sq
    if with_tilt:
        total *= noise_w * noise_w
        for a in range(4):
            total += (prior_w[a] * x[4 + a]) ** 2
    return total


@kernel
def ground_similarity(f1: np.ndarray, f2: np.ndarray) -> tuple[bool, complex, complex]:
    """Ground homography by weighted least squares on the level image planes of bearings f1, f2 (N, 3).

    Fits ``u2 = m u1 + tau`` (complex, ``u = (x + i y) / z``) with weights ``z2^2`` so that the
    residuals approximate angles: (True, m, tau) for
    :func:`mavvo.geometry.ground_2pt.homography_from_similarity`, or (False, 0, 0) when fewer than two
    distinct points lie below the horizon.
    """
    sw = 0.0
    m1 = m2 = 0j
    count = 0
    for i in range(f1.shape[0]):
        if f1[i, 2] > 1e-3 and f2[i, 2] > 1e-3:
            w = f2[i, 2] ** 2
            sw += w
            m1 += w * complex(f1[i, 0] / f1[i, 2], f1[i, 1] / f1[i, 2])
            m2 += w * complex(f2[i, 0] / f2[i, 2], f2[i, 1] / f2[i, 2])
            count += 1
    if count < 2:
        return False, 0j, 0j
    m1, m2 = m1 / sw, m2 / sw
    var = 0.0
    cov = 0j
    for i in range(f1.shape[0]):
        if f1[i, 2] > 1e-3 and f2[i, 2] > 1e-3:
            w = f2[i, 2] ** 2 / sw
            d1 = complex(f1[i, 0] / f1[i, 2], f1[i, 1] / f1[i, 2]) - m1
            d2 = complex(f2[i, 0] / f2[i, 2], f2[i, 1] / f2[i, 2]) - m2
            var += w * (d1.real**2 + d1.imag**2)
            cov += w * d1.conjugate() * d2
    if var < 1e-24:
        return False, 0j, 0j
    m = cov / var
    if abs(m) < 1e-12:
        return False, 0j, 0j
    return True, m, m2 - m * m1


def fit_rotation(f1: np.ndarray, f2: np.ndarray) -> np.ndarray | None:
    """Least-squares rotation R (3,3) with ``f2 = R f1`` (Kabsch); None for fewer than 2 distinct rays.

    The full rotation rather than a yaw: when the roll/pitch of the two views carry errors, a camera
    that only turns still shows a small tilt between the level frames. Compiled.
    """
    R = kabsch(np.ascontiguousarray(f1, dtype=np.float64), np.ascontiguousarray(f2, dtype=np.float64))
    return None if np.isnan(R[0, 0]) else R


@kernel
def kabsch(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """:func:`fit_rotation`; NaN where it gives None."""
    if f1.shape[0] < 2:
        return np.full((3, 3), np.nan)
    M = np.zeros((3, 3))  # f2^T f1
    for i in range(f1.shape[0]):
        for r in range(3):
            for c in range(3):
                M[r, c] += f2[i, r] * f1[i, c]
    U, sv, Vt = np.linalg.svd(M)
    if not sv[1] >= 1e-9 * max(sv[0], 1e-300):
        return np.full((3, 3), np.nan)
    D = np.eye(3)
    D[2, 2] = 1.0 if np.linalg.det(U @ Vt) >= 0.0 else -1.0
    return U @ D @ Vt
