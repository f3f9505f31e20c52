"""Residuals of two-view models on level-frame bearings, as squared angles (rad^2).

Every function returns the squared distance of a correspondence to the model in the joint space of
both bearings (first order), so residuals of the essential, ground-plane and rotation models can be
compared with one noise sigma (model selection, :mod:`mavvo.estimation.relpose`). With isotropic angular noise
sigma on each bearing, a correct model's residual is about sigma^2 per constraint.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.frames import cross
from mavvo.jit import kernel

__all__ = ["sampson_sq_upright", "ground_sq", "rotation_sq"]

# Squared residual returned where a model cannot map a point at all (ground point above the horizon).
UNMAPPABLE_SQ = 1e6


def sampson_sq_upright(e: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Squared Sampson errors (M, N) of M upright models e (M, 6) on the pairs f1, f2 (N, 3).

    For upright E given by e = (E13, E21, E22, E23, E31, E32) the epipolar residual r = f2 E f1 and
    the gradients E f1, E^T f2; on the sphere the gradient of r is projected onto the tangent planes of
    both bearings: ``err^2 = r^2 / (|E f1|^2 + |E^T f2|^2 - 2 r^2)``. Compiled (the scoring's kernel).
    """
    return _sampson_sq_upright(np.ascontiguousarray(e, dtype=np.float64).reshape(-1, 6), np.ascontiguousarray(f1, dtype=np.float64),
                               np.ascontiguousarray(f2, dtype=np.float64))


@kernel
def _sampson_sq_upright(e: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    M, N = e.shape[0], f1.shape[0]
    out = np.empty((M, N))
    for m in range(M):
        e13, e21, e22, e23, e31, e32 = e[m, 0], e[m, 1], e[m, 2], e[m, 3], e[m, 4], e[m, 5]
        for i in range(N):
            x, y, z = f1[i, 0], f1[i, 1], f1[i, 2]
            xp, yp, zp = f2[i, 0], f2[i, 1], f2[i, 2]
            # E = [[e22, -e21, e13], [e21, e22, e23], [e31, e32, 0]]
            a0 = e22 * x - e21 * y + e13 * z  # E f1
            a1 = e21 * x + e22 * y + e23 * z
            a2 = e31 * x + e32 * y
            b0 = e22 * xp + e21 * yp + e31 * zp  # E^T f2
            b1 = -e21 * xp + e22 * yp + e32 * zp
            b2 = e13 * xp + e23 * yp
            r = xp * a0 + yp * a1 + zp * a2
            r2 = r * r
            den = a0 * a0 + a1 * a1 + a2 * a2 + b0 * b0 + b1 * b1 + b2 * b2 - 2.0 * r2
            if den > 1e-300:
                out[m, i] = r2 / den
            else:
                out[m, i] = UNMAPPABLE_SQ if r2 > 0.0 else 0.0
    return out


def ground_sq(H: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Squared residuals (..., N) of ground homographies H (..., 3, 3) (``x_2 ~ H x_1``, see solvers).

    The transfer angle between f2 and H f1, halved in square because the noise of both bearings
    shares it (exact for a rotation, first order for the small scale changes of a ground homography).
    A point that H sends behind view 2 gets ``UNMAPPABLE_SQ``.
    """
    g = f1 @ np.swapaxes(H, -1, -2)
    n_sq = np.sum(g * g, axis=-1)
    c = cross(g, f2)  # |g x f2|^2 / |g|^2 = sin^2 of the angle, precise also for tiny angles
    sin_sq = np.sum(c * c, axis=-1) / np.where(n_sq > 0, n_sq, 1.0)
    ok = (n_sq > 0) & (np.sum(g * f2, axis=-1) > 0) & (f1[:, 2] > 0)
    return np.where(ok, 0.5 * sin_sq, UNMAPPABLE_SQ)


def rotation_sq(R: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Squared residuals (..., N) of pure rotations ``f2 = R f1``, R (..., 3, 3): half the squared chord."""
    d = f2 - f1 @ np.swapaxes(R, -1, -2)
    return 0.5 * np.sum(d * d, axis=-1)
