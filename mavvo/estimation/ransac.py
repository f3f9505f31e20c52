"""One LO-RANSAC loop over a small estimator interface (the shape of PoseLib's ``ransac_impl.h``).

An :class:`Estimator` says how many data points it has and how many a sample takes, generates models
from a block of samples, gives the MSAC costs and the squared residuals of models, and refines one
model on its inliers.
:func:`lo_ransac` does the rest, the same way for every model:

1. samples come in blocks (``first_block``, then as many as the stopping rule still needs, at least
   ``min_block``), so a batched solver makes a block's hypotheses in one call;
2. a block's hypotheses are scored first on a fixed random subset of ``preemptive_points`` points and
   only the best ``full_scores_per_block`` on all of them (early rejection);
3. the score is MSAC: ``sum(min(err^2, thr^2))``;
4. a new best model is locally optimised: refined on its inliers, the inliers re-selected with the
   refined model, up to ``lo_rounds`` times while the score improves;
5. sampling stops once an all-inlier sample has been drawn with probability ``confidence``:
   ``k = log(1 - p) / log(1 - w^s)`` with the best inlier ratio w and sample size s (35 samples for the
   3-point solver at 50% outliers and p = 0.99, 146 for a 5-point one: the paper's figures).

Models are numpy arrays whose first axis counts them (a batch), whatever they hold. Seeded: the same
data, options and generator give the same result. Times are per-thread CPU seconds.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mavvo.jit import kernel
from mavvo.options import bounded, check_fields

__all__ = [
    "Estimator",
    "CostsFromResiduals",
    "RansacOptions",
    "RansacStats",
    "RansacResult",
    "lo_ransac",
    "required_iterations",
    "draw_samples",
    "msac_cost",
]


class Estimator(Protocol):
    """What :func:`lo_ransac` needs from a model."""

    sample_size: int
    num_data: int

    def generate(self, samples: np.ndarray) -> np.ndarray:
        """Models (M, ...) from samples (B, sample_size) of data indices; M may be 0 or exceed B."""
        ...

    def costs(self, models: np.ndarray, thr_sq: float, rows: np.ndarray | None = None) -> np.ndarray:
        """MSAC costs (M,) of models (M, ...) on all data, or on ``rows``; inf for a degenerate model.
        The scoring's hot path: an estimator may compute them without the residuals."""
        ...

    def residuals_sq(self, models: np.ndarray) -> np.ndarray:
        """Squared residuals (M, N) of models (M, ...) on all data."""
        ...

    def refine(self, model: np.ndarray, inliers: np.ndarray) -> np.ndarray:
        """Candidate models (K, ...) from one model (1, ...) refitted on the (N,) bool inliers; K may be 0."""
        ...


@dataclass(frozen=True)
class RansacOptions:
    """The loop's settings (see the module docstring). The threshold is the caller's, on the residual
    in the estimator's units (radians for mavvo's bearing residuals)."""

    confidence: float = bounded(0.99, "probability that an all-inlier sample was drawn when sampling stops", gt=0, lt=1)
    max_iterations: int = bounded(200, "most samples per estimate", ge=1, le=100000)
    min_iterations: int = bounded(
        0, "fewest samples per estimate (0: the stopping rule alone decides)", ge=0, le=100000
    )
    first_block: int = bounded(
        64, "samples in the first batch; later batches are sized to what the stopping rule still needs", ge=1, le=100000
    )
    min_block: int = bounded(8, "the smallest later batch", ge=1, le=100000)
    preemptive_points: int = bounded(
        96, "models are first scored on a fixed random subset of this many points", ge=1, le=100000
    )
    full_scores_per_block: int = bounded(
        3, "models of a batch, best on the subset, that are scored on all points", ge=1, le=100000
    )
    local_optimization: bool = bounded(True, "refine each new best model on its inliers while sampling")
    lo_rounds: int = bounded(
        1, "refine / re-select rounds of one local optimisation, while the score improves", ge=1, le=100
    )

    def __post_init__(self) -> None:
        check_fields(self)
        if self.min_iterations < 0 or self.min_iterations > self.max_iterations:
            raise ValueError(
                f"min_iterations: expected 0..max_iterations ({self.max_iterations}), got {self.min_iterations}"
            )


@dataclass(frozen=True)
class RansacStats:
    """How a run went: samples drawn, hypotheses made and fully scored, local optimisations, the best
    inlier ratio and the samples the stopping rule asked for with it; CPU time per phase (seconds)."""

    iterations: int = 0
    models: int = 0
    models_scored: int = 0
    local_optimizations: int = 0
    inlier_ratio: float = 0.0
    required_iterations: int = 0
    time_generate_s: float = 0.0
    time_score_s: float = 0.0
    time_lo_s: float = 0.0


@dataclass(frozen=True)
class RansacResult:
    """The best model (1, ...) or None when no sample gave one, its MSAC cost, its (N,) residuals
    squared and inliers, and the run's statistics."""

    model: np.ndarray | None
    cost: float
    err_sq: np.ndarray
    inliers: np.ndarray
    stats: RansacStats


def required_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> int:
    """Samples needed to draw one all-inlier sample with ``confidence``: log(1-p) / log(1-w^s)."""
    if inlier_ratio <= 0.0:
        return 2**31 - 1
    p_good = inlier_ratio**sample_size
    if p_good >= 1.0:
        return 1
    return int(math.ceil(math.log(1.0 - confidence) / math.log1p(-p_good)))


def draw_samples(rng: np.random.Generator, n: int, count: int, size: int) -> np.ndarray:
    """(count, size) indices into range(n), distinct within each row."""
    idx = rng.integers(0, n, (count, size))
    while True:
        bad = _rows_with_repeats(idx)
        k = int(np.count_nonzero(bad))
        if not k:
            return idx
        idx[bad] = rng.integers(0, n, (k, size))


@kernel
def _rows_with_repeats(idx: np.ndarray) -> np.ndarray:
    """(count,) bool: the rows of idx (count, size) that hold some index twice."""
    out = np.zeros(idx.shape[0], dtype=np.bool_)
    for r in range(idx.shape[0]):
        for a in range(idx.shape[1]):
            for b in range(a):
                if idx[r, a] == idx[r, b]:
                    out[r] = True
    return out


def msac_cost(err_sq: np.ndarray, thr_sq: float) -> np.ndarray:
    """MSAC cost along the last axis: ``sum(min(err^2, thr^2))``."""
    return np.minimum(err_sq, thr_sq).sum(axis=-1)


class CostsFromResiduals:
    """:meth:`Estimator.costs` from the estimator's residuals, for a model without a scoring kernel
    of its own: ``residuals_sq`` on all data, ``residuals_on`` on a subset of rows."""

    def residuals_sq(self, models: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def residuals_on(self, models: np.ndarray, rows: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def costs(self, models: np.ndarray, thr_sq: float, rows: np.ndarray | None = None) -> np.ndarray:
        c = msac_cost(self.residuals_sq(models) if rows is None else self.residuals_on(models, rows), thr_sq)
        c[~np.isfinite(c)] = math.inf  # a degenerate model (NaN) never wins
        return c


class _Best:
    def __init__(self, n: int) -> None:
        self.model: np.ndarray | None = None
        self.cost = math.inf
        self.err_sq = np.full(n, math.inf)
        self.inliers = 0


def lo_ransac(est: Estimator, options: RansacOptions, threshold: float, rng: np.random.Generator) -> RansacResult:
    """The best model of ``est`` by LO-RANSAC (see the module docstring), inliers those with a residual
    under ``threshold``. Needs at least ``est.sample_size`` data points (the caller checks)."""
    opt = options
    n, s = est.num_data, est.sample_size
    thr_sq = threshold**2
    rows = np.sort(rng.choice(n, opt.preemptive_points, replace=False)) if n > opt.preemptive_points else None
    best = _Best(n)
    clock = time.thread_time
    t_gen = t_score = t_lo = 0.0
    models = scored = lo_runs = drawn = 0
    needed = max(opt.min_iterations, 1)
    block = opt.first_block

    def offer(candidates: np.ndarray) -> bool:
        """Score candidates on all points; keep the best if it beats the current one."""
        nonlocal scored
        scored += len(candidates)
        costs = est.costs(candidates, thr_sq)
        k = int(np.argmin(costs))
        if not costs[k] < best.cost:
            return False
        best.model, best.cost = candidates[k : k + 1], float(costs[k])
        best.err_sq = est.residuals_sq(best.model)[0]
        best.inliers = int(np.count_nonzero(best.err_sq < thr_sq))
        return True

    while drawn < min(max(needed, opt.min_iterations), opt.max_iterations):
        count = min(block, opt.max_iterations - drawn)
        idx = draw_samples(rng, n, count, s)
        drawn += count
        t0 = clock()
        hyp = est.generate(idx)
        t1 = clock()
        t_gen += t1 - t0
        models += len(hyp)
        improved = False
        if len(hyp):
            if rows is not None and len(hyp) > opt.full_scores_per_block:
                pre = est.costs(hyp, thr_sq, rows)
                hyp = hyp[np.argsort(pre, kind="stable")[: opt.full_scores_per_block]]
            improved = offer(hyp)
        t2 = clock()
        t_score += t2 - t1
        if improved and opt.local_optimization and best.inliers >= s:  # nothing to refine on fewer
            lo_runs += 1
            for _ in range(opt.lo_rounds):
                assert best.model is not None
                refined = est.refine(best.model, best.err_sq < thr_sq)
                if not len(refined) or not offer(refined):
                    break
            t_lo += clock() - t2
        needed = required_iterations(best.inliers / n, s, opt.confidence)
        block = max(opt.min_block, min(opt.first_block, needed - drawn))
    stats = RansacStats(
        iterations=drawn,
        models=models,
        models_scored=scored,
        local_optimizations=lo_runs,
        inlier_ratio=best.inliers / n,
        required_iterations=min(needed, opt.max_iterations),
        time_generate_s=t_gen,
        time_score_s=t_score,
        time_lo_s=t_lo,
    )
    return RansacResult(best.model, best.cost, best.err_sq, best.err_sq < thr_sq, stats)
