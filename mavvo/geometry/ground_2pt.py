"""The known-gravity ground-plane homography from 2 points (Saurer et al., ACCV 2014), and its pose.

Conventions: see :mod:`mavvo.geometry.essential`.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.frames import rot_z

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
    w = 1.0 / np.abs(m)
    rot = m * w  # exp(i yaw)
    tt = tau * w
    H = np.zeros(np.shape(m) + (3, 3))
    H[..., 0, 0] = H[..., 1, 1] = rot.real
    H[..., 0, 1] = -rot.imag
    H[..., 1, 0] = rot.imag
    H[..., 0, 2] = tt.real
    H[..., 1, 2] = tt.imag
    H[..., 2, 2] = w
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
    n1 = np.linalg.norm(F1, axis=-1)
    n2 = np.linalg.norm(F2, axis=-1)
    valid = np.all((F1[..., 2] > _MIN_GROUND_Z * n1) & (F2[..., 2] > _MIN_GROUND_Z * n2), axis=1)
    with np.errstate(all="ignore"):
        u1 = (F1[..., 0] + 1j * F1[..., 1]) / F1[..., 2]
        u2 = (F2[..., 0] + 1j * F2[..., 1]) / F2[..., 2]
        du1 = u1[:, 0] - u1[:, 1]
        m = (u2[:, 0] - u2[:, 1]) / du1
        tau = u2[:, 0] - m * u1[:, 0]
        valid &= (np.abs(du1) > 1e-12) & (np.abs(m) > 1e-12) & np.isfinite(m) & np.isfinite(tau)
        H = ground_homography_from_similarity(np.where(valid, m, 1.0), np.where(valid, tau, 0.0))
    H[~valid] = np.nan
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
