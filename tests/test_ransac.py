"""The one LO-RANSAC loop (mavvo.estimation.ransac) on a toy estimator whose answer is known: a
location on a line from s-point samples, half the data gross outliers."""

from __future__ import annotations

import numpy as np
import pytest

from mavvo.estimation.ransac import CostsFromResiduals, RansacOptions, lo_ransac, required_iterations


class Location(CostsFromResiduals):
    """Model: one number (M, 1); a sample's model is its mean; refinement: the inliers' mean."""

    def __init__(self, x: np.ndarray, sample_size: int) -> None:
        self.x = x
        self.num_data = len(x)
        self.sample_size = sample_size
        self.refined = 0

    def generate(self, samples: np.ndarray) -> np.ndarray:
        return self.x[samples].mean(axis=1, keepdims=True)

    def residuals_sq(self, models: np.ndarray) -> np.ndarray:
        return (self.x[None, :] - models[:, :1]) ** 2

    def residuals_on(self, models: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return (self.x[rows][None, :] - models[:, :1]) ** 2

    def refine(self, model: np.ndarray, inliers: np.ndarray) -> np.ndarray:
        assert inliers.any(), "refine is called only with inliers"
        self.refined += 1
        return self.x[inliers].mean(keepdims=True)[None]


def _data(n: int, outliers: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = int(round(n * outliers))
    return np.concatenate([5.0 + 0.01 * rng.standard_normal(n - k), rng.uniform(100.0, 1000.0, k)])


@pytest.mark.parametrize("sample_size, paper", [(3, 35), (5, 146)])
def test_sampling_stops_at_the_papers_counts_at_half_outliers(sample_size, paper):
    """Section 5 of the paper: 35 samples for 3 points, 146 for 5, at 50% outliers and p = 0.99."""
    est = Location(_data(2000, 0.5, seed=1), sample_size)
    opt = RansacOptions(first_block=1, min_block=1, max_iterations=10000)
    res = lo_ransac(est, opt, 0.05, np.random.default_rng(2))
    assert res.stats.inlier_ratio == pytest.approx(0.5)
    assert res.stats.iterations == required_iterations(0.5, sample_size, 0.99) == paper
    assert res.model[0, 0] == pytest.approx(5.0, abs=2e-3) and np.count_nonzero(res.inliers) == 1000


def test_local_optimisation_refines_the_best_and_the_same_seed_gives_the_same_answer():
    est = Location(_data(500, 0.3, seed=3), 3)
    opt = RansacOptions(lo_rounds=3)
    a = lo_ransac(est, opt, 0.05, np.random.default_rng(7))
    assert a.stats.local_optimizations >= 1 and est.refined >= 1
    inl = est.x[a.inliers]
    assert a.model[0, 0] == pytest.approx(inl.mean(), abs=1e-12)  # the refined model won
    b = lo_ransac(Location(est.x, 3), opt, 0.05, np.random.default_rng(7))
    assert b.model[0, 0] == a.model[0, 0]
    assert (b.stats.iterations, b.stats.models, b.stats.models_scored) == (
        a.stats.iterations,
        a.stats.models,
        a.stats.models_scored,
    )


def test_early_rejection_scores_only_the_best_of_a_block_on_all_points():
    est = Location(_data(1000, 0.5, seed=4), 3)
    res = lo_ransac(
        est,
        RansacOptions(preemptive_points=50, full_scores_per_block=2, local_optimization=False),
        0.05,
        np.random.default_rng(1),
    )
    # One hypothesis per sample; of each block only 2 are scored on all 1000 points. The blocks: 64 samples,
    # then what the stopping rule still needs (at least min_block = 8): at most 1 + ceil((iterations - 64) / 8).
    blocks = 1 + max(0, -(-(res.stats.iterations - 64) // 8))
    assert res.stats.models == res.stats.iterations and 2 <= res.stats.models_scored <= 2 * blocks
    assert res.model[0, 0] == pytest.approx(5.0, abs=0.02)


def test_no_model_from_any_sample_is_none_with_no_inliers():
    class Nothing(Location):
        def generate(self, samples):
            return np.zeros((0, 1))

    res = lo_ransac(Nothing(np.arange(10.0), 3), RansacOptions(max_iterations=50), 0.1, np.random.default_rng(0))
    assert res.model is None and not res.inliers.any() and res.stats.iterations == 50


def test_samples_hold_distinct_indices_and_follow_the_seed():
    """Every drawn sample has distinct indices in range, even where repeats are likely (n = 4)."""
    from mavvo.estimation.ransac import draw_samples

    for n, size in ((4, 3), (5, 5), (300, 3)):
        idx = draw_samples(np.random.default_rng(1), n, 500, size)
        assert idx.shape == (500, size) and idx.min() >= 0 and idx.max() < n
        assert all(len(set(row)) == size for row in idx.tolist())
        assert np.array_equal(idx, draw_samples(np.random.default_rng(1), n, 500, size))
