"""Real roots of cubic and quartic polynomials, vectorised over a batch of polynomials.

The solvers need the real roots of many small polynomials at once; ``numpy.roots`` works on one
polynomial per call and batched companion-matrix eigenvalues cost several microseconds each. These
closed forms (Cardano, Ferrari) work on whole arrays and finish with Newton steps on the original
polynomial, which restores full precision after the cancellation the closed forms suffer from.

Coefficients are given highest degree first, as in ``numpy.roots``, along ``axis`` of the input;
roots come back along the same axis. Internally every quantity is one row of B values, so each
step is a single numpy operation over contiguous memory.
"""

from __future__ import annotations

import numpy as np

_NEWTON_STEPS = 2
_MAX_NEWTON_STEP = 1e-3


def _largest_real_root_monic_cubic(a2: np.ndarray, a1: np.ndarray, a0: np.ndarray) -> np.ndarray:
    """Largest real root of ``m**3 + a2*m**2 + a1*m + a0`` (arrays of one shape)."""
    p = a1 - a2 * a2 / 3.0
    # Powers as products: numpy's ``x**3`` of a negative array takes a slow path (about 50x slower).
    q = a2 * (2.0 / 27.0 * a2 * a2 - a1 / 3.0) + a0
    q2, p3 = q * q / 4.0, p * p * p / 27.0
    disc = q2 + p3
    sq = np.sqrt(np.maximum(disc, 0.0))
    one_real = np.cbrt(-q / 2.0 + sq) + np.cbrt(-q / 2.0 - sq)
    # Three real roots: the trigonometric form, whose k = 0 branch is the largest.
    p_neg = np.minimum(p, -1e-300)
    radius = 2.0 * np.sqrt(-p_neg / 3.0)
    cos_arg = np.clip(3.0 * q / (p_neg * radius), -1.0, 1.0)
    three_real = radius * np.cos(np.arccos(cos_arg) / 3.0)
    # At disc = 0 a double root joins the single one; Cardano's form then gives the single root even
    # where the double one is larger, so disc within rounding of zero takes the trigonometric form.
    u = np.where((disc > 1e-12 * (q2 - p3)) | (p >= 0.0), one_real, three_real)
    return u - a2 / 3.0


def _polish(x: np.ndarray, coeffs: tuple[np.ndarray, ...]) -> np.ndarray:
    """Newton steps at roots x (k, B) of the monic polynomial with lower coefficients ``coeffs``
    (each (B,), at least two).

    The closed forms are accurate to about 1e-8 even at a double root, so a step longer than
    ``_MAX_NEWTON_STEP`` of the root's scale only means the derivative vanished there (rounding
    noise over rounding noise) and is not taken.
    """
    for _ in range(_NEWTON_STEPS):
        f = x + coeffs[0]
        df = f + x
        f = f * x + coeffs[1]
        for c in coeffs[2:]:
            df = df * x + f
            f = f * x + c
        step = np.divide(f, df, out=np.zeros_like(f), where=df != 0.0)
        x = x - np.where(np.abs(step) <= _MAX_NEWTON_STEP * (1.0 + np.abs(x)), step, 0.0)
    return x


def _monic(coeffs: np.ndarray, axis: int, degree: int) -> tuple[np.ndarray, ...]:
    k = np.moveaxis(np.asarray(coeffs, dtype=float), axis, 0)
    if k.shape[0] != degree + 1:
        raise ValueError(f"coeffs: expected {degree + 1} coefficients along axis {axis}, got {k.shape[0]}")
    return tuple(k[1:] / k[0])


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
    with np.errstate(all="ignore"):
        a, b, c, d = _monic(coeffs, axis, 4)
        # Depressed quartic y**4 + p*y**2 + q*y + r with x = y - a/4.
        aa = a * a
        p = b - 3.0 / 8.0 * aa
        q = c + a * (aa / 8.0 - b / 2.0)
        r = d + a * (a * (b / 16.0 - 3.0 / 256.0 * aa) - c / 4.0)
        # Resolvent cubic 8m^3 + 8pm^2 + (2p^2 - 8r)m - q^2 = 0 has a root m >= 0 for real input.
        m = np.maximum(_largest_real_root_monic_cubic(p, p * p / 4.0 - r, -q * q / 8.0), 0.0)
        ss = 2.0 * m
        s = np.sqrt(ss)
        t = np.divide(q, 2.0 * s, out=np.zeros_like(q), where=s > 0.0)
        h = p / 2.0 + m
        d1 = ss - 4.0 * (h - t)
        d2 = ss - 4.0 * (h + t)
        floor = -rtol * (ss + 4.0 * (np.abs(h) + np.abs(t)))
        r1 = np.sqrt(np.maximum(d1, 0.0))
        r2 = np.sqrt(np.maximum(d2, 0.0))
        x = np.stack([-s + r1, -s - r1, s + r2, s - r2]) / 2.0 - a / 4.0
        x = _polish(x, (a, b, c, d))
        v1 = d1 >= floor
        v2 = d2 >= floor
    valid = np.stack([v1, v1, v2, v2]) & np.isfinite(x)
    return np.moveaxis(x, 0, axis), np.moveaxis(valid, 0, axis)


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
    with np.errstate(all="ignore"):
        a, b, c = _monic(coeffs, axis, 3)
        x0 = _polish(_largest_real_root_monic_cubic(a, b, c), (a, b, c))
        # Deflate: x^2 + (a + x0) x + (b + x0 (a + x0)).
        p1 = a + x0
        p0 = b + x0 * p1
        disc = p1 * p1 - 4.0 * p0
        ok = disc >= -rtol * (p1 * p1 + 4.0 * np.abs(p0))
        sq = np.sqrt(np.maximum(disc, 0.0))
        x = _polish(np.stack([x0, (-p1 + sq) / 2.0, (-p1 - sq) / 2.0]), (a, b, c))
    valid = np.stack([np.ones_like(ok), ok, ok]) & np.isfinite(x)
    return np.moveaxis(x, 0, axis), np.moveaxis(valid, 0, axis)
