"""The 4-point solver (section 3.2): the 2-dim null space of the N x 6 system and the det(E) = 0 cubic.

Conventions: see :mod:`mavvo.geometry.essential`.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.essential import MIN_DEGENERACY_RATIO, as_bearing_pair, essential_from_vector, singular_system
from mavvo.geometry.polyroots import cubic_real_roots


def _homogeneous_real_roots_cubic(c: np.ndarray) -> np.ndarray:
    """Real roots (lam, mu) of c0 lam^3 + c1 lam^2 mu + c2 lam mu^2 + c3 mu^3 = 0 as rows (k, 2).

    Solved in whichever chart keeps the leading coefficient large, so a root at infinity of one
    chart is an ordinary root of the other.
    """
    if abs(c[0]) >= abs(c[3]):
        x, ok = cubic_real_roots(c[None])
        return np.stack([x[0][ok[0]], np.ones(int(ok[0].sum()))], axis=1)
    x, ok = cubic_real_roots(c[None, ::-1])
    return np.stack([np.ones(int(ok[0].sum())), x[0][ok[0]]], axis=1)


def solve_upright_4pt(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """The 4-point solver (section 3.2): 2-dim null space and the det(E) = 0 cubic.

    Args:
        f1, f2: (N, 3) level-frame bearings, N >= 4; with N > 4 the null space is the least-squares one.

    Returns:
        (k, 3, 3) essential matrices with unit Frobenius norm, 0 <= k <= 3; k = 0 where the cubic
        vanishes identically (all points on a horizontal plane: the system has rank 4 there).
    """
    a, b = as_bearing_pair(f1, f2, 4)
    s, vt = singular_system(a, b)
    E1, E2 = essential_from_vector(vt[4]), essential_from_vector(vt[5])
    if s[3] <= MIN_DEGENERACY_RATIO * s[0]:
        return np.zeros((0, 3, 3))  # rank < 4: fewer independent equations than the solver needs
    # det(lam E1 + mu E2) is a binary cubic; sample it at four (lam, mu) and interpolate.
    lm = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, -1.0]])
    dets = np.linalg.det(lm[:, 0, None, None] * E1 + lm[:, 1, None, None] * E2)
    basis = np.stack([lm[:, 0] ** 3, lm[:, 0] ** 2 * lm[:, 1], lm[:, 0] * lm[:, 1] ** 2, lm[:, 1] ** 3], axis=1)
    coeffs = np.linalg.solve(basis, dets)
    if np.abs(coeffs).max() <= MIN_DEGENERACY_RATIO:
        return np.zeros((0, 3, 3))  # det vanishes on the whole pencil: horizontal plane
    roots = _homogeneous_real_roots_cubic(coeffs)
    E = roots[:, 0, None, None] * E1 + roots[:, 1, None, None] * E2
    return E / np.linalg.norm(E, axis=(1, 2), keepdims=True)
