"""The tracks of an image pair that end off the pair's consensus motion, compiled: the frontend asks on
every pair, and three small least-squares fits through numpy cost mostly its per-call overhead
(docs/odometry.md, "Repeated patterns")."""

from __future__ import annotations

import numpy as np

from mavvo.geometry.small_linalg import solve_spd
from mavvo.jit import kernel

__all__ = ["off_affine_consensus"]

_REFITS = 2
_MIN_BAND_PX = 2.0  # the refits keep tracks within max(3 x median residual, this)


def off_affine_consensus(uv0: np.ndarray, uv1: np.ndarray, keep: np.ndarray, max_px: float) -> np.ndarray:
    """(N,) bool: the tracks ending more than ``max_px`` from the pair's consensus motion.

    uv0, uv1: (N,2) pixel positions in the earlier and later image; keep: (N,) bool, the tracks to fit
    to (at least 3, not all on a line). The consensus is an affine map uv1 = A [uv0; 1] fitted by least
    squares, twice refitted to the tracks within max(3 x median residual, 2 px) of the last fit: a
    median keeps the fit on the majority when a quarter of the tracks slipped one period of a repeated
    pattern either way (a third slipped the same way pulls it too far; docs/odometry.md, "Repeated
    patterns"). Between two frames a plane's homography is affine to well under a pixel. A degenerate
    fit (the tracks on a line) marks nothing.
    """
    out = np.zeros(len(uv0), dtype=np.bool_)
    _off(
        np.ascontiguousarray(uv0, dtype=np.float64),
        np.ascontiguousarray(uv1, dtype=np.float64),
        np.ascontiguousarray(keep, dtype=np.bool_),
        float(max_px),
        out,
    )
    return out


@kernel
def _fit(uv0: np.ndarray, uv1: np.ndarray, use: np.ndarray, c0: float, c1: float, a: np.ndarray) -> bool:
    """Least-squares affine map into a (3,2): uv1 = [u0 - c0, v0 - c1, 1] a, over the tracks in use,
    from the normal equations M a = B (M = sum x x', B = sum x y'; centred pixels keep M well
    conditioned); False when M is not positive definite (the tracks on a line)."""
    m = np.zeros((3, 3))
    b = np.zeros((3, 2))
    x = np.empty(3)
    for i in range(uv0.shape[0]):
        if not use[i]:
            continue
        x[0], x[1], x[2] = uv0[i, 0] - c0, uv0[i, 1] - c1, 1.0
        for j in range(3):
            for k in range(3):
                m[j, k] += x[j] * x[k]
            b[j, 0] += x[j] * uv1[i, 0]
            b[j, 1] += x[j] * uv1[i, 1]
    for col in range(2):  # a = M^-1 B, one column at a time (the solve overwrites M by its factor)
        mc = m.copy()
        a[:, col] = b[:, col]
        if not solve_spd(mc, a[:, col]):
            return False
    return True


@kernel
def _residuals(uv0: np.ndarray, uv1: np.ndarray, c0: float, c1: float, a: np.ndarray, r: np.ndarray) -> None:
    for i in range(uv0.shape[0]):
        x0, x1 = uv0[i, 0] - c0, uv0[i, 1] - c1
        du = x0 * a[0, 0] + x1 * a[1, 0] + a[2, 0] - uv1[i, 0]
        dv = x0 * a[0, 1] + x1 * a[1, 1] + a[2, 1] - uv1[i, 1]
        r[i] = np.sqrt(du * du + dv * dv)


@kernel
def _off(uv0: np.ndarray, uv1: np.ndarray, keep: np.ndarray, max_px: float, out: np.ndarray) -> None:
    n = uv0.shape[0]
    n_keep = 0
    c0 = 0.0
    c1 = 0.0
    for i in range(n):
        if keep[i]:
            n_keep += 1
            c0 += uv0[i, 0]
            c1 += uv0[i, 1]
    if n_keep < 3:
        return
    c0 /= n_keep
    c1 /= n_keep
    a = np.zeros((3, 2))
    r = np.empty(n)
    if not _fit(uv0, uv1, keep, c0, c1, a):
        return
    use = np.empty(n, dtype=np.bool_)
    kept_r = np.empty(n_keep)
    for _ in range(_REFITS):
        _residuals(uv0, uv1, c0, c1, a, r)
        k = 0
        for i in range(n):
            if keep[i]:
                kept_r[k] = r[i]
                k += 1
        band = max(3.0 * np.median(kept_r), _MIN_BAND_PX)
        for i in range(n):
            use[i] = keep[i] and r[i] <= band
        if not _fit(uv0, uv1, use, c0, c1, a):
            return
    _residuals(uv0, uv1, c0, c1, a, r)
    for i in range(n):
        out[i] = r[i] > max_px
