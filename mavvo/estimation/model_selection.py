"""Which model explains two views best, once the upright essential matrix is found
(:func:`mavvo.estimation.relpose.estimate_upright_relpose`, steps 2-3): its refinement, then GRIC (Torr,
1998) between it, the known-gravity ground homography and a pure rotation, with the pure-rotation rule
for too little parallax; and the general 5-point pose where the attitude looks worse than its sigma."""

from __future__ import annotations

import dataclasses
import functools
import math
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
    GroundHomography,
    yaw_of,
)
from mavvo.estimation.general5pt import estimate_general_relpose, sampson_sq_general
from mavvo.estimation.ransac import RansacResult, lo_ransac
from mavvo.estimation.relpose_types import (
    RelposeModel,
    RelposeOptions,
)
from mavvo.geometry import ground_pose_from_homography
from mavvo.geometry.refine import kabsch, tilt_rotation
from mavvo.geometry.residuals import ground_sq, rotation_sq, rotation_sq_point
from mavvo.jit import kernel

__all__ = ["Fit", "general_if_attitude_is_worse", "rotation_fit", "select_model"]

# Bearings this close to the horizon (z of a unit level bearing) count as not on the ground below.
_MIN_GROUND_Z = 0.02
# GRIC constants for 2-view data (r = 4 dimensions per correspondence), Torr 1998.
_GRIC_R = 4
_GRIC_LAMBDA3 = 2.0
# Manifold dimension d and parameter count k of each model.
_GRIC_DK = {RelposeModel.ESSENTIAL: (3, 3), RelposeModel.GROUND: (2, 4), RelposeModel.ROTATION: (2, 3)}
# Fewer tight inliers than this fraction of the points the widened sampling threshold admitted (or
# corrections beyond 3 sigma): try the general model. Relative to the admitted points, not to all, so
# that a high outlier rate alone never pays for the 5-point search.
_FALLBACK_BELOW_RATIO = 0.6
_FALLBACK_MARGIN = 1.25  # ... and take it when it explains this many times the points
# The pure-rotation rule (:func:`translation_unresolved`). Noise alone leaves a pure rotation a
# median parallax (after the best rotation about z) of a few sigmas, more with fewer points: 99th
# percentiles 8.2 / 5.6 / 4.3 / 3.0 / 2.4 / 2.1 / 2.0 sigmas at 15 / 20 / 30 / 50 / 100 / 200 / 400
# inliers (synthetic, 0.1 px, 200 trials each), about 1.8 + 75 / n. The rule asks for half as much
# again (KLT tails, track bias).
_NOISE_PARALLAX_SIGMAS = 1.8
_NOISE_PARALLAX_POINTS = 75.0
_NOISE_PARALLAX_MARGIN = 1.5


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


def _rotation_model(f1: np.ndarray, f2: np.ndarray, rows: np.ndarray, thr_sq: float) -> np.ndarray | None:
    """The pure rotation (3, 3) fitted on ``rows`` (indices), then twice re-selected among all points
    and refitted; None when the first fit has fewer than two distinct rays."""
    R = _rotation_model_kernel(f1, f2, rows, thr_sq, 2)
    return None if np.isnan(R[0, 0]) else R


@kernel
def _rotation_model_kernel(f1: np.ndarray, f2: np.ndarray, rows: np.ndarray, thr_sq: float, rounds: int) -> np.ndarray:
    """:func:`rotation_model` (NaN for None)."""
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
    run = lo_ransac(
        GroundHomography(f1.take(below, axis=0), f2.take(below, axis=0)), _ground_sampling(opt), threshold_rad, rng
    )
    return None if run.model is None else run.model[0]


@functools.lru_cache(maxsize=8)
def _ground_sampling(opt: RelposeOptions) -> RelposeOptions:
    """The loop's settings for the ground homography: among the essential inliers a ground scene is
    nearly all inliers, so a few samples decide. Made once per settings (options check their fields
    when made, and this runs on every frame)."""
    return dataclasses.replace(
        opt,
        min_iterations=0,
        max_iterations=opt.ground_samples,
        first_block=min(8, opt.ground_samples),
        min_block=1,
        lo_rounds=2,
        local_optimization=True,
    )


@dataclass(frozen=True)
class Fit:
    """One model's answer, before it becomes an :class:`UprightRelpose`."""

    model: RelposeModel
    yaw: float
    t: np.ndarray
    err_sq: np.ndarray  # (N,) on all points
    t_per_height: np.ndarray | None = None
    tilt1: np.ndarray = field(default_factory=lambda: np.zeros(2))
    tilt2: np.ndarray = field(default_factory=lambda: np.zeros(2))
    correction: Correction = Correction.AS_GIVEN


def rotation_fit(R: np.ndarray, err_sq: np.ndarray) -> Fit:
    return Fit(RelposeModel.ROTATION, yaw_of(R), np.zeros(3), err_sq)


def select_model(
    f1: np.ndarray,
    f2: np.ndarray,
    run: RansacResult,
    opt: RelposeOptions,
    max_err_rad: float,
    rng: np.random.Generator,
    attitude_sigma_rad: tuple[float, float] | None,
    sample_thr: float,
    yaw_prior_rad: float | None,
) -> tuple[Fit, Fit, float, dict[RelposeModel, float]]:
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
    essential = Fit(RelposeModel.ESSENTIAL, yaw, t, err_e, None, tilt1, tilt2, correction)

    # GRIC runs on the essential inliers only: its outlier cap differs between models (2 for E, 4
    # for the others), so gross outliers, which fit none of them, would otherwise decide the choice.
    sigma_sq = sigma**2
    inl_idx = np.nonzero(err_e < thr_sq)[0]
    gric = {RelposeModel.ESSENTIAL: _gric(err_e, inl_idx, sigma_sq, RelposeModel.ESSENTIAL)}
    rotation = _rotation_fit_corrected(f1c, f2c, inl_idx, thr_sq, essential)
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
            ground = _ground_fit(H, f1c, f2c, essential)
            gric[RelposeModel.GROUND] = _gric(ground.err_sq, inl_idx, sigma_sq, RelposeModel.GROUND)
            if ground.t_per_height is None:  # no translation: the homography's pose is no ground model
                ground = None
    choice = _gric_choice(gric, opt.model)
    if (
        choice == RelposeModel.GROUND
        and ground is not None
        and attitude_sigma_rad is not None
        and correction != Correction.AS_GIVEN
    ):
        ground = _ground_refined(f1, f2, ground, attitude_sigma_rad, max_err_rad, opt.refine_steps)
    fits = {RelposeModel.ESSENTIAL: essential, RelposeModel.ROTATION: rotation, RelposeModel.GROUND: ground}
    return fits[choice] or essential, essential, sigma, gric


def _rotation_fit_corrected(
    f1c: np.ndarray, f2c: np.ndarray, rows: np.ndarray, thr_sq: float, essential: Fit
) -> Fit | None:
    """The pure rotation fitted on the corrected bearings' ``rows``, with the essential fit's corrections."""
    R = _rotation_model(f1c, f2c, rows, thr_sq)
    if R is None:
        return None
    err_sq = rotation_sq(R, f1c, f2c)
    return Fit(
        RelposeModel.ROTATION,
        yaw_of(R),
        np.zeros(3),
        err_sq,
        None,
        essential.tilt1,
        essential.tilt2,
        essential.correction,
    )


def _gric_choice(gric: dict[RelposeModel, float], asked: str) -> RelposeModel:
    """The model of lowest GRIC among those ``model`` (the option) allows."""
    if asked == "auto":
        allowed: tuple[RelposeModel, ...] = (RelposeModel.ESSENTIAL, RelposeModel.GROUND, RelposeModel.ROTATION)
    elif asked == "ground" and RelposeModel.GROUND in gric:
        allowed = (RelposeModel.GROUND, RelposeModel.ROTATION)
    else:  # essential asked for, or the ground model is not applicable
        allowed = (RelposeModel.ESSENTIAL, RelposeModel.ROTATION)
    return min((m for m in gric if m in allowed), key=gric.__getitem__, default=RelposeModel.ESSENTIAL)


def _ground_fit(H: np.ndarray, f1c: np.ndarray, f2c: np.ndarray, essential: Fit) -> Fit:
    """The ground homography ``H``'s pose on the corrected bearings, with the essential fit's
    corrections; ``t_per_height`` None where its translation is zero."""
    R, t_per_h = ground_pose_from_homography(H)
    nt = float(np.linalg.norm(t_per_h))
    t, t_per_height = (t_per_h / nt, t_per_h) if nt > 0 else (np.zeros(3), None)
    return Fit(
        RelposeModel.GROUND,
        yaw_of(R),
        t,
        ground_sq(H, f1c, f2c),
        t_per_height,
        essential.tilt1,
        essential.tilt2,
        essential.correction,
    )


def _ground_refined(
    f1: np.ndarray,
    f2: np.ndarray,
    ground: Fit,
    attitude_sigma_rad: tuple[float, float],
    max_err_rad: float,
    steps: int,
) -> Fit:
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
    return Fit(
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


def general_if_attitude_is_worse(
    f1: np.ndarray,
    f2: np.ndarray,
    fit: Fit,
    essential: Fit,
    attitude_sigma_rad: tuple[float, float],
    max_err_rad: float,
    seed: int,
    candidates: np.ndarray,
) -> Fit:
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
    return Fit(RelposeModel.GENERAL, yaw, t2, err, None, np.zeros(2), tilt2, Correction.RESOLVED)
