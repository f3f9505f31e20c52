"""Batched real roots of cubics and quartics against numpy.roots."""

import numpy as np

from mavvo.geometry.polyroots import cubic_real_roots, quartic_real_roots


def _real_roots(coeffs: np.ndarray) -> np.ndarray:
    r = np.roots(coeffs)
    return np.sort(r.real[np.abs(r.imag) < 1e-7])


def _mismatches(x: np.ndarray, valid: np.ndarray, coeffs: np.ndarray) -> int:
    """Polynomials whose valid roots differ from numpy's real roots (count or value, 1e-7)."""
    bad = 0
    for xi, vi, ki in zip(x, valid, coeffs):
        got, ref = np.sort(xi[vi]), _real_roots(ki)
        bad += len(got) != len(ref) or not np.allclose(got, ref, atol=1e-7)
    return bad


def test_quartic_with_four_real_roots() -> None:
    rng = np.random.default_rng(1)
    roots = rng.normal(size=(5000, 4))
    x, valid = quartic_real_roots(np.array([np.poly(r) for r in roots]))
    assert valid.all()
    np.testing.assert_allclose(np.sort(x, axis=1), np.sort(roots, axis=1), atol=1e-8)


def test_quartic_random_coefficients_match_numpy() -> None:
    rng = np.random.default_rng(2)
    k = rng.normal(size=(5000, 5))
    x, valid = quartic_real_roots(k)
    assert _mismatches(x, valid, k) <= 2  # pairs that touch the real axis within rounding may go either way


def test_quartic_double_root_is_found() -> None:
    x, valid = quartic_real_roots(np.array([np.poly([0.5, 0.5, -2.0, 3.0])]))
    got = np.sort(x[0][valid[0]])
    np.testing.assert_allclose(got, [-2.0, 0.5, 0.5, 3.0], atol=1e-7)


def test_quartic_zero_leading_coefficient_gives_no_root() -> None:
    _, valid = quartic_real_roots(np.array([[0.0, 1.0, 2.0, 3.0, 4.0]]))
    assert not valid.any()


def test_cubic_matches_numpy() -> None:
    rng = np.random.default_rng(3)
    k = rng.normal(size=(5000, 4))
    x, valid = cubic_real_roots(k)
    assert _mismatches(x, valid, k) <= 2
    assert valid[:, 0].all()  # a real cubic always has a real root
