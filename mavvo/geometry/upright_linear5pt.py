"""The linear 5-point solver (section 3.1): least squares on the six entries of the upright E, then
the nearest upright essential matrix.

Conventions: see :mod:`mavvo.geometry.essential`.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.essential import MIN_DEGENERACY_RATIO, as_bearing_pair, singular_system
from mavvo.geometry.frames import rot_z, skew
from mavvo.geometry.upright_pose import nearest_upright


def solve_upright_linear5pt(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """The linear 5-point solver (section 3.1): least squares on the six entries, then correction.

    The paper corrects the singular values; on this six-entry structure the equivalent that keeps
    E upright is the nearest ``[t]x Rz(yaw)`` in Frobenius norm (:func:`nearest_upright`).

    Args:
        f1, f2: (N, 3) level-frame bearings, N >= 5.

    Returns:
        (k, 3, 3) with k in {0, 1}: none when the system has rank < 5 (all points on a horizontal
        plane, where it has rank 4 and the solution is a one-parameter family).
    """
    a, b = as_bearing_pair(f1, f2, 5)
    s, vt = singular_system(a, b)
    if s[4] <= MIN_DEGENERACY_RATIO * s[0]:
        return np.zeros((0, 3, 3))
    yaw, t = nearest_upright(vt[5])
    E = skew(t) @ rot_z(yaw)
    return (E / np.linalg.norm(E))[None]
