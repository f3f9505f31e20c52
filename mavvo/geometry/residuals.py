"""Residuals of two-view models on level-frame bearings, as squared angles (rad^2).

Every function returns the squared distance of a correspondence to the model in the joint space of
both bearings (first order), so residuals of the essential, ground-plane and rotation models can be
compared with one noise sigma (model selection, :mod:`mavvo.estimation.relpose`). With isotropic angular noise
sigma on each bearing, a correct model's residual is about sigma^2 per constraint.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.frames import cross

__all__ = ["upright_design", "sampson_sq_upright", "ground_sq", "rotation_sq"]

# Squared residual returned where a model cannot map a point at all (ground point above the horizon).
UNMAPPABLE_SQ = 1e6


def upright_design(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """(6, 7N) matrix G with ``e @ G`` = (r, E f1, E^T f2 without its redundant row) for all points.

    For upright E given by e = (E13, E21, E22, E23, E31, E32) the epipolar residual r = f2 E f1 and
    the gradients E f1, E^T f2 are all linear in e, so scoring M models is one (M,6) @ (6,7N) product.
    """
    x, y, z = f1.T
    xp, yp, zp = f2.T
    zero = np.zeros_like(x)
    # Row k of each block: coefficient of e_k.
    blocks = [
        [xp * z, yp * x - xp * y, xp * x + yp * y, yp * z, zp * x, zp * y],  # r
        [z, -y, x, zero, zero, zero],  # (E f1)_x = E22 x - E21 y + E13 z
        [zero, x, y, z, zero, zero],  # (E f1)_y = E21 x + E22 y + E23 z
        [zero, zero, zero, zero, x, y],  # (E f1)_z = E31 x + E32 y
        [zero, yp, xp, zero, zp, zero],  # (E^T f2)_x = E22 x' + E21 y' + E31 z'
        [zero, -xp, yp, zero, zero, zp],  # (E^T f2)_y = -E21 x' + E22 y' + E32 z'
        [xp, zero, zero, yp, zero, zero],  # (E^T f2)_z = E13 x' + E23 y'
    ]
    return np.concatenate([np.stack(b) for b in blocks], axis=1)


def sampson_sq_upright(e: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Squared Sampson errors (M, N) of M upright models e (M, 6) on the points behind G (6, 7N).

    On the sphere the gradient of r = f2 E f1 is projected onto the tangent planes of both bearings:
    ``err^2 = r^2 / (|E f1|^2 + |E^T f2|^2 - 2 r^2)``.
    """
    M = e.shape[0]
    V = (e @ G).reshape(M, 7, -1)
    r2 = V[:, 0] ** 2
    den = np.einsum("mkn,mkn->mn", V[:, 1:], V[:, 1:]) - 2.0 * r2
    with np.errstate(divide="ignore", invalid="ignore"):
        out = r2 / den
    return np.where(den > 1e-300, out, np.where(r2 > 0, UNMAPPABLE_SQ, 0.0))


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
