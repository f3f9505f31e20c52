"""Residuals of two-view models on level-frame bearings, as squared angles (rad^2).

Every function returns the squared distance of a correspondence to the model in the joint space of
both bearings (first order), so residuals of the essential, ground-plane and rotation models can be
compared with one noise sigma (model selection, :mod:`mavvo.estimation.relpose`). With isotropic angular noise
sigma on each bearing, a correct model's residual is about sigma^2 per constraint.
"""

from __future__ import annotations

import numpy as np

from mavvo.jit import kernel

__all__ = ["sampson_sq_upright", "sampson_msac_upright", "ground_sq", "ground_msac", "rotation_sq"]

# Squared residual returned where a model cannot map a point at all (ground point above the horizon).
UNMAPPABLE_SQ = 1e6


def sampson_sq_upright(e: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Squared Sampson errors (M, N) of M upright models e (M, 6) on the pairs f1, f2 (N, 3).

    For upright E given by e = (E13, E21, E22, E23, E31, E32) the epipolar residual r = f2 E f1 and
    the gradients E f1, E^T f2; on the sphere the gradient of r is projected onto the tangent planes of
    both bearings: ``err^2 = r^2 / (|E f1|^2 + |E^T f2|^2 - 2 r^2)``. Compiled (the sampling scores with :func:`sampson_msac_upright`).
    """
    return sampson_sq_kernel(
        np.ascontiguousarray(e, dtype=np.float64).reshape(-1, 6),
        np.ascontiguousarray(f1, dtype=np.float64),
        np.ascontiguousarray(f2, dtype=np.float64),
    )


@kernel(inline=True)
def sampson_sq_point(
    e: tuple[float, float, float, float, float, float], x: float, y: float, z: float, xp: float, yp: float, zp: float
) -> float:
    """The squared Sampson error of one correspondence (x, y, z), (xp, yp, zp) under the upright e
    (E13, E21, E22, E23, E31, E32); ``UNMAPPABLE_SQ`` where its gradient vanishes but r does not."""
    e13, e21, e22, e23, e31, e32 = e
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
    # A vanishing gradient: r2 / 1e-300 is capped (an angle's square is at most pi^2 otherwise). No
    # branch, so that the scoring loop stays vectorisable.
    return min(r2 / max(den, 1e-300), UNMAPPABLE_SQ)


@kernel
def sampson_sq_kernel(e: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    M, N = e.shape[0], f1.shape[0]
    out = np.empty((M, N))
    for m in range(M):
        em = (e[m, 0], e[m, 1], e[m, 2], e[m, 3], e[m, 4], e[m, 5])
        for i in range(N):
            out[m, i] = sampson_sq_point(em, f1[i, 0], f1[i, 1], f1[i, 2], f2[i, 0], f2[i, 1], f2[i, 2])
    return out


def sampson_msac_upright(e: np.ndarray, f1_xyz: np.ndarray, f2_xyz: np.ndarray, thr_sq: float) -> np.ndarray:
    """MSAC costs (M,), ``sum_i min(err_i^2, thr_sq)``, of M upright models e (M, 6) on the pairs given
    as coordinate rows f1_xyz, f2_xyz (3, N) (x, y and z of every bearing in one contiguous row each).

    The errors of :func:`sampson_sq_upright` without storing them: this is what the sampling scores
    every hypothesis with. The bearings' rows and a sum that may be reassociated let the compiler
    work on several points at once (five times faster than the (M, N) errors and their sum). A model
    with a non-finite entry costs inf.
    """
    return _sampson_msac_kernel(np.ascontiguousarray(e, dtype=np.float64).reshape(-1, 6), f1_xyz, f2_xyz, float(thr_sq))


@kernel(fastmath={"reassoc", "contract", "arcp", "nsz"})  # no assumption on NaN or inf: only reassociation
def _sampson_msac_kernel(e: np.ndarray, f1: np.ndarray, f2: np.ndarray, thr_sq: float) -> np.ndarray:
    M, N = e.shape[0], f1.shape[1]
    x, y, z = f1[0], f1[1], f1[2]
    xp, yp, zp = f2[0], f2[1], f2[2]
    out = np.empty(M)
    for m in range(M):
        e13, e21, e22, e23, e31, e32 = e[m, 0], e[m, 1], e[m, 2], e[m, 3], e[m, 4], e[m, 5]
        finite = True
        for k in range(6):  # comparisons, not np.isfinite: reassociation may fold an x - x test away
            finite = finite and abs(e[m, k]) < np.inf
        if not finite:
            out[m] = np.inf
            continue
        acc = 0.0
        for i in range(N):
            acc += min(sampson_sq_point((e13, e21, e22, e23, e31, e32), x[i], y[i], z[i], xp[i], yp[i], zp[i]), thr_sq)
        out[m] = acc
    return out


def ground_sq(H: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Squared residuals (..., N) of ground homographies H (..., 3, 3) (``x_2 ~ H x_1``, see solvers).

    The transfer angle between f2 and H f1, halved in square because the noise of both bearings
    shares it (exact for a rotation, first order for the small scale changes of a ground homography).
    A point that H sends behind view 2 gets ``UNMAPPABLE_SQ``. Compiled.
    """
    return _per_model(_ground_sq, H, f1, f2)


def rotation_sq(R: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Squared residuals (..., N) of pure rotations ``f2 = R f1``, R (..., 3, 3): half the squared chord. Compiled."""
    return _per_model(_rotation_sq, R, f1, f2)


def _per_model(fn, M: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
    """A (K, N) kernel over models M (..., 3, 3), shaped back to (..., N)."""
    M = np.asarray(M, dtype=np.float64)
    out = fn(
        np.ascontiguousarray(M.reshape(-1, 3, 3)),
        np.ascontiguousarray(f1, dtype=np.float64),
        np.ascontiguousarray(f2, dtype=np.float64),
    )
    return out.reshape(M.shape[:-2] + (out.shape[1],))


@kernel
def _ground_sq(H: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    out = np.empty((H.shape[0], f1.shape[0]))
    for m in range(H.shape[0]):
        for i in range(f1.shape[0]):
            out[m, i] = ground_sq_point(H[m], f1, f2, i)
    return out


@kernel(inline=True)
def ground_sq_point(h: np.ndarray, f1: np.ndarray, f2: np.ndarray, i: int) -> float:
    """:func:`ground_sq` of one homography h (3, 3) on row i of f1, f2 (N, 3)."""
    x, y, z = f1[i, 0], f1[i, 1], f1[i, 2]
    g0 = h[0, 0] * x + h[0, 1] * y + h[0, 2] * z  # g = H f1
    g1 = h[1, 0] * x + h[1, 1] * y + h[1, 2] * z
    g2 = h[2, 0] * x + h[2, 1] * y + h[2, 2] * z
    b0, b1, b2 = f2[i, 0], f2[i, 1], f2[i, 2]
    n_sq = g0 * g0 + g1 * g1 + g2 * g2
    # |g x f2|^2 / |g|^2 = sin^2 of the angle, precise also for tiny angles
    c0, c1, c2 = g1 * b2 - g2 * b1, g2 * b0 - g0 * b2, g0 * b1 - g1 * b0
    if n_sq > 0.0 and g0 * b0 + g1 * b1 + g2 * b2 > 0.0 and z > 0.0:
        return 0.5 * (c0 * c0 + c1 * c1 + c2 * c2) / n_sq
    return UNMAPPABLE_SQ


def ground_msac(H: np.ndarray, f1: np.ndarray, f2: np.ndarray, thr_sq: float) -> np.ndarray:
    """MSAC costs (M,) of ground homographies H (M, 3, 3) on f1, f2 (N, 3): :func:`ground_sq` capped at
    ``thr_sq`` and summed, without storing the errors; inf for a homography with a non-finite entry."""
    return _ground_msac_kernel(np.ascontiguousarray(H, dtype=np.float64).reshape(-1, 3, 3), f1, f2, float(thr_sq))


@kernel
def _ground_msac_kernel(H: np.ndarray, f1: np.ndarray, f2: np.ndarray, thr_sq: float) -> np.ndarray:
    out = np.empty(H.shape[0])
    for m in range(H.shape[0]):
        if not np.all(np.isfinite(H[m])):
            out[m] = np.inf
            continue
        acc = 0.0
        for i in range(f1.shape[0]):
            acc += min(ground_sq_point(H[m], f1, f2, i), thr_sq)
        out[m] = acc
    return out


@kernel
def _rotation_sq(R: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    out = np.empty((R.shape[0], f1.shape[0]))
    for m in range(R.shape[0]):
        for i in range(f1.shape[0]):
            out[m, i] = rotation_sq_point(R[m], f1, f2, i)
    return out


@kernel(inline=True)
def rotation_sq_point(R: np.ndarray, f1: np.ndarray, f2: np.ndarray, i: int) -> float:
    """:func:`rotation_sq` of R (3, 3) on row i of f1, f2 (N, 3): half the squared chord |f2 - R f1|^2."""
    x, y, z = f1[i, 0], f1[i, 1], f1[i, 2]
    d0 = f2[i, 0] - (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z)
    d1 = f2[i, 1] - (R[1, 0] * x + R[1, 1] * y + R[1, 2] * z)
    d2 = f2[i, 2] - (R[2, 0] * x + R[2, 1] * y + R[2, 2] * z)
    return 0.5 * (d0 * d0 + d1 * d1 + d2 * d2)
