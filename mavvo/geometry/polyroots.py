"""Real roots of cubic and quartic polynomials: compiled kernels for one polynomial, and batches.

The solvers need the real roots of many small polynomials; ``numpy.roots`` costs several
microseconds per polynomial. These closed forms (Cardano, Ferrari) finish with Newton steps on the
original polynomial, which restores full precision after the cancellation the closed forms suffer
from. :func:`quartic_roots` and :func:`cubic_roots` are the kernels the compiled solvers call;
:func:`quartic_real_roots` and :func:`cubic_real_roots` run them over a batch.

Coefficients are given highest degree first, as in ``numpy.roots``, along ``axis`` of the input;
roots come back along the same axis.
"""

from __future__ import annotations

import math

import numpy as np

from mavvo.jit import kernel

_NEWTON_STEPS = 2
_MAX_NEWTON_STEP = 1e-3


def quartic_real_roots(coeffs: np.ndarray, rtol: float = 1e-10, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Real roots of quartics by Ferrari's method.

    Args:
        coeffs: real coefficients with 5 along ``axis``, highest degree first: (B, 5) by default.
            The leading coefficient must be non-zero where a result is wanted; polynomials with a
            zero or non-finite leading coefficient come back with no valid root.
        rtol: a quadratic factor whose discriminant is negative by less than ``rtol`` times its
            scale counts as a double root rather than a complex pair.
        axis: the coefficient axis; the roots come back along it.

    Returns:
        roots and valid (bool), with 4 along ``axis``: (B, 4) by default. A double root appears twice.
    """
    return _along_axis(coeffs, axis, 4, rtol)


def cubic_real_roots(coeffs: np.ndarray, rtol: float = 1e-10, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Real roots of cubics.

    Args:
        coeffs: real coefficients with 4 along ``axis``, highest degree first (leading coefficient
            non-zero): (B, 4) by default.
        rtol: as in :func:`quartic_real_roots`, for the quadratic left after the first root.
        axis: the coefficient axis; the roots come back along it.

    Returns:
        roots and valid (bool), with 3 along ``axis``: (B, 3) by default.
    """
    return _along_axis(coeffs, axis, 3, rtol)


def _along_axis(coeffs: np.ndarray, axis: int, degree: int, rtol: float) -> tuple[np.ndarray, np.ndarray]:
    k = np.moveaxis(np.asarray(coeffs, dtype=float), axis, -1)
    if k.shape[-1] != degree + 1:
        raise ValueError(f"coeffs: expected {degree + 1} coefficients along axis {axis}, got {k.shape[-1]}")
    rows = np.ascontiguousarray(k.reshape(-1, degree + 1))
    roots, valid = _rows(rows, float(rtol))
    shape = k.shape[:-1] + (degree,)
    return np.moveaxis(roots.reshape(shape), -1, axis), np.moveaxis(valid.reshape(shape), -1, axis)


@kernel
def _rows(rows: np.ndarray, rtol: float) -> tuple[np.ndarray, np.ndarray]:
    """Real roots of each row of coefficients (K, 5) or (K, 4): roots and valid (K, degree)."""
    degree = rows.shape[1] - 1
    roots = np.empty((rows.shape[0], degree))
    valid = np.empty((rows.shape[0], degree), dtype=np.bool_)
    for n in range(rows.shape[0]):
        if degree == 4:
            quartic_roots(rows[n], rtol, roots[n], valid[n])
        else:
            cubic_roots(rows[n], rtol, roots[n], valid[n])
    return roots, valid


@kernel
def _nonneg(x: float) -> float:
    """max(x, 0), NaN kept (math.sqrt then gives NaN rather than raising)."""
    return 0.0 if x < 0.0 else x


@kernel
def _largest_real_root_monic_cubic(a2: float, a1: float, a0: float) -> float:
    """Largest real root of ``m**3 + a2*m**2 + a1*m + a0``."""
    p = a1 - a2 * a2 / 3.0
    q = a2 * (2.0 / 27.0 * a2 * a2 - a1 / 3.0) + a0
    q2, p3 = q * q / 4.0, p * p * p / 27.0
    disc = q2 + p3
    # At disc = 0 a double root joins the single one; Cardano's form then gives the single root even
    # where the double one is larger, so disc within rounding of zero takes the trigonometric form.
    if disc > 1e-12 * (q2 - p3) or p >= 0.0:
        sq = math.sqrt(_nonneg(disc))
        u = np.cbrt(-q / 2.0 + sq) + np.cbrt(-q / 2.0 - sq)
    else:  # three real roots: the trigonometric form, whose k = 0 branch is the largest
        p_neg = min(p, -1e-300)
        radius = 2.0 * math.sqrt(-p_neg / 3.0)
        c = 3.0 * q / (p_neg * radius)
        c = -1.0 if c < -1.0 else (1.0 if c > 1.0 else c)
        u = radius * math.cos(math.acos(c) / 3.0)
    return u - a2 / 3.0


@kernel
def _polish(x: float, low: np.ndarray) -> float:
    """Newton steps at a root x of the monic polynomial with lower coefficients ``low`` (at least two).

    The closed forms are accurate to about 1e-8 even at a double root, so a step longer than
    ``_MAX_NEWTON_STEP`` of the root's scale only means the derivative vanished there (rounding
    noise over rounding noise) and is not taken.
    """
    for _ in range(_NEWTON_STEPS):
        f = x + low[0]
        df = f + x
        f = f * x + low[1]
        for j in range(2, low.shape[0]):
            df = df * x + f
            f = f * x + low[j]
        step = f / df if df != 0.0 else 0.0
        if abs(step) <= _MAX_NEWTON_STEP * (1.0 + abs(x)):
            x = x - step
    return x


@kernel
def quartic_roots(k: np.ndarray, rtol: float, roots: np.ndarray, valid: np.ndarray) -> None:
    """Ferrari on one quartic k (5,), highest degree first: roots (4,) and valid (4,) written."""
    if not (k[0] != 0.0 and math.isfinite(k[0])):
        roots[:] = np.nan
        valid[:] = False
        return
    low = k[1:] / k[0]
    a, b, c, d = low[0], low[1], low[2], low[3]
    # Depressed quartic y**4 + p*y**2 + q*y + r with x = y - a/4.
    aa = a * a
    p = b - 3.0 / 8.0 * aa
    q = c + a * (aa / 8.0 - b / 2.0)
    r = d + a * (a * (b / 16.0 - 3.0 / 256.0 * aa) - c / 4.0)
    # Resolvent cubic 8m^3 + 8pm^2 + (2p^2 - 8r)m - q^2 = 0 has a root m >= 0 for real input.
    m = _nonneg(_largest_real_root_monic_cubic(p, p * p / 4.0 - r, -q * q / 8.0))
    ss = 2.0 * m
    s = math.sqrt(ss)
    t = q / (2.0 * s) if s > 0.0 else 0.0
    h = p / 2.0 + m
    d1 = ss - 4.0 * (h - t)
    d2 = ss - 4.0 * (h + t)
    floor = -rtol * (ss + 4.0 * (abs(h) + abs(t)))
    r1 = math.sqrt(_nonneg(d1))
    r2 = math.sqrt(_nonneg(d2))
    roots[0] = (-s + r1) / 2.0 - a / 4.0
    roots[1] = (-s - r1) / 2.0 - a / 4.0
    roots[2] = (s + r2) / 2.0 - a / 4.0
    roots[3] = (s - r2) / 2.0 - a / 4.0
    for j in range(4):
        roots[j] = _polish(roots[j], low)
        valid[j] = (d1 >= floor if j < 2 else d2 >= floor) and math.isfinite(roots[j])


@kernel
def cubic_roots(k: np.ndarray, rtol: float, roots: np.ndarray, valid: np.ndarray) -> None:
    """Real roots of one cubic k (4,), highest degree first: roots (3,) and valid (3,) written."""
    if not (k[0] != 0.0 and math.isfinite(k[0])):
        roots[:] = np.nan
        valid[:] = False
        return
    low = k[1:] / k[0]
    x0 = _polish(_largest_real_root_monic_cubic(low[0], low[1], low[2]), low)
    # Deflate: x^2 + (a + x0) x + (b + x0 (a + x0)).
    p1 = low[0] + x0
    p0 = low[1] + x0 * p1
    disc = p1 * p1 - 4.0 * p0
    ok = disc >= -rtol * (p1 * p1 + 4.0 * abs(p0))
    sq = math.sqrt(_nonneg(disc))
    roots[0] = x0
    roots[1] = (-p1 + sq) / 2.0
    roots[2] = (-p1 - sq) / 2.0
    for j in range(3):
        roots[j] = _polish(roots[j], low)
        valid[j] = (True if j == 0 else ok) and math.isfinite(roots[j])
