"""Linear algebra of tiny matrices inside compiled kernels, where LAPACK's bindings cost seconds of
compilation each and microseconds of call overhead for a 3x3 problem."""

from __future__ import annotations

import math

import numpy as np

from mavvo.jit import kernel

__all__ = ["solve_spd", "symmetric_eigen"]

_SWEEPS = 30


@kernel
def symmetric_eigen(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (n,), ascending, and eigenvectors (n, n), one per column, of a symmetric A (n, n)
    by cyclic Jacobi rotations (accurate to rounding; n up to a few dozen)."""
    n = A.shape[0]
    a = A.copy()
    v = np.eye(n)
    for _ in range(_SWEEPS):
        off = 0.0
        for p in range(n):
            for q in range(p + 1, n):
                off += a[p, q] * a[p, q]
        scale = 0.0
        for p in range(n):
            scale += a[p, p] * a[p, p]
        if off <= 1e-34 * scale or off == 0.0:
            break
        for p in range(n):
            for q in range(p + 1, n):
                if a[p, q] == 0.0:
                    continue
                # The rotation in the (p, q) plane that zeroes a[p, q]: tan(theta) = t (the smaller root).
                theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    akp, akq = a[k, p], a[k, q]
                    a[k, p], a[k, q] = c * akp - s * akq, s * akp + c * akq
                for k in range(n):
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k], a[q, k] = c * apk - s * aqk, s * apk + c * aqk
                for k in range(n):
                    vkp, vkq = v[k, p], v[k, q]
                    v[k, p], v[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
    # Ascending by insertion (n is tiny): eigenvalue p and column p of v move together.
    w = np.empty(n)
    vecs = np.empty((n, n))
    for p in range(n):
        j = p
        while j > 0 and w[j - 1] > a[p, p]:
            w[j] = w[j - 1]
            for k in range(n):
                vecs[k, j] = vecs[k, j - 1]
            j -= 1
        w[j] = a[p, p]
        for k in range(n):
            vecs[k, j] = v[k, p]
    return w, vecs


@kernel
def solve_spd(A: np.ndarray, b: np.ndarray) -> bool:
    """Solve ``A x = b`` for symmetric positive definite A (n, n) by Cholesky; x overwrites b, A is
    overwritten by its factor. False (b unchanged in meaning) when A is not positive definite."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= A[j, k] * A[j, k]
        if not s > 0.0:
            return False
        A[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s / A[j, j]
    for i in range(n):  # L y = b
        s = b[i]
        for k in range(i):
            s -= A[i, k] * b[k]
        b[i] = s / A[i, i]
    for i in range(n - 1, -1, -1):  # L^T x = y
        s = b[i]
        for k in range(i + 1, n):
            s -= A[k, i] * b[k]
        b[i] = s / A[i, i]
    return True
