"""Pose from an upright essential matrix: yaw and translation direction, chirality.

Conventions: see :mod:`mavvo.geometry.essential`.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.essential import as_bearing_pair, essential_to_vector
from mavvo.geometry.frames import rot_z

# --------------------------------------------------------------------------- decomposition


def _translation_for_yaw(e: np.ndarray, yaw: float) -> np.ndarray:
    """Least-squares t with ``[t]x Rz(yaw)`` closest to e (6,): the columns are orthogonal."""
    c, s = np.cos(yaw), np.sin(yaw)
    e13, e21, e22, e23, e31, e32 = e
    return np.array([(-e23 + s * e31 + c * e32) / 2.0, (e13 - c * e31 + s * e32) / 2.0, c * e21 - s * e22])


def _yaw_candidates(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stationary yaws of the fit of ``[t]x Rz(yaw)`` to e, and the fitted energy at each.

    For fixed yaw the best t (Frobenius norm on E) is linear least squares, leaving the energy
    f(yaw) = K + P sin + Q cos + U cos 2yaw + V sin 2yaw to maximise; with u = tan(yaw/2) its
    stationary points are the roots of a quartic (plus yaw = pi, the quartic's root at infinity).
    """
    e13, e21, e22, e23, e31, e32 = e
    P = e13 * e32 - e23 * e31
    Q = -(e23 * e32 + e13 * e31)
    U = e21**2 - e22**2  # E21 and E22 each stand twice in E, hence twice the weight
    V = -2.0 * e21 * e22
    quartic = np.array([2 * V - P, 8 * U - 2 * Q, -12 * V, -2 * Q - 8 * U, P + 2 * V])
    roots = np.roots(quartic) if np.any(quartic != 0) else np.zeros(0)
    u = roots.real[np.abs(roots.imag) <= 1e-8 * (1.0 + np.abs(roots))]
    yaws = np.concatenate([2.0 * np.arctan(u), [np.pi]])
    for _ in range(2):  # Newton on f'(yaw) = 0: the quartic's roots carry only ~1e-8 precision
        d1 = P * np.cos(yaws) - Q * np.sin(yaws) - 2 * U * np.sin(2 * yaws) + 2 * V * np.cos(2 * yaws)
        d2 = -P * np.sin(yaws) - Q * np.cos(yaws) - 4 * U * np.cos(2 * yaws) - 4 * V * np.sin(2 * yaws)
        yaws = yaws - np.where(np.abs(d2) > 1e-12, d1 / np.where(np.abs(d2) > 1e-12, d2, 1.0), 0.0)
    energy = P * np.sin(yaws) + Q * np.cos(yaws) + U * np.cos(2 * yaws) + V * np.sin(2 * yaws)
    return yaws, energy


def nearest_upright(e: np.ndarray) -> tuple[float, np.ndarray]:
    """Yaw and t of the upright essential matrix nearest to e (6,) in Frobenius norm."""
    yaws, energy = _yaw_candidates(e)
    yaw = float(yaws[int(np.argmax(energy))])
    return yaw, _translation_for_yaw(e, yaw)


def _count_in_front(R: np.ndarray, t: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> int:
    """Points whose midpoint triangulation lies in front of both views."""
    a = f1 @ R.T
    aa = np.sum(a * a, axis=1)
    bb = np.sum(f2 * f2, axis=1)
    ab = np.sum(a * f2, axis=1)
    at = a @ t
    bt = f2 @ t
    det = aa * bb - ab * ab
    ok = det > 1e-12
    lam1 = (-at * bb + ab * bt) / np.where(ok, det, 1.0)
    lam2 = (aa * bt - ab * at) / np.where(ok, det, 1.0)
    return int(np.sum(ok & (lam1 > 0) & (lam2 > 0)))


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
    e = e / np.linalg.norm(e)
    yaws, energy = _yaw_candidates(e)
    keep = energy >= energy.max() - 1e-9 * (1.0 + abs(energy.max()))
    best: tuple[int, float, np.ndarray, np.ndarray] | None = None
    for yaw, en in zip(yaws[keep], energy[keep]):
        t = _translation_for_yaw(e, float(yaw))
        t = t / np.linalg.norm(t)
        R = rot_z(float(yaw))
        for sign in (1.0, -1.0):
            score = (_count_in_front(R, sign * t, a, b), float(en))
            if best is None or score > best[:2]:
                best = (score[0], score[1], R, sign * t)
    assert best is not None
    return best[2], best[3]


