"""Real roots of cubic and quartic polynomials, vectorised over a leading batch axis.

The solvers need the real roots of many small polynomials at once; ``numpy.roots`` works on one
polynomial per call and batched companion-matrix eigenvalues cost several microseconds each. These
closed forms (Cardano, Ferrari) work on whole arrays and finish with Newton steps on the original
polynomial, which restores full precision after the cancellation the closed forms suffer from.

Coefficients are given highest degree first, as in ``numpy.roots``.
"""

from __future__ import annotations

import numpy as np

_NEWTON_STEPS = 2


def _largest_real_root_monic_cubic(a2: np.ndarray, a1: np.ndarray, a0: np.ndarray) -> np.ndarray:
    """Largest real root of ``m**3 + a2*m**2 + a1*m + a0`` (arrays of one shape)."""
    p = a1 - a2 * a2 / 3.0
    q = 2.0 * a2**3 / 27.0 - a2 * a1 / 3.0 + a0
    disc = q * q / 4.0 + p**3 / 27.0
    sq = np.sqrt(np.maximum(disc, 0.0))
    one_real = np.cbrt(-q / 2.0 + sq) + np.cbrt(-q / 2.0 - sq)
    # Three real roots: the trigonometric form, whose k = 0 branch is the largest.
    p_neg = np.minimum(p, -1e-300)
    radius = 2.0 * np.sqrt(-p_neg / 3.0)
    cos_arg = np.clip(3.0 * q / (p_neg * radius), -1.0, 1.0)
    three_real = radius * np.cos(np.arccos(cos_arg) / 3.0)
    u = np.where((disc > 0.0) | (p >= 0.0), one_real, three_real)
    return u - a2 / 3.0


def _polish(x: np.ndarray, coeffs: tuple[np.ndarray, ...]) -> np.ndarray:
    """Newton steps on the monic polynomial with lower coefficients ``coeffs`` (each (B,1))."""
    for _ in range(_NEWTON_STEPS):
        f = np.ones_like(x)
        df = np.zeros_like(x)
        for c in coeffs:
            df = df * x + f
            f = f * x + c
        ok = np.abs(df) > 1e-300
        x = x - np.where(ok, f / np.where(ok, df, 1.0), 0.0)
    return x


def quartic_real_roots(coeffs: np.ndarray, rtol: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
    """Real roots of quartics by Ferrari's method.

    Args:
        coeffs: (B,5) real coefficients, highest degree first. The leading coefficient must be
            non-zero where a result is wanted; rows with a zero or non-finite leading coefficient
            come back with no valid root.
        rtol: a quadratic factor whose discriminant is negative by less than ``rtol`` times its
            scale counts as a double root rather than a complex pair.

    Returns:
        roots (B,4) float and valid (B,4) bool. A double root appears twice.
    """
    k = np.asarray(coeffs, dtype=float)
    with np.errstate(all="ignore"):
        lead = k[:, 0]
        a, b, c, d = (k[:, i] / lead for i in range(1, 5))
        # Depressed quartic y**4 + p*y**2 + q*y + r with x = y - a/4.
        p = b - 3.0 * a * a / 8.0
        q = c - a * b / 2.0 + a**3 / 8.0
        r = d - a * c / 4.0 + a * a * b / 16.0 - 3.0 * a**4 / 256.0
        # Resolvent cubic 8m^3 + 8pm^2 + (2p^2 - 8r)m - q^2 = 0 has a root m >= 0 for real input.
        m = np.maximum(_largest_real_root_monic_cubic(p, p * p / 4.0 - r, -q * q / 8.0), 0.0)
        s = np.sqrt(2.0 * m)
        t = np.where(s > 0.0, q / np.where(s > 0.0, 2.0 * s, 1.0), 0.0)
        h = p / 2.0 + m
        d1 = s * s - 4.0 * (h - t)
        d2 = s * s - 4.0 * (h + t)
        scale = s * s + 4.0 * (np.abs(h) + np.abs(t))
        v1 = d1 >= -rtol * scale
        v2 = d2 >= -rtol * scale
        r1 = np.sqrt(np.maximum(d1, 0.0))
        r2 = np.sqrt(np.maximum(d2, 0.0))
        y = np.stack([(-s + r1) / 2.0, (-s - r1) / 2.0, (s + r2) / 2.0, (s - r2) / 2.0], axis=-1)
        x = y - a[:, None] / 4.0
        x = _polish(x, (a[:, None], b[:, None], c[:, None], d[:, None]))
    valid = np.stack([v1, v1, v2, v2], axis=-1) & np.isfinite(x)
    return x, valid


def cubic_real_roots(coeffs: np.ndarray, rtol: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
    """Real roots of cubics.

    Args:
        coeffs: (B,4) real coefficients, highest degree first (leading coefficient non-zero).
        rtol: as in :func:`quartic_real_roots`, for the quadratic left after the first root.

    Returns:
        roots (B,3) float and valid (B,3) bool.
    """
    k = np.asarray(coeffs, dtype=float)
    with np.errstate(all="ignore"):
        lead = k[:, 0]
        a, b, c = (k[:, i] / lead for i in range(1, 4))
        x0 = _largest_real_root_monic_cubic(a, b, c)
        x0 = _polish(x0[:, None], (a[:, None], b[:, None], c[:, None]))[:, 0]
        # Deflate: x^2 + (a + x0) x + (b + x0 (a + x0)).
        p1 = a + x0
        p0 = b + x0 * p1
        disc = p1 * p1 - 4.0 * p0
        ok = disc >= -rtol * (p1 * p1 + 4.0 * np.abs(p0))
        sq = np.sqrt(np.maximum(disc, 0.0))
        x = np.stack([x0, (-p1 + sq) / 2.0, (-p1 - sq) / 2.0], axis=-1)
        x = _polish(x, (a[:, None], b[:, None], c[:, None]))
    valid = np.stack([np.ones_like(ok), ok, ok], axis=-1) & np.isfinite(x)
    return x, valid
