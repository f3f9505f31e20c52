"""Pose from an upright essential matrix: yaw and translation direction, chirality.

Conventions: see :mod:`mavvo.geometry.essential`.
"""

from __future__ import annotations

import math

import numpy as np

from mavvo.geometry.essential import as_bearing_pair, essential_to_vector
from mavvo.geometry.frames import rot_z
from mavvo.jit import kernel

# --------------------------------------------------------------------------- decomposition


@kernel
def _translation_for_yaw(e: np.ndarray, yaw: float) -> np.ndarray:
    """Least-squares t with ``[t]x Rz(yaw)`` closest to e (6,): the columns are orthogonal."""
    c, s = math.cos(yaw), math.sin(yaw)
    e13, e21, e22, e23, e31, e32 = e[0], e[1], e[2], e[3], e[4], e[5]
    return np.array([(-e23 + s * e31 + c * e32) / 2.0, (e13 - c * e31 + s * e32) / 2.0, c * e21 - s * e22])


@kernel
def _yaw_candidates(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stationary yaws of the fit of ``[t]x Rz(yaw)`` to e, and the fitted energy at each.

    For fixed yaw the best t (Frobenius norm on E) is linear least squares, leaving the energy
    f(yaw) = K + P sin + Q cos + U cos 2yaw + V sin 2yaw to maximise; with u = tan(yaw/2) its
    stationary points are the roots of a quartic (plus yaw = pi, the quartic's root at infinity).
    """
    e13, e21, e22, e23, e31, e32 = e[0], e[1], e[2], e[3], e[4], e[5]
    P = e13 * e32 - e23 * e31
    Q = -(e23 * e32 + e13 * e31)
    U = e21**2 - e22**2  # E21 and E22 each stand twice in E, hence twice the weight
    V = -2.0 * e21 * e22
    quartic = np.array([2 * V - P, 8 * U - 2 * Q, -12 * V, -2 * Q - 8 * U, P + 2 * V])
    yaws = [math.pi]
    if np.any(quartic != 0.0):
        for root in np.roots(quartic.astype(np.complex128)):
            if abs(root.imag) <= 1e-8 * (1.0 + abs(root)):
                yaws.append(2.0 * math.atan(root.real))
    out = np.array(yaws)
    energy = np.empty(len(yaws))
    for k in range(len(yaws)):
        y = out[k]
        # Newton on f'(yaw) = 0 to convergence: the quartic's roots carry only ~1e-8 precision, and the
        # root at infinity starts at pi, up to a few tenths of a radian from its stationary point; two
        # fixed steps left that one 1e-9 off, which picks it over the converged twin by rounding alone.
        for _ in range(8):
            d1 = P * math.cos(y) - Q * math.sin(y) - 2 * U * math.sin(2 * y) + 2 * V * math.cos(2 * y)
            d2 = -P * math.sin(y) - Q * math.cos(y) - 4 * U * math.cos(2 * y) - 4 * V * math.sin(2 * y)
            if abs(d2) <= 1e-12:
                break
            step = d1 / d2
            y -= step
            if abs(step) <= 1e-15:
                break
        out[k] = y
        energy[k] = P * math.sin(y) + Q * math.cos(y) + U * math.cos(2 * y) + V * math.sin(2 * y)
    return out, energy


def nearest_upright(e: np.ndarray) -> tuple[float, np.ndarray]:
    """Yaw and t of the upright essential matrix nearest to e (6,) in Frobenius norm."""
    e = np.ascontiguousarray(e, dtype=np.float64)
    yaws, energy = _yaw_candidates(e)
    yaw = float(yaws[int(np.argmax(energy))])
    return yaw, _translation_for_yaw(e, yaw)


@kernel(inline=True)
def midpoint_depths(
    c: float,
    s: float,
    t0: float,
    t1: float,
    t2: float,
    x1: float,
    y1: float,
    z1: float,
    x2: float,
    y2: float,
    z2: float,
) -> tuple[float, float, float]:
    """The midpoint triangulation of f1 = (x1, y1, z1), f2 = (x2, y2, z2) for R = Rz(yaw) (c, s its
    cosine and sine) and t: its depths along f1 and along f2, each times ``det``, and ``det`` =
    sin^2 of the parallax times |f1|^2 |f2|^2."""
    a0, a1, a2 = c * x1 - s * y1, s * x1 + c * y1, z1
    aa = a0 * a0 + a1 * a1 + a2 * a2
    bb = x2 * x2 + y2 * y2 + z2 * z2
    ab = a0 * x2 + a1 * y2 + a2 * z2
    at = a0 * t0 + a1 * t1 + a2 * t2
    bt = x2 * t0 + y2 * t1 + z2 * t2
    return -at * bb + ab * bt, aa * bt - ab * at, aa * bb - ab * ab


@kernel(inline=True)
def _row_depths(
    c: float, s: float, t: np.ndarray, f1: np.ndarray, f2: np.ndarray, i: int
) -> tuple[float, float, float]:
    """:func:`midpoint_depths` of row i of f1, f2 (N, 3)."""
    return midpoint_depths(c, s, t[0], t[1], t[2], f1[i, 0], f1[i, 1], f1[i, 2], f2[i, 0], f2[i, 1], f2[i, 2])


@kernel
def _count_in_front(yaw: float, t: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> int:
    """Points whose midpoint triangulation lies in front of both views (R = Rz(yaw))."""
    c, s = math.cos(yaw), math.sin(yaw)
    count = 0
    for i in range(f1.shape[0]):
        d1, d2, det = _row_depths(c, s, t, f1, f2, i)
        if det > 1e-12 and d1 > 0.0 and d2 > 0.0:
            count += 1
    return count


@kernel
def behind_upright(yaw: float, t: np.ndarray, f1: np.ndarray, f2: np.ndarray, min_parallax_rad: float) -> np.ndarray:
    """(N,) bool: points with more parallax than ``min_parallax_rad`` whose midpoint triangulation for
    R = Rz(yaw) and t lies behind either view (unit bearings). With less parallax the side is noise."""
    c, s = math.cos(yaw), math.sin(yaw)
    min_det = math.sin(min_parallax_rad) ** 2
    out = np.zeros(f1.shape[0], dtype=np.bool_)
    for i in range(f1.shape[0]):
        out[i] = point_behind(
            c, s, t[0], t[1], t[2], f1[i, 0], f1[i, 1], f1[i, 2], f2[i, 0], f2[i, 1], f2[i, 2], min_det
        )
    return out


@kernel(inline=True)
def point_behind(
    c: float,
    s: float,
    t0: float,
    t1: float,
    t2: float,
    x1: float,
    y1: float,
    z1: float,
    x2: float,
    y2: float,
    z2: float,
    min_det: float,
) -> bool:
    """:func:`behind_upright` of one point, ``min_det`` the sine of the least parallax squared."""
    d1, d2, det = midpoint_depths(c, s, t0, t1, t2, x1, y1, z1, x2, y2, z2)
    return det > min_det and (d1 <= 0.0 or d2 <= 0.0)


@kernel
def upright_pose_kernel(e: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> tuple[float, np.ndarray]:
    """:func:`upright_pose_from_essential` on a unit upright vector e (6,) and unit bearings (N, 3):
    (yaw, unit t)."""
    yaws, energy = _yaw_candidates(e)
    top = energy.max()
    best_count, best_energy, best_yaw, best_t = -1, -np.inf, 0.0, np.zeros(3)
    for k in range(len(yaws)):
        if energy[k] < top - 1e-9 * (1.0 + abs(top)):
            continue
        t = _translation_for_yaw(e, yaws[k])
        t = t / math.sqrt(t[0] ** 2 + t[1] ** 2 + t[2] ** 2)
        for sign in (1.0, -1.0):
            count = _count_in_front(yaws[k], sign * t, f1, f2)
            if count > best_count or (count == best_count and energy[k] > best_energy):
                best_count, best_energy, best_yaw, best_t = count, energy[k], yaws[k], sign * t
    return best_yaw, best_t


def upright_pose_from_essential(E: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decompose an upright essential matrix into the pose that puts the points in front of both views.

    E is first fitted by the nearest ``[t]x Rz(yaw)`` (exact for a solver's output). When t is
    vertical the twisted pair (yaw + pi, -t) is upright too and cheirality decides between them.

    Args:
        E: (3, 3) essential matrix with the upright structure (any scale).
        f1, f2: (N, 3) level-frame bearings used for the cheirality test, N >= 1.

    Returns:
        R_2_1 (3, 3), a rotation about z, and t_2_1 (3,), a unit vector.
    """
    E = np.asarray(E, dtype=float)
    if E.shape != (3, 3) or not np.all(np.isfinite(E)):
        raise ValueError(f"E: expected a finite (3,3) matrix, got shape {E.shape}")
    a, b = as_bearing_pair(f1, f2, 1)
    e = essential_to_vector(E)
    if np.linalg.norm(e) < 1e-300:
        raise ValueError("E: expected a non-zero essential matrix")
    yaw, t = upright_pose_kernel(e / np.linalg.norm(e), a, b)
    return rot_z(yaw), t
