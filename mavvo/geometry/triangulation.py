"""Triangulation of matched bearings for a known relative pose, compiled (every frame triangulates
its inliers for the scale)."""

from __future__ import annotations

import math

import numpy as np

from mavvo.geometry.refine import rotate_row
from mavvo.jit import kernel

__all__ = ["triangulate_midpoints"]


@kernel
def triangulate_midpoints(
    f1: np.ndarray, f2: np.ndarray, R: np.ndarray, t: np.ndarray, min_parallax_rad: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Midpoints of the closest approach of the rays of unit bearings f1, f2 (N, 3) (C-contiguous
    float64) for the pose ``x_2 = R x_1 + t`` (R (3, 3), t (3,)): depths (N,) along f1 and along f2
    in units of |t|, the rotation-compensated angle between the rays (N,) (rad), and valid (N,) where
    that angle is at least ``min_parallax_rad`` and the point lies in front of both views."""
    n = f1.shape[0]
    lam1, lam2, parallax = np.empty(n), np.empty(n), np.empty(n)
    valid = np.empty(n, dtype=np.bool_)
    for i in range(n):
        a0, a1, a2 = rotate_row(R, f1, i)  # view 1's ray in view 2's orientation
        c = a0 * f2[i, 0] + a1 * f2[i, 1] + a2 * f2[i, 2]
        parallax[i] = math.acos(min(max(c, -1.0), 1.0))
        at = a0 * t[0] + a1 * t[1] + a2 * t[2]
        ft = f2[i, 0] * t[0] + f2[i, 1] * t[1] + f2[i, 2] * t[2]
        # the rays x = t + lam1 a and x = lam2 f2 closest where lam1 (1 - c^2) = c ft - at, lam2 = ft + c lam1
        lam1[i] = (c * ft - at) / max(1.0 - c * c, 1e-300)
        lam2[i] = ft + c * lam1[i]
        valid[i] = parallax[i] >= min_parallax_rad and lam1[i] > 0.0 and lam2[i] > 0.0
    return lam1, lam2, parallax, valid
