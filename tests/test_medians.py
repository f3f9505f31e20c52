"""The compiled medians against numpy's and the definition of the weighted median."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mavvo.geometry.medians import median, weighted_median


@pytest.mark.parametrize("n", [1, 2, 7, 200, 1001])
def test_the_median_is_numpys(n: int) -> None:
    x = np.random.default_rng(n).normal(size=n)
    assert median(x) == np.median(x)
    assert median(x[::2]) == np.median(x[::2])  # any stride


def test_the_median_of_nothing_or_of_a_nan_is_nan() -> None:
    assert math.isnan(median(np.array([])))
    assert math.isnan(median(np.array([1.0, np.nan, 2.0])))


def test_the_weighted_median_is_where_half_the_weight_is_reached() -> None:
    assert weighted_median(np.array([3.0, 1.0, 2.0]), np.array([1.0, 1.0, 1.0])) == 2.0
    assert weighted_median(np.array([3.0, 1.0, 2.0]), np.array([10.0, 1.0, 1.0])) == 3.0  # the heavy one wins
    assert weighted_median(np.array([1.0, 2.0]), np.array([1.0, 1.0])) == 1.0  # the lower of two halves
    rng = np.random.default_rng(4)
    for _ in range(50):
        x, w = rng.normal(size=31), rng.uniform(0.1, 1.0, 31)
        m = weighted_median(x, w)
        below, above = w[x < m].sum(), w[x > m].sum()
        assert below < 0.5 * w.sum() and above <= 0.5 * w.sum()
