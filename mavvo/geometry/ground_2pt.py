"""The known-gravity ground-plane homography from 2 points (Saurer et al., ACCV 2014), and its pose.

Conventions: see :mod:`mavvo.geometry.essential`.
"""

from __future__ import annotations

import math

import numpy as np

from mavvo.geometry.frames import rot_z
from mavvo.jit import kernel

# --------------------------------------------------------------------------- ground plane, 2-point
#
# With gravity known and every point on the horizontal ground plane ``z_lvl1 = d1`` below view 1,
# ``x_2 = (Rz(yaw) + (t_2_1 / d1) [0 0 1]) x_1``: a homography with 4 degrees of freedom (Saurer,
# Vasseur, Demonceaux and Fraundorfer, ACCV 2014). On the level image planes ``u = (x/z, y/z)`` it is
# a similarity, which in complex numbers reads ``u2 = m u1 + tau`` with ``m = exp(i yaw) / w``,
# ``w = 1 + tz/d1`` and ``tau = (tx + i ty) / (d1 w)``. Two points fix m and tau.

# Bearings closer than this (z of a unit bearing) to the horizon cannot lie on the ground below.
_MIN_GROUND_Z = 1e-3


def ground_homography_from_similarity(m: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """(..., 3, 3) ground homographies ``Rz(yaw) + (t/d1) e_z^T`` from complex similarity parameters (...)."""
    m, tau = np.broadcast_arrays(np.asarray(m, dtype=np.complex128), np.asarray(tau, dtype=np.complex128))
    H = _homographies(np.ascontiguousarray(m).ravel(), np.ascontiguousarray(tau).ravel())
    return H.reshape(m.shape + (3, 3))


@kernel
def homography_from_similarity(m: complex, tau: complex, H: np.ndarray) -> None:
    """H (3, 3) written for one similarity (m, tau)."""
    w = 1.0 / abs(m)
    rot = m * w  # exp(i yaw)
    tt = tau * w
    H[0, 0], H[0, 1], H[0, 2] = rot.real, -rot.imag, tt.real
    H[1, 0], H[1, 1], H[1, 2] = rot.imag, rot.real, tt.imag
    H[2, 0], H[2, 1], H[2, 2] = 0.0, 0.0, w


@kernel
def _homographies(m: np.ndarray, tau: np.ndarray) -> np.ndarray:
    H = np.empty((m.shape[0], 3, 3))
    for k in range(m.shape[0]):
        homography_from_similarity(m[k], tau[k], H[k])
    return H


def solve_ground_2pt_batch(F1: np.ndarray, F2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The known-gravity ground-plane homography from 2 points, for B samples at once.

    Args:
        F1, F2: (B, 2, 3) level-frame bearings; both points of a sample on the ground below the views.

    Returns:
        H (B, 3, 3) with ``x_2 ~ H @ x_1``, ``H = Rz(yaw_2_1) + (t_2_1 / d1) @ [0, 0, 1]`` where d1 is the
        height of view 1 above the plane (NaN where invalid), and valid (B,) bool. At most one
        solution per sample. Invalid: a bearing at or above the horizon, or two coincident points.
    """
    F1 = np.asarray(F1, dtype=float)
    F2 = np.asarray(F2, dtype=float)
    for name, F in (("F1", F1), ("F2", F2)):
        if F.ndim != 3 or F.shape[1:] != (2, 3):
            raise ValueError(f"{name}: expected a (B,2,3) array (B samples of 2 bearings), got shape {F.shape}")
        if not np.all(np.isfinite(F)):
            raise ValueError(f"{name}: bearings must be finite, got NaN or inf")
    if F1.shape != F2.shape:
        raise ValueError(f"F1 and F2: expected the same shape, got {F1.shape} and {F2.shape}")
    return solve_ground_2pt_samples(np.ascontiguousarray(F1), np.ascontiguousarray(F2))


@kernel
def solve_ground_2pt_samples(F1: np.ndarray, F2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`solve_ground_2pt_batch` on finite (B, 2, 3) arrays, compiled."""
    B = F1.shape[0]
    H = np.full((B, 3, 3), np.nan)
    valid = np.zeros(B, dtype=np.bool_)
    for k in range(B):
        ok = True
        u = np.empty(4, dtype=np.complex128)  # u1 of both points, then u2 of both: (x + i y) / z
        for v, F in enumerate((F1, F2)):
            for j in range(2):
                x, y, z = F[k, j, 0], F[k, j, 1], F[k, j, 2]
                if not z > _MIN_GROUND_Z * math.sqrt(x * x + y * y + z * z):
                    ok = False
                else:
                    u[2 * v + j] = complex(x / z, y / z)
        if not ok:
            continue
        du1 = u[0] - u[1]
        if not abs(du1) > 1e-12:
            continue
        m = (u[2] - u[3]) / du1
        tau = u[2] - m * u[0]
        if (
            abs(m) > 1e-12
            and math.isfinite(m.real)
            and math.isfinite(m.imag)
            and math.isfinite(tau.real)
            and math.isfinite(tau.imag)
        ):
            homography_from_similarity(m, tau, H[k])
            valid[k] = True
    return H, valid


def ground_pose_from_homography(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation per height of a ground homography (3, 3) of the form above.

    Returns:
        R_2_1 (3, 3), a rotation about z, and ``t_2_1 / d1`` (3,): the translation divided by the
        height of view 1 above the ground plane, so a rangefinder's height makes it metric.
    """
    H = np.asarray(H, dtype=float)
    if H.shape != (3, 3) or not np.all(np.isfinite(H)):
        raise ValueError(f"H: expected a finite (3,3) matrix, got shape {H.shape}")
    k = np.hypot(H[0, 0], H[1, 0])
    if k < 1e-12:
        raise ValueError("H: expected a ground homography, the rotation block is zero")
    H = H / k
    yaw = float(np.arctan2(H[1, 0], H[0, 0]))
    return rot_z(yaw), np.array([H[0, 2], H[1, 2], H[2, 2] - 1.0])
