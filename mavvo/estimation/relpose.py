"""Robust relative pose with known gravity: LO-RANSAC over two-view estimators, refinement, model selection.

:func:`estimate_upright_relpose` works on level-frame bearings (z along gravity), where two views
differ by a yaw and a translation: ``x_2 = R_2_1 @ x_1 + t_2_1``, ``R_2_1 = Rz(yaw)``.

1. The upright essential matrix (:class:`mavvo.estimation.estimators.UprightEssential`: the paper's
   3-point solver, batched, or its 4-point / linear 5-point) by the one LO-RANSAC loop
   (:func:`mavvo.estimation.ransac.lo_ransac`: blocks of samples, early rejection on a subset, MSAC on
   the Sampson error, local optimisation of each new best model, adaptive stopping).
2. The best model is refined on the upright manifold (yaw and translation direction), optionally with
   roll and pitch free under the IMU's sigma; also from a pose the attitude's error cannot mislead
   (over flat ground the ground homography's, where the tilt's share of the flow is large; elsewhere
   the general 5-point's, wherever the parallax gives it a translation and roll/pitch are uncertain
   beyond the threshold), keeping the better of two different answers
   (:func:`mavvo.estimation.attitude_refine.refine_essential`).
3. Model selection by GRIC (Torr, 1998) between the essential matrix, the known-gravity ground-plane
   homography (Saurer et al., 2 points; :class:`~mavvo.estimation.estimators.GroundHomography` by the
   same loop among the essential inliers) and a pure rotation (no baseline; closed form on them).
   A median parallax under a pixel or so (``min_parallax_ratio``; for finer tracks, half as much
   again as noise alone leaves a pure rotation of as many points) is a pure rotation outright. With
   no essential model at all, a pure rotation is searched by the same loop
   (:class:`~mavvo.estimation.estimators.PureRotation`).

:func:`estimate_relpose_known_gravity` is the same for pixel coordinates and camera frames.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from mavvo.estimation.attitude_refine import (
    Correction,
    pose_err_sq,
    refine_at_threshold,
    refine_essential,
    robust_sigma,
    upright_from_general,
    yaw_parallax_rad,
)
from mavvo.estimation.estimators import (
    SAMPLE_SIZE,
    GroundHomography,
    PureRotation,
    UprightEssential,
    yaw_of,
)
from mavvo.estimation.general5pt import estimate_general_relpose, sampson_sq_general
from mavvo.estimation.ransac import RansacResult, lo_ransac
from mavvo.estimation.relpose_types import (
    CameraRelpose,
    RelposeFailure,
    RelposeModel,
    RelposeOptions,
    RelposeStats,
    UprightRelpose,
)
from mavvo.geometry import as_bearing_pair, ground_pose_from_homography
from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.frames import as_rotation, rot_z
from mavvo.geometry.refine import kabsch, tilt_rotation
from mavvo.geometry.residuals import ground_sq, rotation_sq, rotation_sq_point
from mavvo.jit import kernel

__all__ = ["estimate_upright_relpose", "estimate_relpose_known_gravity"]

# Bearings this close to the horizon (z of a unit level bearing) count as not on the ground below.
_MIN_GROUND_Z = 0.02
# GRIC constants for 2-view data (r = 4 dimensions per correspondence), Torr 1998.
_GRIC_R = 4
_GRIC_LAMBDA3 = 2.0
# Manifold dimension d and parameter count k of each model.
_GRIC_DK = {RelposeModel.ESSENTIAL: (3, 3), RelposeModel.GROUND: (2, 4), RelposeModel.ROTATION: (2, 3)}
# With roll/pitch uncertain, hypotheses are scored allowing this many sigmas of relative tilt error.
_TILT_SIGMAS = 2.0
# Fewer tight inliers than this fraction of the points the widened sampling threshold admitted (or
# corrections beyond 3 sigma): try the general model. Relative to the admitted points, not to all, so
# that a high outlier rate alone never pays for the 5-point search.
_FALLBACK_BELOW_RATIO = 0.6
_FALLBACK_MARGIN = 1.25  # ... and take it when it explains this many times the points
# The pure-rotation rule (:func:`_translation_unresolved`). Noise alone leaves a pure rotation a
# median parallax (after the best rotation about z) of a few sigmas, more with fewer points: 99th
# percentiles 8.2 / 5.6 / 4.3 / 3.0 / 2.4 / 2.1 / 2.0 sigmas at 15 / 20 / 30 / 50 / 100 / 200 / 400
# inliers (synthetic, 0.1 px, 200 trials each), about 1.8 + 75 / n. The rule asks for half as much
# again (KLT tails, track bias).
_NOISE_PARALLAX_SIGMAS = 1.8
_NOISE_PARALLAX_POINTS = 75.0
_NOISE_PARALLAX_MARGIN = 1.5


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _gric(err_sq: np.ndarray, rows: np.ndarray, sigma_sq: float, model: RelposeModel) -> float:
    """GRIC of a model with squared errors err_sq (N,) over the points ``rows`` (indices); inf without any."""
    d, k = _GRIC_DK[model]
    return _gric_kernel(err_sq, rows, sigma_sq, d, k)


@kernel
def _gric_kernel(err_sq: np.ndarray, rows: np.ndarray, sigma_sq: float, d: int, k: int) -> float:
    n = rows.shape[0]
    if n == 0:
        return math.inf  # nothing to judge the model by
    cap = _GRIC_LAMBDA3 * (_GRIC_R - d)
    rho = 0.0
    for i in rows:
        rho += min(err_sq[i] / sigma_sq, cap)
    return rho + math.log(_GRIC_R) * d * n + math.log(_GRIC_R * n) * k


@kernel
def _all_alike(f1: np.ndarray, f2: np.ndarray, tol: float) -> bool:
    """True when every row of f1 is within ``tol`` of f1's first row, and so for f2 (one point, repeated)."""
    for f in (f1, f2):
        for i in range(1, f.shape[0]):
            if abs(f[i, 0] - f[0, 0]) + abs(f[i, 1] - f[0, 1]) + abs(f[i, 2] - f[0, 2]) > tol:
                return False
    return True


def _rotation_model(f1: np.ndarray, f2: np.ndarray, rows: np.ndarray, thr_sq: float) -> np.ndarray | None:
    """The pure rotation (3, 3) fitted on ``rows`` (indices), then twice re-selected among all points
    and refitted; None when the first fit has fewer than two distinct rays."""
    R = _rotation_model_kernel(f1, f2, rows, thr_sq, 2)
    return None if np.isnan(R[0, 0]) else R


@kernel
def _rotation_model_kernel(f1: np.ndarray, f2: np.ndarray, rows: np.ndarray, thr_sq: float, rounds: int) -> np.ndarray:
    """:func:`_rotation_model` (NaN for None)."""
    R = kabsch(f1[rows], f2[rows])
    for _ in range(rounds if not np.isnan(R[0, 0]) else 0):
        inl = np.empty(f1.shape[0], dtype=np.bool_)
        for i in range(f1.shape[0]):
            inl[i] = rotation_sq_point(R, f1, f2, i) < thr_sq
        refit = kabsch(f1[inl], f2[inl])
        if np.isnan(refit[0, 0]):
            break
        R = refit
    return R


def _ground_model(
    f1: np.ndarray,
    f2: np.ndarray,
    candidates: np.ndarray,
    opt: RelposeOptions,
    threshold_rad: float,
    rng: np.random.Generator,
) -> np.ndarray | None:
    """Ground homography (3, 3) among the candidate indices by the LO-RANSAC loop (2-point samples,
    refitted twice on re-selected inliers); None when the candidates are not all below the horizon."""
    below = candidates[(f1[candidates, 2] > _MIN_GROUND_Z) & (f2[candidates, 2] > _MIN_GROUND_Z)]
    if below.size < max(4, 0.8 * candidates.size):
        return None  # a scene that is all ground lies below the horizon in both views
    # Among the essential inliers a ground scene is nearly all inliers: a few samples decide.
    block = min(8, opt.ground_samples)
    sampling = dataclasses.replace(
        opt,
        min_iterations=0,
        max_iterations=opt.ground_samples,
        first_block=block,
        min_block=1,
        lo_rounds=2,
        local_optimization=True,
    )
    run = lo_ransac(GroundHomography(f1[below], f2[below]), sampling, threshold_rad, rng)
    return None if run.model is None else run.model[0]


@dataclass(frozen=True)
class _Fit:
    """One model's answer, before it becomes an :class:`UprightRelpose`."""

    model: RelposeModel
    yaw: float
    t: np.ndarray
    err_sq: np.ndarray  # (N,) on all points
    t_per_height: np.ndarray | None = None
    tilt1: np.ndarray = field(default_factory=lambda: np.zeros(2))
    tilt2: np.ndarray = field(default_factory=lambda: np.zeros(2))
    correction: Correction = Correction.AS_GIVEN


def _rotation_fit(R: np.ndarray, err_sq: np.ndarray) -> _Fit:
    return _Fit(RelposeModel.ROTATION, yaw_of(R), np.zeros(3), err_sq)


def _failure(reason: RelposeFailure, n: int, iterations: int = 0, stats: RelposeStats | None = None) -> UprightRelpose:
    return UprightRelpose(
        success=False,
        reason=reason,
        model=RelposeModel.NONE,
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
    attitude_sigma_rad: tuple[float, float] | None = None,
    confidence: float | None = None,
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
        attitude_sigma_rad: the roll/pitch uncertainty (1 sigma) of the level frame of view 1 and of
            view 2, or None for ``options.tilt_sigma_deg`` for both (0: roll/pitch taken as exact, the
            paper's setting). With an uncertainty, hypotheses are scored with a threshold that allows
            for the tilt error they inherit; the refinement then corrects roll/pitch under that prior,
            re-selecting the inliers with a threshold halved each round down to ``max_err_rad``.
        confidence: deprecated (a keyword of 0.1.0's first releases): ``options.confidence`` replaces
            it. Still taken, with a ``DeprecationWarning``, in place of ``options.confidence``.

    Returns:
        :class:`UprightRelpose`. Degenerate input (fewer points than a sample, identical points, no
        motion) gives ``success=False`` with a reason; malformed input raises ``ValueError``.
    """
    opt = options or RelposeOptions()
    if confidence is not None:
        warnings.warn(
            "estimate_upright_relpose(confidence=...) is deprecated: pass options=RelposeOptions(confidence=...)",
            DeprecationWarning,
            stacklevel=2,
        )
        opt = dataclasses.replace(opt, confidence=confidence)  # checked where the option is declared
    f1, f2 = as_bearing_pair(f1_lvl, f2_lvl, names=("f1_lvl", "f2_lvl"))
    if not (np.isfinite(max_err_rad) and max_err_rad > 0):
        raise ValueError(f"max_err_rad: expected a positive angle, got {max_err_rad}")
    n = len(f1)
    s = SAMPLE_SIZE[opt.minimal_solver]
    if n < s:
        return _failure(RelposeFailure.TOO_FEW_POINTS, n)
    if _all_alike(f1, f2, 1e-9):
        return _failure(RelposeFailure.DEGENERATE_POINTS, n)

    if attitude_sigma_rad is None and opt.tilt_sigma_rad is not None:
        attitude_sigma_rad = (opt.tilt_sigma_rad, opt.tilt_sigma_rad)
    if attitude_sigma_rad is not None and not all(np.isfinite(x) and x >= 0 for x in attitude_sigma_rad):
        raise ValueError(f"attitude_sigma_rad: expected two angles >= 0, got {attitude_sigma_rad}")
    if attitude_sigma_rad is not None and max(attitude_sigma_rad) <= 0:
        attitude_sigma_rad = None
    # A hypothesis from roll/pitch off by d1 and d2 misplaces every bearing by up to their relative error.
    sample_thr = (
        max_err_rad
        if attitude_sigma_rad is None
        else math.hypot(max_err_rad, _TILT_SIGMAS * math.hypot(*attitude_sigma_rad))
    )

    rng = np.random.default_rng(seed)
    thr_sq = float(max_err_rad) ** 2
    essential = UprightEssential(
        f1,
        f2,
        solver=opt.minimal_solver,
        nonminimal=opt.nonminimal_solver,
        lo_steps=opt.lo_steps,
        yaw_prior_rad=yaw_prior_rad,
        yaw_tolerance_rad=math.radians(opt.yaw_prior_tolerance_deg),
    )
    run = lo_ransac(essential, opt, sample_thr, rng)
    t_refine = time.thread_time()
    rs = run.stats
    sigma, gric = math.nan, dict[RelposeModel, float]()
    if run.model is None:
        rot = lo_ransac(
            PureRotation(f1, f2), dataclasses.replace(opt, lo_rounds=2, local_optimization=True), sample_thr, rng
        )
        if rot.model is None or np.count_nonzero(rot.inliers) < s:
            return _failure(RelposeFailure.NO_MODEL, n, rs.iterations, RelposeStats(rs))
        fit = _rotation_fit(rot.model[0], rotation_sq(rot.model[0], f1, f2))
    else:
        fit, essential, sigma, gric = _select(
            f1, f2, run, opt, max_err_rad, rng, attitude_sigma_rad, sample_thr, yaw_prior_rad
        )
        if attitude_sigma_rad is not None and fit.model != RelposeModel.ROTATION:
            fit = _general_if_attitude_is_worse(
                f1, f2, fit, essential, attitude_sigma_rad, max_err_rad, seed, run.inliers
            )
    final = RelposeStats(rs, sigma, gric, time.thread_time() - t_refine)
    return _result(fit, thr_sq, rs.iterations, final)


def _select(
    f1: np.ndarray,
    f2: np.ndarray,
    run: RansacResult,
    opt: RelposeOptions,
    max_err_rad: float,
    rng: np.random.Generator,
    attitude_sigma_rad: tuple[float, float] | None,
    sample_thr: float,
    yaw_prior_rad: float | None,
) -> tuple[_Fit, _Fit, float, dict[RelposeModel, float]]:
    """Refine the essential model found, then choose between it, the ground homography and a pure
    rotation (GRIC) on the bearings with the roll/pitch corrections the refinement found: the chosen
    fit, the refined essential fit (what the attitude is judged by), the noise sigma and the GRIC scores."""
    thr_sq = max_err_rad**2
    pose, correction = refine_essential(
        f1,
        f2,
        run,
        max_err_rad,
        attitude_sigma_rad,
        sample_thr,
        yaw_prior_rad,
        steps=opt.refine_steps,
        yaw_tolerance_rad=math.radians(opt.yaw_prior_tolerance_deg),
    )
    yaw, t, tilt1, tilt2 = pose
    err_e = pose_err_sq(pose, f1, f2, max_err_rad)
    f1c, f2c = (
        (f1, f2) if correction == Correction.AS_GIVEN else (f1 @ tilt_rotation(tilt1).T, f2 @ tilt_rotation(tilt2).T)
    )
    sigma = robust_sigma(err_e[err_e < thr_sq], max_err_rad)
    essential = _Fit(RelposeModel.ESSENTIAL, yaw, t, err_e, None, tilt1, tilt2, correction)

    # GRIC runs on the essential inliers only: its outlier cap differs between models (2 for E, 4
    # for the others), so gross outliers, which fit none of them, would otherwise decide the choice.
    sigma_sq = sigma**2
    inl_idx = np.nonzero(err_e < thr_sq)[0]
    gric = {RelposeModel.ESSENTIAL: _gric(err_e, inl_idx, sigma_sq, RelposeModel.ESSENTIAL)}
    R_rot = _rotation_model(f1c, f2c, inl_idx, thr_sq)
    rotation = (
        None
        if R_rot is None
        else _Fit(
            RelposeModel.ROTATION,
            yaw_of(R_rot),
            np.zeros(3),
            rotation_sq(R_rot, f1c, f2c),
            None,
            tilt1,
            tilt2,
            correction,
        )
    )
    if rotation is not None:
        gric[RelposeModel.ROTATION] = _gric(rotation.err_sq, inl_idx, sigma_sq, RelposeModel.ROTATION)
        # Measured about z only: roll and pitch are known, and a free tilt would pass off a nadir
        # camera's image shift as rotation.
        parallax = yaw_parallax_rad(rotation.yaw, f1c, f2c, inl_idx)
        if _translation_unresolved(parallax, len(inl_idx), sigma, max_err_rad, opt.min_parallax_ratio):
            return rotation, essential, sigma, gric
    ground = None
    if opt.model in ("auto", "ground"):
        H = _ground_model(f1c, f2c, inl_idx, opt, max_err_rad, rng)
        if H is not None:
            err_g = ground_sq(H, f1c, f2c)
            gric[RelposeModel.GROUND] = _gric(err_g, inl_idx, sigma_sq, RelposeModel.GROUND)
            R, t_per_h = ground_pose_from_homography(H)
            nt = float(np.linalg.norm(t_per_h))
            if nt > 0:
                ground = _Fit(RelposeModel.GROUND, yaw_of(R), t_per_h / nt, err_g, t_per_h, tilt1, tilt2, correction)
    if opt.model == "auto":
        allowed: tuple[RelposeModel, ...] = (RelposeModel.ESSENTIAL, RelposeModel.GROUND, RelposeModel.ROTATION)
    elif opt.model == "ground" and RelposeModel.GROUND in gric:
        allowed = (RelposeModel.GROUND, RelposeModel.ROTATION)
    else:  # essential asked for, or the ground model is not applicable
        allowed = (RelposeModel.ESSENTIAL, RelposeModel.ROTATION)
    choice = min((m for m in gric if m in allowed), key=gric.__getitem__, default=RelposeModel.ESSENTIAL)
    if (
        choice == RelposeModel.GROUND
        and ground is not None
        and attitude_sigma_rad is not None
        and correction != Correction.AS_GIVEN
    ):
        ground = _ground_refined(f1, f2, ground, attitude_sigma_rad, max_err_rad, opt.refine_steps)
    fits = {RelposeModel.ESSENTIAL: essential, RelposeModel.ROTATION: rotation, RelposeModel.GROUND: ground}
    return fits[choice] or essential, essential, sigma, gric


def _ground_refined(
    f1: np.ndarray,
    f2: np.ndarray,
    ground: _Fit,
    attitude_sigma_rad: tuple[float, float],
    max_err_rad: float,
    steps: int,
) -> _Fit:
    """The ground model's pose, found with the essential fit's roll/pitch corrections held, refined
    with the corrections under the attitude prior on the epipolar (Sampson) error, from that pose and
    at the inlier threshold: the homography decides the model and the basin, the joint refinement the
    last digits: the homography's transfer error with the corrections held carries their residual
    error into yaw and translation (docs/relpose.md has the figures). Where roll/pitch are taken as
    exact (no corrections) the homography is as good or better, and there it is kept (the caller does
    not refine). The sign of the translation and its size per height stay the homography's."""
    yaw, t, tilt1, tilt2 = refine_at_threshold(
        f1, f2, (ground.yaw, ground.t, ground.tilt1, ground.tilt2), attitude_sigma_rad, max_err_rad, steps
    )
    t = t if np.dot(t, ground.t) >= 0 else -t  # a refinement from the homography's pose keeps its side
    assert ground.t_per_height is not None  # a ground fit has its translation per height
    return _Fit(
        RelposeModel.GROUND,
        yaw,
        t,
        ground.err_sq,
        float(np.linalg.norm(ground.t_per_height)) * t,
        tilt1,
        tilt2,
        ground.correction,
    )


def _translation_unresolved(
    parallax_rad: float, n_inliers: int, sigma_rad: float, max_err_rad: float, ratio: float
) -> bool:
    """The pure-rotation rule: True where ``n_inliers`` points with this median parallax (after the
    best rotation about z) leave a translation to noise, and a near-vertical one leaves the yaw open
    by pi (``E = [t]x Rz(yaw)`` is the same for yaw + pi when t is along z): under ``ratio`` times the
    threshold (about a pixel) or, where the tracks are finer, half as much again as noise alone
    leaves a pure rotation of that many points. ``ratio`` 0 turns the rule off."""
    floor = _NOISE_PARALLAX_SIGMAS + _NOISE_PARALLAX_POINTS / max(n_inliers, 1)
    return parallax_rad < ratio * min(max_err_rad, _NOISE_PARALLAX_MARGIN * floor * sigma_rad)


def _general_if_attitude_is_worse(
    f1: np.ndarray,
    f2: np.ndarray,
    fit: _Fit,
    essential: _Fit,
    attitude_sigma_rad: tuple[float, float],
    max_err_rad: float,
    seed: int,
    candidates: np.ndarray,
) -> _Fit:
    """The general 5-point pose instead of ``fit`` (the model chosen) when the attitude looks worse than
    its sigma says and the general model explains clearly more points (25%) than the upright essential.
    The attitude is judged by the upright ``essential`` fit, the model that holds for any scene given
    the roll/pitch: its corrections beyond 3 sigma, or under 60% of the points the sampling admitted
    explained. (Judged by a ground homography that GRIC preferred, the points off the ground plane
    would pass for a bad attitude, and over flat ground the general model then finds the plane's
    other pose: a 10 deg tilt and a vertical translation in the ``faults`` flight.) The general model
    is searched among the points the sampling's widened threshold admitted (``candidates``: the true
    inliers and few others, so it is quick), and counted on all. Its rotation is given as a yaw and a
    tilt correction of view 2."""
    thr_sq = max_err_rad**2
    upright = int(np.count_nonzero(essential.err_sq < thr_sq))
    beyond = (
        np.linalg.norm(essential.tilt1) > 3 * attitude_sigma_rad[0]
        or np.linalg.norm(essential.tilt2) > 3 * attitude_sigma_rad[1]
    )
    if not beyond and upright >= _FALLBACK_BELOW_RATIO * np.count_nonzero(candidates):
        return fit
    general = estimate_general_relpose(f1[candidates], f2[candidates], max_err_rad, seed=seed)
    if general is None:
        return fit
    R, t, E = general
    err = sampson_sq_general(E, f1, f2)
    if np.count_nonzero(err < thr_sq) <= _FALLBACK_MARGIN * upright:
        return fit
    yaw, t2, tilt2 = upright_from_general(R, t)
    return _Fit(RelposeModel.GENERAL, yaw, t2, err, None, np.zeros(2), tilt2, Correction.RESOLVED)


@kernel
def _error_sums(err_sq: np.ndarray, thr_sq: float) -> tuple[int, float, float]:
    """Of squared errors (N,): the count under ``thr_sq``, the sum capped at it (MSAC), the sum of those under it."""
    k, capped, inlier = 0, 0.0, 0.0
    for v in err_sq:
        if v < thr_sq:
            k += 1
            inlier += v
        capped += min(v, thr_sq)
    return k, capped, inlier


def _result(fit: _Fit, thr_sq: float, iterations: int, stats: RelposeStats) -> UprightRelpose:
    err_sq = fit.err_sq
    inl = err_sq < thr_sq
    k, capped_sum, inlier_sum = _error_sums(err_sq, thr_sq)
    n = len(err_sq)
    translation = fit.model in (RelposeModel.ESSENTIAL, RelposeModel.GROUND, RelposeModel.GENERAL)
    return UprightRelpose(
        success=translation,
        reason=RelposeFailure.NONE if translation else RelposeFailure.PURE_ROTATION,
        model=fit.model,
        R_2_1=_frozen(rot_z(fit.yaw)),
        t_2_1=_frozen(fit.t),
        yaw_rad=float(fit.yaw),
        t_2_1_per_height=None if fit.t_per_height is None else _frozen(fit.t_per_height),
        inliers=_frozen(inl),
        num_inliers=k,
        inlier_ratio=k / n if n else 0.0,
        score=capped_sum / (thr_sq * n) if n else 1.0,
        residual_rms_rad=math.sqrt(inlier_sum / k) if k else float("nan"),
        iterations=iterations,
        tilt1_rad=_frozen(fit.tilt1),
        tilt2_rad=_frozen(fit.tilt2),
        stats=stats,
        attitude_corrected=fit.correction != Correction.AS_GIVEN,
        attitude_resolved=fit.correction == Correction.RESOLVED,
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
    attitude_sigma_rad: tuple[float, float] | None = None,
    yaw_prior_rad: float | None = None,
) -> CameraRelpose:
    """Relative pose between two camera frames from matched pixels and each view's gravity.

    Args:
        uv1_px, uv2_px: (N, 2) matched pixel coordinates in image 1 and image 2.
        camera: the intrinsics and distortion of both images.
        R_lvl_cam1, R_lvl_cam2: (3, 3) level-from-camera rotations of each view
            (:func:`mavvo.geometry.frames.R_lvl_cam` of the roll/pitch at each exposure).
        max_err_px: inlier threshold in pixels (default ``options.max_err_px``), converted once to an
            angle with the mean focal length.
        seed, options, attitude_sigma_rad, yaw_prior_rad: as for :func:`estimate_upright_relpose` (the
            yaw prior between the level frames: the flight controller's yaw at view 1 minus at view 2).

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
    up = estimate_upright_relpose(
        f1,
        f2,
        max_err_rad=max_err_rad,
        seed=seed,
        options=opt,
        attitude_sigma_rad=attitude_sigma_rad,
        yaw_prior_rad=yaw_prior_rad,
    )
    R1c = tilt_rotation(up.tilt1_rad) @ R1
    R2c = tilt_rotation(up.tilt2_rad) @ R2
    return CameraRelpose(
        success=up.success,
        R_c2_c1=_frozen(R2c.T @ up.R_2_1 @ R1c),
        t_c2_c1=_frozen(R2c.T @ up.t_2_1),
        inliers=up.inliers,
        upright=up,
    )
