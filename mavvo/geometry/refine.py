"""Least-squares refinement of two-view models on level-frame bearings.

- :func:`refine_upright`: Gauss-Newton on the upright manifold (yaw and the unit translation: 3
  degrees of freedom of E, 4 parameters with the scale of t fixed) on Sampson errors; optionally the
  roll and pitch of both views move too, held by a Gaussian prior of the IMU's sigma, and a Cauchy
  loss keeps far points from pulling.
- :func:`fit_ground_similarity`: the ground-plane homography in closed form (weighted least squares).
- :func:`fit_rotation`: the pure rotation (no baseline) in closed form.

Conventions as in :mod:`mavvo.geometry.essential`: ``x_2 = R_2_1 @ x_1 + t_2_1``, ``R_2_1 = Rz(yaw)``. A tilt
correction ``d = (dx, dy)`` of a view is the small rotation ``exp([dx, dy, 0]x)`` applied to that
view's level bearings: ``f_corrected = tilt_rotation(d) @ f``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavvo.geometry.frames import cross, rot_z, skew

__all__ = ["UprightFit", "tilt_rotation", "refine_upright", "fit_ground_similarity", "fit_rotation"]

_EX = np.array([1.0, 0.0, 0.0])
_EY = np.array([0.0, 1.0, 0.0])


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
    w = np.array([d[0], d[1], 0.0])
    th = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * (K @ K)


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal basis of the plane perpendicular to the unit vector t."""
    helper = _EX if abs(t[0]) < 0.9 else _EY
    b1 = cross(t, helper)
    b1 /= np.sqrt(b1 @ b1)
    return np.stack([b1, cross(t, b1)])


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
    yaw = float(yaw_rad)
    t = np.asarray(t_2_1, dtype=float) / np.linalg.norm(t_2_1)
    d1 = np.zeros(2) if tilt1_rad is None else np.asarray(tilt1_rad, dtype=float).copy()
    d2 = np.zeros(2) if tilt2_rad is None else np.asarray(tilt2_rad, dtype=float).copy()
    if with_tilt:
        s1, s2 = (tilt_sigma_rad, tilt_sigma_rad) if np.isscalar(tilt_sigma_rad) else tilt_sigma_rad  # type: ignore[misc]
        prior_w = np.array([1.0 / s1, 1.0 / s1, 1.0 / s2, 1.0 / s2])  # type: ignore[operator]
    n_params = 7 if with_tilt else 3
    steps = 0
    if len(f1) < (3 if not with_tilt else 1):
        return UprightFit(yaw, t, d1, d2, 0)
    for steps in range(1, iterations + 1):
        f1c = f1 @ tilt_rotation(d1).T if with_tilt else f1
        f2c = f2 @ tilt_rotation(d2).T if with_tilt else f2
        Rz = rot_z(yaw)
        E = skew(t) @ Rz
        g = f1c @ Rz.T
        Ef1 = f1c @ E.T  # rows E @ f1 = t x g
        Etf2 = f2c @ E  # rows E^T @ f2
        n = np.einsum("ij,ij->i", f2c, Ef1)  # f2 . (t x g) = t . (g x f2)
        # Sampson scale: the tangent gradients of n at both bearings, held fixed within a step.
        den = np.einsum("ij,ij->i", Ef1, Ef1) + np.einsum("ij,ij->i", Etf2, Etf2) - 2.0 * n * n
        inv_s = 1.0 / np.sqrt(np.maximum(den, 1e-30))
        B = _tangent_basis(t)
        c = cross(g, f2c)
        # d g / d yaw = e_z x g, so d n / d yaw = t . ((e_z x g) x f2) = (t . g) f2_z - t_z (g . f2)
        gf2 = np.einsum("ij,ij->i", g, f2c)
        cols = [(g @ t) * f2c[:, 2] - t[2] * gf2, *(c @ B.T).T]
        if with_tilt:
            q = cross(f2c, t)
            for e in (_EX, _EY):
                cols.append(np.einsum("ij,ij->i", cross(e, f1c) @ Rz.T, q))
            for e in (_EX, _EY):
                cols.append(np.einsum("ij,ij->i", cross(e, f2c), Ef1))
        J = np.stack(cols, axis=1) * inv_s[:, None]
        r = n * inv_s
        if robust_scale_rad is not None:
            # Cauchy IRLS: weight 1 / (1 + r^2/c^2) on the squared residual, its root on the rows.
            sw = 1.0 / np.sqrt(1.0 + (r / robust_scale_rad) ** 2)
            J, r = J * sw[:, None], r * sw
        if with_tilt:
            w = 1.0 / noise_sigma_rad  # type: ignore[operator]
            J = np.concatenate([J * w, np.zeros((4, n_params))])
            r = np.concatenate([r * w, np.concatenate([d1, d2]) * prior_w])
            J[-4:, 3:] = np.diag(prior_w)
        JtJ = J.T @ J
        try:
            delta = -np.linalg.solve(JtJ + 1e-12 * np.trace(JtJ) * np.eye(n_params), J.T @ r)
        except np.linalg.LinAlgError:
            break
        yaw += float(delta[0])
        t = t + delta[1] * B[0] + delta[2] * B[1]
        t /= np.linalg.norm(t)
        if with_tilt:
            d1 = d1 + delta[3:5]
            d2 = d2 + delta[5:7]
        if np.max(np.abs(delta)) < 1e-8:
            break
    yaw = float(np.arctan2(np.sin(yaw), np.cos(yaw)))
    return UprightFit(yaw, t, d1, d2, steps)


def fit_ground_similarity(f1: np.ndarray, f2: np.ndarray) -> tuple[complex, complex] | None:
    """Ground homography by weighted least squares on the level image planes.

    Fits ``u2 = m u1 + tau`` (complex, ``u = (x + i y) / z``) with weights ``z2^2`` so that the
    residuals approximate angles. Returns (m, tau) for
    :func:`mavvo.geometry.ground_2pt.ground_homography_from_similarity`, or None when fewer than two distinct
    points lie below the horizon.
    """
    ok = (f1[:, 2] > 1e-3) & (f2[:, 2] > 1e-3)
    if np.count_nonzero(ok) < 2:
        return None
    a, b = f1[ok], f2[ok]
    u1 = (a[:, 0] + 1j * a[:, 1]) / a[:, 2]
    u2 = (b[:, 0] + 1j * b[:, 1]) / b[:, 2]
    w = b[:, 2] ** 2
    w = w / w.sum()
    m1, m2 = w @ u1, w @ u2
    d1, d2 = u1 - m1, u2 - m2
    var = float(w @ (d1.real**2 + d1.imag**2))
    if var < 1e-24:
        return None
    m = complex(w @ (np.conj(d1) * d2)) / var
    if abs(m) < 1e-12:
        return None
    return m, complex(m2 - m * m1)


def fit_rotation(f1: np.ndarray, f2: np.ndarray) -> np.ndarray | None:
    """Least-squares rotation R (3,3) with ``f2 = R f1`` (Kabsch); None for fewer than 2 distinct rays.

    The full rotation rather than a yaw: when the roll/pitch of the two views carry errors, a camera
    that only turns still shows a small tilt between the level frames.
    """
    if len(f1) < 2:
        return None
    U, sv, Vt = np.linalg.svd(f2.T @ f1)
    if sv[1] < 1e-9 * max(sv[0], 1e-300):
        return None
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt
