"""Robust relative pose with known gravity: batched 3-point LO-RANSAC, refinement, model selection.

:func:`estimate_upright_relpose` works on level-frame bearings (z along gravity), where two views
differ by a yaw and a translation: ``x_2 = R_2_1 @ x_1 + t_2_1``, ``R_2_1 = Rz(yaw)``.

1. Hypotheses come in blocks of samples from :func:`mavvo.geometry.upright_3pt.solve_upright_3pt_batch` (or the
   4-point / linear 5-point, one sample per call, for comparison).
2. Every hypothesis of a block is scored at once on a fixed random subset of the points; only the
   best few of a block are scored on all points (early rejection).
3. The score is MSAC on the Sampson error (:mod:`mavvo.geometry.residuals`): ``sum(min(err^2, thr^2))``.
4. A new best model is locally optimised (Gauss-Newton on its inliers, inliers re-selected).
5. Sampling stops when the best inlier ratio w says that a clean sample was drawn with the requested
   confidence: ``k = log(1 - p) / log(1 - w^s)``, s the sample size.
6. The best model is refined on the upright manifold (yaw and translation direction), optionally with
   roll and pitch free under the IMU's sigma.
7. Model selection by GRIC (Torr, 1998) between the essential matrix, the known-gravity ground-plane
   homography (Saurer et al., 2 points) and a pure rotation (no baseline).
   A median parallax under a pixel or so (``min_parallax_ratio``) is a pure rotation outright.

:func:`estimate_relpose_known_gravity` is the same for pixel coordinates and camera frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Mapping

import numpy as np

from mavvo.options import bounded
from mavvo.types import StrEnum

from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.frames import as_rotation, rot_z, skew
from mavvo.geometry.refine import fit_ground_similarity, fit_rotation, refine_upright, tilt_rotation
from mavvo.geometry.residuals import ground_sq, rotation_sq, sampson_sq_upright, upright_design
from mavvo.geometry import (
    alpha_beta_gamma,
    as_bearing_pair,
    essential_from_vector,
    essential_to_vector,
    ground_homography_from_similarity,
    ground_pose_from_homography,
    solve_ground_2pt_batch,
    solve_upright_3pt_batch,
    solve_upright_4pt,
    solve_upright_linear5pt,
    upright_pose_from_essential,
)

__all__ = [
    "RelposeFailure",
    "RelposeOptions",
    "RelposeStats",
    "UprightRelpose",
    "CameraRelpose",
    "estimate_upright_relpose",
    "estimate_relpose_known_gravity",
    "required_iterations",
]

MinimalSolver = Literal["3pt", "4pt", "linear5pt"]
NonminimalSolver = Literal["none", "4pt", "linear5pt"]
ModelChoice = Literal["auto", "essential", "ground"]
ModelName = Literal["essential", "ground", "rotation", "none"]


class RelposeFailure(StrEnum):
    """Why :func:`estimate_upright_relpose` found no pose with a translation direction."""

    NONE = ""
    TOO_FEW_POINTS = "too_few_points"
    DEGENERATE_POINTS = "degenerate_points"
    NO_MODEL = "no_model"
    PURE_ROTATION = "pure_rotation"  #: ``R_2_1`` holds the yaw, ``t_2_1`` is zero

_SAMPLE_SIZE = {"3pt": 3, "4pt": 4, "linear5pt": 5}
# Bearings this close to the horizon (z of a unit level bearing) count as not on the ground below.
_MIN_GROUND_Z = 0.02
# GRIC constants for 2-view data (r = 4 dimensions per correspondence), Torr 1998.
_GRIC_R = 4
_GRIC_LAMBDA3 = 2.0
# Manifold dimension d and parameter count k of each model.
_GRIC_DK = {"essential": (3, 3), "ground": (2, 4), "rotation": (2, 3)}


@dataclass(frozen=True)
class RelposeOptions:
    """The relative pose's robust estimation (:func:`estimate_upright_relpose`, ``docs/relpose.md``).

    The ``odometry.ransac`` section of the service's configuration; the defaults suit the service.
    """

    max_err_px: float = bounded(1.5, "inlier threshold on the Sampson error, pixels (as an angle: divided by the mean focal length)", gt=0, le=100)
    confidence: float = bounded(0.99, "probability that an all-inlier sample was drawn when sampling stops", gt=0, lt=1)
    max_iterations: int = bounded(200, "most samples per estimate", ge=1, le=100000)
    min_iterations: int = bounded(0, "fewest samples per estimate (0: the stopping rule alone decides)", ge=0, le=100000)
    minimal_solver: MinimalSolver = bounded("3pt", "hypothesis generator: 3pt (batched, fast), 4pt or linear5pt (one sample per call)")
    first_block: int = bounded(64, "samples in the first batch; later batches are sized to what the stopping rule still needs", ge=1, le=100000)
    min_block: int = bounded(8, "the smallest later batch", ge=1, le=100000)
    preemptive_points: int = bounded(96, "models are first scored on a fixed random subset of this many points", ge=1, le=100000)
    full_scores_per_block: int = bounded(3, "models of a batch, best on the subset, that are scored on all points", ge=1, le=100000)
    local_optimization: bool = bounded(True, "refine each new best model on its inliers while sampling")
    lo_steps: int = bounded(3, "Gauss-Newton steps per local optimisation", ge=0, le=100)
    refine_steps: int = bounded(8, "Gauss-Newton steps of the final refinement (0: none)", ge=0, le=100)
    nonminimal_solver: NonminimalSolver = bounded("none", "re-fit each new best model on its inliers with the 4pt or linear5pt least squares (kept when it scores better)")
    model: ModelChoice = bounded("auto", "auto: essential matrix or ground homography by GRIC; essential or ground forces one (pure rotation is always checked)")
    tilt_sigma_deg: float = bounded(0.0, "let vision correct roll/pitch of both views within this sigma, degrees (0: off; the corrections are reported)", ge=0, le=30)
    ground_samples: int = bounded(16, "2-point samples for the ground model among the essential inliers", ge=1, le=10000)
    min_parallax_ratio: float = bounded(1.0, "median inlier parallax below this many thresholds: a pure rotation (translation not observable)", ge=0, le=100)
    yaw_prior_tolerance_deg: float = bounded(
        30.0, "with a yaw prior, hypotheses further from it are dropped (a nadir camera over flat ground sees a twin at yaw + 180 deg)", gt=0, le=180
    )

    def __post_init__(self) -> None:
        if self.minimal_solver not in _SAMPLE_SIZE:
            raise ValueError(f"minimal_solver: expected one of {sorted(_SAMPLE_SIZE)}, got {self.minimal_solver!r}")
        if self.nonminimal_solver not in ("none", "4pt", "linear5pt"):
            raise ValueError(f"nonminimal_solver: expected 'none', '4pt' or 'linear5pt', got {self.nonminimal_solver!r}")
        if self.model not in ("auto", "essential", "ground"):
            raise ValueError(f"model: expected 'auto', 'essential' or 'ground', got {self.model!r}")
        for name in ("max_iterations", "first_block", "min_block", "preemptive_points", "full_scores_per_block"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected a positive integer, got {getattr(self, name)}")
        if self.min_iterations < 0 or self.min_iterations > self.max_iterations:
            raise ValueError(f"min_iterations: expected 0..max_iterations ({self.max_iterations}), got {self.min_iterations}")
        if not 0 < self.yaw_prior_tolerance_deg <= 180:
            raise ValueError(f"yaw_prior_tolerance_deg: expected an angle in (0, 180], got {self.yaw_prior_tolerance_deg}")
        if not self.min_parallax_ratio >= 0:
            raise ValueError(f"min_parallax_ratio: expected a number >= 0, got {self.min_parallax_ratio}")
        if not self.tilt_sigma_deg >= 0:
            raise ValueError(f"tilt_sigma_deg: expected an angle >= 0 (0: off), got {self.tilt_sigma_deg}")
        if not 0 < self.confidence < 1:
            raise ValueError(f"confidence: expected a probability in (0, 1), got {self.confidence}")
        if not self.max_err_px > 0:
            raise ValueError(f"max_err_px: expected a positive number of pixels, got {self.max_err_px}")

    @property
    def tilt_sigma_rad(self) -> float | None:
        """``tilt_sigma_deg`` in radians, None when off."""
        return math.radians(self.tilt_sigma_deg) if self.tilt_sigma_deg > 0 else None


@dataclass(frozen=True)
class RelposeStats:
    """How the estimate came about.

    Attributes:
        models: hypotheses generated. models_scored: hypotheses scored on all points.
        local_optimizations: LO runs. required_iterations: samples the stopping rule asked for at the end.
        sample_inlier_ratio: the best inlier ratio during sampling (what drove the stopping rule).
        noise_sigma_rad: robust estimate of the bearing noise from the inlier residuals.
        gric: GRIC score of each model considered (lower is better).
    """

    models: int = 0
    models_scored: int = 0
    local_optimizations: int = 0
    required_iterations: int = 0
    sample_inlier_ratio: float = 0.0
    noise_sigma_rad: float = float("nan")
    gric: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class UprightRelpose:
    """Relative pose between two level frames.

    Attributes:
        success: a pose with a translation direction was found.
        reason: :class:`RelposeFailure` (``NONE`` on success; ``PURE_ROTATION``: ``R_2_1`` holds the
            estimated yaw and ``t_2_1`` is zero).
        model: ``essential``, ``ground`` (all inliers on the horizontal ground plane), ``rotation`` or ``none``.
        R_2_1: (3, 3) rotation about z between the (tilt-corrected) level frames.
        t_2_1: (3,) unit translation in level frame 2 (zeros when unknown).
        yaw_rad: the yaw of ``R_2_1``.
        t_2_1_per_height: (3,) for the ground model, the translation divided by the height of view 1
            above the ground plane: multiplied by a rangefinder height it is metric. None otherwise.
        inliers: (N,) bool. num_inliers, inlier_ratio: their count and fraction.
        score: MSAC cost of the final model, in units of ``max_err_rad^2`` per point (0 best, 1 worst).
        residual_rms_rad: RMS error of the inliers (Sampson for essential, transfer for the others).
        iterations: samples drawn.
        tilt1_rad, tilt2_rad: (2,) roll/pitch corrections of each view's level frame (``tilt_sigma_deg``).
        stats: :class:`RelposeStats`.
    """

    success: bool
    reason: RelposeFailure
    model: ModelName
    R_2_1: np.ndarray
    t_2_1: np.ndarray
    yaw_rad: float
    t_2_1_per_height: np.ndarray | None
    inliers: np.ndarray
    num_inliers: int
    inlier_ratio: float
    score: float
    residual_rms_rad: float
    iterations: int
    tilt1_rad: np.ndarray
    tilt2_rad: np.ndarray
    stats: RelposeStats


@dataclass(frozen=True)
class CameraRelpose:
    """Relative pose between two camera frames: ``x_c2 = R_c2_c1 @ x_c1 + t_c2_c1`` (t unit).

    ``upright`` is the level-frame estimate it came from, with all statistics; the camera frames use
    the tilt corrections when ``tilt_sigma_deg`` was set.
    """

    success: bool
    R_c2_c1: np.ndarray
    t_c2_c1: np.ndarray
    inliers: np.ndarray
    upright: UprightRelpose


def required_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> int:
    """Samples needed to draw one all-inlier sample with ``confidence``: log(1-p) / log(1-w^s)."""
    if inlier_ratio <= 0.0:
        return 2**31 - 1
    p_good = inlier_ratio**sample_size
    if p_good >= 1.0:
        return 1
    return int(math.ceil(math.log(1.0 - confidence) / math.log1p(-p_good)))


def _yaw_of(R: np.ndarray) -> float:
    """Yaw (Euler 3-2-1) of a rotation (3, 3)."""
    return float(np.arctan2(R[1, 0], R[0, 0]))


def _upright_e(yaw: float, t: np.ndarray) -> np.ndarray:
    """e vector (6,) of ``[t]x Rz(yaw)``."""
    return essential_to_vector(skew(t) @ rot_z(yaw))


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _draw_samples(rng: np.random.Generator, n: int, count: int, size: int) -> np.ndarray:
    """(count, size) indices into range(n), distinct within each row."""
    idx = rng.integers(0, n, (count, size))
    while True:
        s = np.sort(idx, axis=1)
        bad = np.any(s[:, 1:] == s[:, :-1], axis=1)
        if not bad.any():
            return idx
        idx[bad] = rng.integers(0, n, (int(bad.sum()), size))


class _Search:
    """Mutable state of one RANSAC run (kept out of the public result)."""

    def __init__(self, f1: np.ndarray, f2: np.ndarray, thr_sq: float, options: RelposeOptions, rng: np.random.Generator, yaw_prior: float | None):
        self.f1, self.f2, self.thr_sq, self.opt = f1, f2, thr_sq, options
        self.yaw_prior = yaw_prior
        self.n = len(f1)
        self.G = upright_design(f1, f2)
        if self.n > options.preemptive_points:
            sub = np.sort(rng.choice(self.n, options.preemptive_points, replace=False))
            self.G_sub = upright_design(f1[sub], f2[sub])
        else:
            self.G_sub = None
        self.best_e: np.ndarray | None = None
        self.best_pose: tuple[float, np.ndarray] | None = None  # (yaw, t) of best_e when known
        self.best_cost = np.inf
        self.best_inliers = 0
        self.models = 0
        self.scored = 0
        self.lo_runs = 0

    def cost(self, err_sq: np.ndarray) -> np.ndarray:
        return np.minimum(err_sq, self.thr_sq).sum(axis=-1)

    def offer(self, e: np.ndarray) -> None:
        """Score hypotheses e (M, 6); keep and locally optimise the best if it beats the current one."""
        self.models += len(e)
        if self.yaw_prior is not None:
            e = e[_near_yaw(e, self.yaw_prior, math.radians(self.opt.yaw_prior_tolerance_deg))]
            if not len(e):
                return
        if self.G_sub is not None and len(e) > self.opt.full_scores_per_block:
            pre = self.cost(sampson_sq_upright(e, self.G_sub))
            e = e[np.argsort(pre)[: self.opt.full_scores_per_block]]
        self.scored += len(e)
        err = sampson_sq_upright(e, self.G)
        costs = self.cost(err)
        k = int(np.argmin(costs))
        if costs[k] >= self.best_cost:
            return
        self._accept(e[k], float(costs[k]), err[k])
        if self.opt.local_optimization:
            self._local_optimization()

    def _accept(self, e: np.ndarray, cost: float, err_sq: np.ndarray, pose: tuple[float, np.ndarray] | None = None) -> None:
        self.best_e, self.best_cost, self.best_pose = e, cost, pose
        self.best_inliers = int(np.count_nonzero(err_sq < self.thr_sq))

    def pose(self) -> tuple[float, np.ndarray]:
        """(yaw, t) of the best model, decomposed on its inliers if LO has not done it."""
        assert self.best_e is not None
        if self.best_pose is None:
            inl = sampson_sq_upright(self.best_e[None], self.G)[0] < self.thr_sq
            self.best_pose = _decompose(self.best_e, self.f1[inl], self.f2[inl])
        assert self.best_pose is not None  # a model has at least its own sample as inliers
        return self.best_pose

    def _local_optimization(self) -> None:
        self.lo_runs += 1
        assert self.best_e is not None
        inl = sampson_sq_upright(self.best_e[None], self.G)[0] < self.thr_sq
        candidates: list[np.ndarray] = []
        poses: list[tuple[float, np.ndarray] | None] = []
        if self.opt.nonminimal_solver != "none" and np.count_nonzero(inl) >= _SAMPLE_SIZE[self.opt.nonminimal_solver]:
            solve = solve_upright_4pt if self.opt.nonminimal_solver == "4pt" else solve_upright_linear5pt
            for e in essential_to_vector(solve(self.f1[inl], self.f2[inl])):
                candidates.append(e / np.linalg.norm(e))
                poses.append(None)
        pose = _decompose(self.best_e, self.f1[inl], self.f2[inl])
        self.best_pose = pose
        if pose is not None and self.opt.lo_steps > 0:
            fit = refine_upright(*pose, self.f1[inl], self.f2[inl], iterations=self.opt.lo_steps)
            candidates.append(_upright_e(fit.yaw_rad, fit.t_2_1))
            poses.append((fit.yaw_rad, fit.t_2_1))
        if not candidates:
            return
        err = sampson_sq_upright(np.array(candidates), self.G)
        costs = self.cost(err)
        k = int(np.argmin(costs))
        if costs[k] < self.best_cost:
            self._accept(candidates[k], float(costs[k]), err[k], poses[k])


def _near_yaw(e: np.ndarray, prior: float, tol: float) -> np.ndarray:
    """(M,) bool: the yaw of each upright hypothesis e (M, 6) is within ``tol`` of ``prior``.

    For ``E = [t]x Rz(yaw)`` with |t| = 1: ``-conj(gamma) * beta = exp(i yaw) |t_xy|^2`` fixes the yaw
    whenever t has a horizontal part; for t along z only ``alpha^2 = -t_z^2 exp(2i yaw)`` is left,
    which fixes it up to pi.
    """
    alpha, beta, gamma = alpha_beta_gamma(e)
    # A solver's E has the upright form exactly, so even a small horizontal part fixes the yaw.
    horizontal = np.abs(beta) ** 2 > 1e-9 * (np.abs(alpha) ** 2 + np.abs(beta) ** 2)
    ref = np.exp(1j * prior)
    d1 = np.abs(np.angle(-np.conj(gamma) * beta * np.conj(ref)))
    d2 = 0.5 * np.abs(np.angle(-(alpha**2) * np.conj(ref**2)))
    return np.where(horizontal, d1, d2) <= tol


def _decompose(e: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(yaw, t) of an upright e with cheirality decided on the given inliers."""
    if len(f1) == 0:
        return None
    R, t = upright_pose_from_essential(essential_from_vector(e), f1, f2)
    return _yaw_of(R), t


def _minimal_models(f1: np.ndarray, f2: np.ndarray, idx: np.ndarray, solver: MinimalSolver) -> np.ndarray:
    """Hypotheses (M, 6) from the samples idx (B, s)."""
    if solver == "3pt":
        E, valid = solve_upright_3pt_batch(f1[idx], f2[idx])
        return essential_to_vector(E[valid])
    solve = solve_upright_4pt if solver == "4pt" else solve_upright_linear5pt
    out = [essential_to_vector(solve(f1[row], f2[row])) for row in idx]
    return np.concatenate(out) if out else np.zeros((0, 6))


def _gric(err_sq: np.ndarray, sigma_sq: float, model: str) -> float:
    d, k = _GRIC_DK[model]
    n = len(err_sq)
    rho = np.minimum(err_sq / sigma_sq, _GRIC_LAMBDA3 * (_GRIC_R - d))
    return float(rho.sum() + math.log(_GRIC_R) * d * n + math.log(_GRIC_R * n) * k)


def _rotation_ransac(f1: np.ndarray, f2: np.ndarray, thr_sq: float, rng: np.random.Generator, samples: int = 32) -> np.ndarray | None:
    """A pure rotation from 1-point yaw samples, refitted (all 3 axes) on its inliers; None if nothing fits."""
    h1 = f1[:, 0] + 1j * f1[:, 1]
    h2 = f2[:, 0] + 1j * f2[:, 1]
    usable = np.nonzero((np.abs(h1) > 1e-6) & (np.abs(h2) > 1e-6))[0]
    if usable.size == 0:
        return None
    pick = usable[rng.integers(0, usable.size, min(samples, usable.size))]
    R = np.array([rot_z(y) for y in np.angle(h2[pick] * np.conj(h1[pick]))])
    return _refit_rotation(R[int(np.argmin(np.minimum(rotation_sq(R, f1, f2), thr_sq).sum(axis=1)))], f1, f2, thr_sq)


def _refit_rotation(R: np.ndarray | None, f1: np.ndarray, f2: np.ndarray, thr_sq: float, rounds: int = 2) -> np.ndarray | None:
    """Re-select the inliers of a rotation and refit it on them, ``rounds`` times."""
    for _ in range(rounds if R is not None else 0):
        inl = rotation_sq(R, f1, f2) < thr_sq
        refit = fit_rotation(f1[inl], f2[inl])
        if refit is None:
            break
        R = refit
    return R


def _ground_model(f1: np.ndarray, f2: np.ndarray, candidates: np.ndarray, thr_sq: float, samples: int, rng: np.random.Generator) -> np.ndarray | None:
    """Ground homography (3, 3) by 2-point RANSAC among the candidate indices, then least squares."""
    below = candidates[(f1[candidates, 2] > _MIN_GROUND_Z) & (f2[candidates, 2] > _MIN_GROUND_Z)]
    if below.size < max(4, 0.8 * candidates.size):
        return None  # a scene that is all ground lies below the horizon in both views
    idx = below[_draw_samples(rng, below.size, samples, 2)]
    H, valid = solve_ground_2pt_batch(f1[idx], f2[idx])
    if not valid.any():
        return None
    costs = np.minimum(ground_sq(H[valid], f1[below], f2[below]), thr_sq).sum(axis=1)
    best = H[valid][int(np.argmin(costs))]
    for _ in range(2):
        inl = ground_sq(best, f1, f2) < thr_sq
        fit = fit_ground_similarity(f1[inl], f2[inl])
        if fit is None:
            break
        best = ground_homography_from_similarity(np.array(fit[0]), np.array(fit[1]))
    return best


def _failure(reason: RelposeFailure, n: int, iterations: int = 0, stats: RelposeStats | None = None) -> UprightRelpose:
    return UprightRelpose(
        success=False,
        reason=reason,
        model="none",
        R_2_1=_frozen(np.eye(3)),
        t_2_1=_frozen(np.zeros(3)),
        yaw_rad=0.0,
        t_2_1_per_height=None,
        inliers=_frozen(np.zeros(n, dtype=bool)),
        num_inliers=0,
        inlier_ratio=0.0,
        score=1.0,
        residual_rms_rad=float("nan"),
        iterations=iterations,
        tilt1_rad=_frozen(np.zeros(2)),
        tilt2_rad=_frozen(np.zeros(2)),
        stats=stats or RelposeStats(),
    )


def estimate_upright_relpose(
    f1_lvl: np.ndarray,
    f2_lvl: np.ndarray,
    *,
    max_err_rad: float,
    seed: int = 0,
    options: RelposeOptions | None = None,
    yaw_prior_rad: float | None = None,
) -> UprightRelpose:
    """Robust relative pose between two level frames from bearing correspondences.

    Args:
        f1_lvl, f2_lvl: (N, 3) bearings in the level frames of view 1 and view 2 (any length, not zero),
            row i of one matching row i of the other.
        max_err_rad: inlier threshold on the Sampson (angular) error.
        seed: seed of the random sampling; the same inputs and seed give the same result.
        options: :class:`RelposeOptions`.
        yaw_prior_rad: the expected yaw of ``R_2_1`` (within ``options.yaw_prior_tolerance_deg``),
            or None.

    Returns:
        :class:`UprightRelpose`. Degenerate input (fewer points than a sample, identical points, no
        motion) gives ``success=False`` with a reason; malformed input raises ``ValueError``.
    """
    opt = options or RelposeOptions()
    f1, f2 = as_bearing_pair(f1_lvl, f2_lvl, names=("f1_lvl", "f2_lvl"))
    if not (np.isfinite(max_err_rad) and max_err_rad > 0):
        raise ValueError(f"max_err_rad: expected a positive angle, got {max_err_rad}")
    n = len(f1)
    s = _SAMPLE_SIZE[opt.minimal_solver]
    if n < s:
        return _failure(RelposeFailure.TOO_FEW_POINTS, n)
    spread = max(np.linalg.norm(f1 - f1.mean(axis=0), axis=1).max(), np.linalg.norm(f2 - f2.mean(axis=0), axis=1).max())
    if spread < 1e-9:
        return _failure(RelposeFailure.DEGENERATE_POINTS, n)

    rng = np.random.default_rng(seed)
    thr_sq = float(max_err_rad) ** 2
    search = _Search(f1, f2, thr_sq, opt, rng, yaw_prior_rad)
    drawn = 0
    needed = max(opt.min_iterations, 1)
    block = opt.first_block
    while drawn < min(max(needed, opt.min_iterations), opt.max_iterations):
        count = min(block, opt.max_iterations - drawn)
        idx = _draw_samples(rng, n, count, s)
        drawn += count
        e = _minimal_models(f1, f2, idx, opt.minimal_solver)
        if len(e):
            search.offer(e)
        needed = required_iterations(search.best_inliers / n, s, opt.confidence)
        block = max(opt.min_block, min(opt.first_block, needed - drawn))
    stats = dict(
        models=search.models,
        models_scored=search.scored,
        local_optimizations=search.lo_runs,
        required_iterations=min(needed, opt.max_iterations),
        sample_inlier_ratio=search.best_inliers / n,
    )

    if search.best_e is None:
        R_rot = _rotation_ransac(f1, f2, thr_sq, rng)
        err = rotation_sq(R_rot, f1, f2) if R_rot is not None else None
        if R_rot is None or err is None or np.count_nonzero(err < thr_sq) < s:
            return _failure(RelposeFailure.NO_MODEL, n, drawn, RelposeStats(**stats))
        return _result(False, RelposeFailure.PURE_ROTATION, "rotation", _yaw_of(R_rot), np.zeros(3), None, err, thr_sq, drawn, np.zeros(2), np.zeros(2), RelposeStats(**stats))

    # Final refinement on the inliers, which are then re-selected for a second round (with the
    # roll/pitch of both views free under the IMU prior when asked).
    yaw, t = search.pose()
    tilt1 = tilt2 = np.zeros(2)
    err_e = sampson_sq_upright(_upright_e(yaw, t)[None], search.G)[0]
    if opt.refine_steps > 0:
        inl = err_e < thr_sq
        fit = refine_upright(yaw, t, f1[inl], f2[inl], iterations=opt.refine_steps)
        yaw, t = fit.yaw_rad, fit.t_2_1
        err_e = sampson_sq_upright(_upright_e(yaw, t)[None], search.G)[0]
    sigma = _robust_sigma(err_e[err_e < thr_sq], max_err_rad)
    if opt.refine_steps > 0:
        inl = err_e < thr_sq
        if opt.tilt_sigma_rad is None:
            fit = refine_upright(yaw, t, f1[inl], f2[inl], iterations=min(opt.refine_steps, 2))
            G = search.G
        else:
            fit = refine_upright(yaw, t, f1[inl], f2[inl], iterations=opt.refine_steps, tilt_sigma_rad=opt.tilt_sigma_rad, noise_sigma_rad=sigma)
            tilt1, tilt2 = fit.tilt1_rad, fit.tilt2_rad
            G = upright_design(f1 @ tilt_rotation(tilt1).T, f2 @ tilt_rotation(tilt2).T)
        yaw, t = fit.yaw_rad, fit.t_2_1
        err_e = sampson_sq_upright(_upright_e(yaw, t)[None], G)[0]

    # GRIC runs on the essential inliers only: its outlier cap differs between models (2 for E, 4
    # for the others), so gross outliers, which fit none of them, would otherwise decide the choice.
    sigma_sq = sigma**2
    inl_idx = np.nonzero(err_e < thr_sq)[0]
    gric = {"essential": _gric(err_e[inl_idx], sigma_sq, "essential")}
    R_rot = _refit_rotation(fit_rotation(f1[inl_idx], f2[inl_idx]), f1, f2, thr_sq)
    err_r = rotation_sq(R_rot, f1, f2) if R_rot is not None else None
    if err_r is not None:
        gric["rotation"] = _gric(err_r[inl_idx], sigma_sq, "rotation")
        # Below about a pixel of parallax a translation direction is noise, and a near-vertical one
        # leaves yaw ambiguous by pi (E = [t]x Rz(yaw) is the same for yaw + pi when t is along z).
        # Measured about z only: roll and pitch are known, and a free tilt would pass off a nadir
        # camera's image shift as rotation.
        err_yaw = rotation_sq(rot_z(_yaw_of(R_rot)), f1[inl_idx], f2[inl_idx])
        parallax = float(np.median(np.sqrt(2.0 * err_yaw))) if len(inl_idx) else 0.0
        if parallax < opt.min_parallax_ratio * max_err_rad:
            stats_final = RelposeStats(**stats, noise_sigma_rad=sigma, gric=dict(gric))
            return _result(False, RelposeFailure.PURE_ROTATION, "rotation", _yaw_of(R_rot), np.zeros(3), None, err_r, thr_sq, drawn, np.zeros(2), np.zeros(2), stats_final)
    H = None
    if opt.model in ("auto", "ground"):
        H = _ground_model(f1, f2, inl_idx, thr_sq, opt.ground_samples, rng)
        if H is not None:
            gric["ground"] = _gric(ground_sq(H, f1[inl_idx], f2[inl_idx]), sigma_sq, "ground")
    stats_final = RelposeStats(**stats, noise_sigma_rad=sigma, gric=dict(gric))
    if opt.model == "auto":
        allowed: tuple[str, ...] = ("essential", "ground", "rotation")
    elif opt.model == "ground" and "ground" in gric:
        allowed = ("ground", "rotation")
    else:  # essential asked for, or the ground model is not applicable
        allowed = ("essential", "rotation")
    choice = min((m for m in gric if m in allowed), key=gric.__getitem__, default="essential")
    if choice == "rotation" and R_rot is not None and err_r is not None:
        return _result(False, RelposeFailure.PURE_ROTATION, "rotation", _yaw_of(R_rot), np.zeros(3), None, err_r, thr_sq, drawn, np.zeros(2), np.zeros(2), stats_final)
    if choice == "ground" and H is not None:
        R, t_per_h = ground_pose_from_homography(H)
        yaw_g = _yaw_of(R)
        nt = float(np.linalg.norm(t_per_h))
        if nt > 0:
            return _result(True, RelposeFailure.NONE, "ground", yaw_g, t_per_h / nt, t_per_h, ground_sq(H, f1, f2), thr_sq, drawn, np.zeros(2), np.zeros(2), stats_final)
    return _result(True, RelposeFailure.NONE, "essential", yaw, t, None, err_e, thr_sq, drawn, tilt1, tilt2, stats_final)


def _robust_sigma(err_sq_inliers: np.ndarray, max_err_rad: float) -> float:
    """Noise sigma from inlier residuals (MAD), floored at 1% of the threshold."""
    if err_sq_inliers.size == 0:
        return max_err_rad
    return max(1.4826 * float(np.median(np.sqrt(err_sq_inliers))), 0.01 * max_err_rad)


def _result(
    success: bool,
    reason: RelposeFailure,
    model: ModelName,
    yaw: float,
    t: np.ndarray,
    t_per_height: np.ndarray | None,
    err_sq: np.ndarray,
    thr_sq: float,
    iterations: int,
    tilt1: np.ndarray,
    tilt2: np.ndarray,
    stats: RelposeStats,
) -> UprightRelpose:
    inl = err_sq < thr_sq
    k = int(np.count_nonzero(inl))
    n = len(err_sq)
    return UprightRelpose(
        success=success,
        reason=reason,
        model=model,
        R_2_1=_frozen(rot_z(yaw)),
        t_2_1=_frozen(t),
        yaw_rad=float(yaw),
        t_2_1_per_height=None if t_per_height is None else _frozen(t_per_height),
        inliers=_frozen(inl),
        num_inliers=k,
        inlier_ratio=k / n if n else 0.0,
        score=float(np.minimum(err_sq, thr_sq).sum() / (thr_sq * n)) if n else 1.0,
        residual_rms_rad=float(np.sqrt(np.mean(err_sq[inl]))) if k else float("nan"),
        iterations=iterations,
        tilt1_rad=_frozen(tilt1),
        tilt2_rad=_frozen(tilt2),
        stats=stats,
    )


def estimate_relpose_known_gravity(
    uv1_px: np.ndarray,
    uv2_px: np.ndarray,
    camera: CameraModel,
    R_lvl_cam1: np.ndarray,
    R_lvl_cam2: np.ndarray,
    max_err_px: float | None = None,
    *,
    seed: int = 0,
    options: RelposeOptions | None = None,
) -> CameraRelpose:
    """Relative pose between two camera frames from matched pixels and each view's gravity.

    Args:
        uv1_px, uv2_px: (N, 2) matched pixel coordinates in image 1 and image 2.
        camera: the intrinsics and distortion of both images.
        R_lvl_cam1, R_lvl_cam2: (3, 3) level-from-camera rotations of each view
            (:func:`mavvo.geometry.frames.R_lvl_cam` of the roll/pitch at each exposure).
        max_err_px: inlier threshold in pixels (default ``options.max_err_px``), converted once to an
            angle with the mean focal length.
        seed, options: as for :func:`estimate_upright_relpose`.

    Returns:
        :class:`CameraRelpose` with ``x_c2 = R_c2_c1 @ x_c1 + t_c2_c1``.
    """
    opt = options or RelposeOptions()
    max_err_px = opt.max_err_px if max_err_px is None else max_err_px
    if not (np.isfinite(max_err_px) and max_err_px > 0):
        raise ValueError(f"max_err_px: expected a positive number of pixels, got {max_err_px}")
    R1 = as_rotation("R_lvl_cam1", R_lvl_cam1)
    R2 = as_rotation("R_lvl_cam2", R_lvl_cam2)
    for name, uv in (("uv1_px", uv1_px), ("uv2_px", uv2_px)):
        a = np.asarray(uv, dtype=float)
        if a.ndim != 2 or a.shape[1] != 2:
            raise ValueError(f"{name}: expected an (N,2) array of pixels, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: pixels must be finite, got NaN or inf")
    f1 = camera.pixels_to_bearings(uv1_px) @ R1.T
    f2 = camera.pixels_to_bearings(uv2_px) @ R2.T
    max_err_rad = max_err_px / (0.5 * (camera.fx_px + camera.fy_px))
    up = estimate_upright_relpose(f1, f2, max_err_rad=max_err_rad, seed=seed, options=opt)
    R1c = tilt_rotation(up.tilt1_rad) @ R1
    R2c = tilt_rotation(up.tilt2_rad) @ R2
    return CameraRelpose(
        success=up.success,
        R_c2_c1=_frozen(R2c.T @ up.R_2_1 @ R1c),
        t_c2_c1=_frozen(R2c.T @ up.t_2_1),
        inliers=up.inliers,
        upright=up,
    )
