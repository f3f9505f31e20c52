"""Medians of the per-frame sizes (tens to a thousand values), compiled: ``numpy.median`` spends
about 18 us per call on its Python layers where the kernel needs 1 us, and the odometry takes several
per frame."""

from __future__ import annotations

import numpy as np

from mavvo.jit import kernel

__all__ = ["median", "weighted_median"]


def median(values: np.ndarray) -> float:
    """The median of a 1-D array (the mean of the middle two for an even count; NaN if any is NaN,
    as ``numpy.median``); NaN for an empty one."""
    a = np.ascontiguousarray(values, dtype=np.float64)
    return float(_median(a)) if a.size else float("nan")


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """The value of x (N,) at which the cumulative weight w (N,), in the order of x, first reaches half
    the total (the lower weighted median); N > 0."""
    return float(_weighted_median(np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(w, dtype=np.float64)))


@kernel
def _median(a: np.ndarray) -> float:
    return np.median(a)


@kernel
def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    order = np.argsort(x)
    half = 0.0
    for v in w:
        half += v
    half *= 0.5
    cum = 0.0
    for k in order:
        cum += w[k]
        if cum >= half:
            return x[k]
    return x[order[-1]]
