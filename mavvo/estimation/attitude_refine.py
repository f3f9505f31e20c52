"""The upright essential model's pose refined, with roll/pitch corrected under the attitude prior.

The sampling's hypothesis (:func:`mavvo.estimation.relpose.estimate_upright_relpose`) gives a yaw and
a translation direction between two level frames. :func:`refine_essential` refines them on the
inliers; with an attitude sigma, also the roll/pitch corrections of both views under their priors, in
rounds that re-select the inliers from the threshold widened for the tilt error down to the tight
one, from a second start that roll/pitch cannot have misled where one may be needed, with the
translation's sign decided by cheirality on the corrected bearings. :func:`refine_at_threshold`
refines a pose another model found (the ground homography's) by the same rounds. ``docs/relpose.md``
("Roll/pitch that are not exact") gives the measurements.

A pose is ``(yaw, t, tilt1, tilt2)``: radians, the unit translation in the corrected level frame 2,
and the (2,) roll/pitch corrections of each view's level frame in radians.
"""

from __future__ import annotations

import math
from enum import Enum

import cv2
import numpy as np

from mavvo.estimation.estimators import decompose_upright, upright_e, yaw_of
from mavvo.estimation.general5pt import estimate_general_start, estimate_ground_plane_relpose, sees_ground
from mavvo.estimation.ransac import RansacResult
from mavvo.geometry.frames import rot_z
from mavvo.geometry.refine import (
    gauss_newton_upright,
    refine_upright,
    rotate_row,
    tilt_matrix,
    tilt_rotation,
    upright_tuple,
)
from mavvo.geometry.residuals import UNMAPPABLE_SQ, rotation_sq_point, sampson_sq_point, sampson_sq_upright
from mavvo.geometry.upright_pose import behind_upright, point_behind
from mavvo.jit import kernel

__all__ = [
    "Correction",
    "Pose",
    "pose_err_sq",
    "refine_at_threshold",
    "refine_essential",
    "robust_sigma",
    "upright_from_general",
    "yaw_parallax_rad",
]

_TILT_ROUNDS = 8  # refine / re-select rounds under the attitude prior, at most
# With less median parallax than this many sigmas of the views' relative roll/pitch error or this many
# inlier thresholds, a tilt and a translation explain nearly the same flow: roll/pitch are corrected
# only where that lowers the posterior cost by this much (chi-square, 4 corrections, p = 0.999).
_TILT_MIN_PARALLAX_SIGMAS = 1.0
_TILT_MIN_PARALLAX_THRESHOLDS = 3.0
_CORRECTION_MIN_COST_DROP = 18.5
# Refinements weigh inliers with a Cauchy loss of this many noise sigmas (95% efficiency for Gaussian noise).
_CAUCHY_NOISE_SIGMAS = 2.385
# ... and of this many while the attitude rounds' threshold is still widened for the tilt error the
# hypothesis inherits, where the parallax tells a tilt from a translation: that set holds outliers and
# the pose is still off, and at 2.385 they pulled the rounds to other fixed points (docs/relpose.md has
# the rotation errors on forward flights' pairs and the paper's scenes). Tighter everywhere, the paper's
# scenes lost: at the threshold their Gaussian noise wants the efficient loss.
_CAUCHY_WIDE_NOISE_SIGMAS = 1.0
# Parallax under this many noise sigmas is noise to a single point (its side, in the sign's vote).
_PARALLAX_NOISE_SIGMAS = 10.0
# The refined translation's sign is reversed where it puts at least this fraction of its inliers
# behind a view and the reverse puts none (where both put some, neither is in the data).
_SIGN_MIN_BEHIND = 0.05
# Over the ground, refinements whose translations are further apart than this are two answers, not one
# (closer, the choice between them is noise: the simulated take-off's ATE). The general 5-point's start
# has no such rule: its refinement is kept wherever it is the cheaper (below).
_OTHER_ANSWER_DEG = 10.0
# The ground homography's start is tried with less median parallax than this many relative attitude
# sigmas: only where the tilt's share of the flow is large enough to mislead a 3-point hypothesis (the
# survey pairs it put right had 1-15 px of parallax against 6-12 px of relative sigma).
_PLANE_START_PARALLAX_SIGMAS = 3.0
# ... and taken where its translation makes this many noise sigmas of parallax (or the threshold):
# noise starts in a spin on the spot had 1.6-3.9, the survey pairs it put right 9.9-23.
_PLANE_START_NOISE_SIGMAS = 5.0


class Correction(Enum):
    """How roll/pitch went into a fit."""

    AS_GIVEN = 0
    FITTED = 1  # corrected with little parallax, where that fitted significantly better: about the prior's error left
    RESOLVED = 2  # corrected with parallax enough to tell a tilt from a translation


Pose = tuple[float, np.ndarray, np.ndarray, np.ndarray]  # yaw, unit t, tilt1, tilt2 (rad) in the corrected level frames


@kernel
def yaw_parallax_rad(yaw: float, f1: np.ndarray, f2: np.ndarray, rows: np.ndarray) -> float:
    """Median over ``rows`` (indices) of the chord |f2 - Rz(yaw) f1|: the flow that a rotation about z
    leaves, about the parallax angle for small angles (radians); 0 without rows."""
    if rows.shape[0] == 0:
        return 0.0
    R = np.zeros((3, 3))
    R[0, 0], R[0, 1], R[1, 0], R[1, 1], R[2, 2] = math.cos(yaw), -math.sin(yaw), math.sin(yaw), math.cos(yaw), 1.0
    chord = np.empty(rows.shape[0])
    for k in range(rows.shape[0]):
        chord[k] = math.sqrt(2.0 * rotation_sq_point(R, f1, f2, rows[k]))
    return float(np.median(chord))


def refine_essential(
    f1: np.ndarray,
    f2: np.ndarray,
    run: RansacResult,
    max_err_rad: float,
    attitude_sigma_rad: tuple[float, float] | None,
    sample_thr: float,
    yaw_prior_rad: float | None,
    *,
    steps: int,
    yaw_tolerance_rad: float,
) -> tuple[Pose, Correction]:
    """The sampling's essential model refined, and how roll/pitch went into it.

    Without an attitude sigma, yaw and translation with roll/pitch as given. With one, under the
    attitude prior (:func:`_refine_with_attitude`, and a second start, :func:`_second_start`: over the
    ground where the tilt's share of the flow can mislead the hypothesis, elsewhere wherever the
    parallax gives the general 5-point a translation). With less median parallax than the relative attitude sigma
    or a few thresholds a tilt and a translation explain nearly the same flow, and the corrections are
    kept only where they fit significantly better than roll/pitch as given: their posterior cost lower
    by ``_CORRECTION_MIN_COST_DROP`` (a likelihood-ratio test of the 4 corrections). Exact roll/pitch
    then stay as given (a free tilt would fit noise and pass a pixel's parallax off as a tilt), while a
    flight controller's 0.2-1 deg errors, which leave a nadir view over flat ground with a translation
    tens of degrees off, are corrected.

    Args:
        f1, f2: (N, 3) unit bearings in the level frames of view 1 and view 2 (as given).
        run: the essential model's sampling (its model, inliers and squared errors).
        max_err_rad: the inlier threshold (Sampson error, an angle).
        attitude_sigma_rad: roll/pitch sigma of view 1 and of view 2, or None (taken as exact).
        sample_thr: the sampling's threshold, widened for the tilt error a hypothesis inherits.
        yaw_prior_rad: the expected yaw, or None; a second start further from it than
            ``yaw_tolerance_rad`` is not taken.
        steps: Gauss-Newton steps of the refinement (``RelposeOptions.refine_steps``).
    """
    assert run.model is not None
    pose = decompose_upright(run.model[0], f1.compress(run.inliers, axis=0), f2.compress(run.inliers, axis=0))
    assert pose is not None  # a model has at least its own sample as inliers
    yaw, t = pose
    if attitude_sigma_rad is None:
        return _refine_uncorrected(f1, f2, yaw, t, max_err_rad, steps), Correction.AS_GIVEN
    inl = run.err_sq < max_err_rad**2  # the points the hypothesis fits closely: outliers would inflate it
    parallax = yaw_parallax_rad(yaw, f1, f2, np.flatnonzero(inl))
    relative_sigma = math.hypot(*attitude_sigma_rad)
    resolved = parallax >= max(_TILT_MIN_PARALLAX_SIGMAS * relative_sigma, _TILT_MIN_PARALLAX_THRESHOLDS * max_err_rad)
    # With parallax enough to tell a tilt from a translation, the widened rounds weigh with one noise
    # sigma. With less, the fit is near-degenerate and a tight loss let it settle on a subset: in a spin
    # on the spot (`yaw_spin`, seed 102) essential fits on 72-85 points where a rotation explained 218-229.
    wide_c = _CAUCHY_WIDE_NOISE_SIGMAS if resolved else _CAUCHY_NOISE_SIGMAS
    corrected = _refine_with_attitude(f1, f2, yaw, t, attitude_sigma_rad, sample_thr, max_err_rad, steps, wide_c)
    # A second start where one may be needed: over the ground where the tilt's share of the flow is large;
    # elsewhere where the tilt error the hypothesis may inherit is more than the threshold allows for and
    # the parallax is enough for the general 5-point's translation (with less it is noise).
    ground = parallax < _PLANE_START_PARALLAX_SIGMAS * relative_sigma
    general = relative_sigma >= max_err_rad and parallax >= _TILT_MIN_PARALLAX_THRESHOLDS * max_err_rad
    if ground or general:
        corrected = _second_start(
            f1,
            f2,
            run.inliers,
            corrected,
            attitude_sigma_rad,
            sample_thr,
            max_err_rad,
            steps,
            yaw_prior_rad,
            yaw_tolerance_rad,
            ground,
            general,
            wide_c,
        )
    if resolved:
        return corrected, Correction.RESOLVED
    as_given = _refine_uncorrected(f1, f2, yaw, t, max_err_rad, steps)
    cost_corrected, cost_as_given = _posterior_costs(f1, f2, (corrected, as_given), attitude_sigma_rad, max_err_rad)
    if cost_as_given - cost_corrected >= _CORRECTION_MIN_COST_DROP:
        return corrected, Correction.FITTED
    return as_given, Correction.AS_GIVEN


def _refine_uncorrected(
    f1: np.ndarray, f2: np.ndarray, yaw: float, t: np.ndarray, max_err_rad: float, steps: int
) -> Pose:
    """Yaw and translation refined on the inliers (Cauchy loss at ``_CAUCHY_NOISE_SIGMAS`` noise
    sigmas), which are then re-selected for a second round; roll/pitch as given (zero corrections)."""
    zero = np.zeros(2)
    for k in (steps, min(steps, 2)) if steps > 0 else ():
        err = pose_err_sq((yaw, t, zero, zero), f1, f2, max_err_rad)
        inl = err < max_err_rad**2
        noise = robust_sigma(err[inl], max_err_rad)
        fit = refine_upright(
            yaw,
            t,
            f1.compress(inl, axis=0),
            f2.compress(inl, axis=0),
            iterations=k,
            robust_scale_rad=_CAUCHY_NOISE_SIGMAS * noise,
        )
        yaw, t = fit.yaw_rad, fit.t_2_1
    return yaw, t, zero, zero


def pose_err_sq(pose: Pose, f1: np.ndarray, f2: np.ndarray, max_err_rad: float) -> np.ndarray:
    """:func:`_corrected_err_sq` of a pose."""
    yaw, t, tilt1, tilt2 = pose
    return _corrected_err_sq(np.array([yaw, *t, *tilt1, *tilt2]), f1, f2, max_err_rad)


def _second_start(
    f1: np.ndarray,
    f2: np.ndarray,
    candidates: np.ndarray,
    pose: Pose,
    attitude_sigma_rad: tuple[float, float],
    sample_thr: float,
    max_err_rad: float,
    steps: int,
    yaw_prior_rad: float | None,
    yaw_tolerance_rad: float,
    ground: bool,
    general: bool,
    wide_c_sigmas: float,
) -> Pose:
    """``pose`` (refined under the attitude prior from the sampling's hypothesis), or the pose refined
    from a start that roll/pitch cannot have misled, when that is a better one (over the ground, only
    when it is also another answer). docs/relpose.md (Roll/pitch that are not exact) has the cases and
    the figures.

    A 3-point hypothesis made with roll/pitch off by a few tenths of a degree can take the tilt's share
    of the flow for translation and refine into a local minimum of its own: over flat ground a tilt and
    a sideways translation explain the same flow to first order. There, with ``ground`` (the tilt's
    share of the flow large), the start is the ground homography's pose
    (:func:`~mavvo.estimation.general5pt.estimate_ground_plane_relpose`), taken where its translation
    makes ``_PLANE_START_NOISE_SIGMAS`` noise sigmas of parallax or the threshold
    (:func:`_min_parallax_rad`: noise starts in a spin on the spot would be taken at any parallax, and
    at the pure-rotation rule's ten sigmas a real one was missed). Where the scene is not mostly below
    the horizon, with ``general`` (parallax enough for a translation, and a relative attitude sigma of
    a threshold or more: with less, the tilt error a hypothesis inherits is within the noise the
    threshold allows), the start is the general 5-point's pose
    (:func:`~mavvo.estimation.general5pt.estimate_general_start`). Over a plane the 5-point's two
    poses fit alike, so it is no start there.

    Refined from the start under the same prior, the answer replaces ``pose`` when its yaw keeps to
    the prior and its posterior cost is lower, and over the ground only when its translation is another
    answer, ``_OTHER_ANSWER_DEG`` away: closer, the two are one answer and the first is kept (a choice
    between two refinements of one answer is noise). The 5-point's start is refined however close it
    is: the hypothesis was made with roll/pitch as given, and the refinement's re-selected inliers keep
    something of where it started. The start's translation sign is decided by cheirality first (the
    refinement counts points behind a view as outliers)."""
    t = pose[1]
    c1, c2 = f1.compress(candidates, axis=0), f2.compress(candidates, axis=0)
    on_ground = sees_ground(c1, c2)
    start = None
    if on_ground and ground:
        start = estimate_ground_plane_relpose(c1, c2, sample_thr)
        if start is not None:
            err = pose_err_sq(pose, f1, f2, max_err_rad)
            t_per_d = float(np.linalg.norm(start[1]))  # about the parallax it makes, radians
            floor = _min_parallax_rad(err[err < max_err_rad**2], max_err_rad, _PLANE_START_NOISE_SIGMAS)
            start = (start[0], start[1] / t_per_d) if t_per_d >= floor else None
    elif not on_ground and general:
        start = estimate_general_start(c1, c2, max_err_rad, rot_z(pose[0]))
    if start is None:
        return pose

    def same_answer(u: np.ndarray) -> bool:  # over the ground only (above)
        return on_ground and abs(float(np.dot(u, t))) >= math.cos(math.radians(_OTHER_ANSWER_DEG))

    start_yaw, start_t, start_tilt2 = upright_from_general(*start)
    if same_answer(start_t):
        return pose  # not worth a second refinement
    start_yaw, start_t, _, _ = _in_front((start_yaw, start_t, np.zeros(2), start_tilt2), f1, f2, max_err_rad)
    alt = _refine_with_attitude(
        f1, f2, start_yaw, start_t, attitude_sigma_rad, sample_thr, max_err_rad, steps, wide_c_sigmas, tilt2=start_tilt2
    )
    if same_answer(alt[1]):
        return pose
    if yaw_prior_rad is not None and abs(math.remainder(alt[0] - yaw_prior_rad, math.tau)) > yaw_tolerance_rad:
        return pose
    cost_alt, cost = _posterior_costs(f1, f2, (alt, pose), attitude_sigma_rad, max_err_rad)
    return alt if cost_alt < cost else pose


def _min_parallax_rad(
    err_sq_inliers: np.ndarray, max_err_rad: float, noise_sigmas: float = _PARALLAX_NOISE_SIGMAS
) -> float:
    """The parallax under which one point's translation is noise: the threshold, or ``noise_sigmas``
    noise sigmas (from a fit's inlier errors) where the tracks are finer."""
    return min(max_err_rad, noise_sigmas * robust_sigma(err_sq_inliers, max_err_rad))


def _in_front(pose: Pose, f1: np.ndarray, f2: np.ndarray, max_err_rad: float) -> Pose:
    """The pose with the sign of its translation (and for a vertical one, the yaw's twin) that puts
    the points it fits in front of both views."""
    yaw, t, tilt1, tilt2 = pose
    g1, g2, _ = _fitted_bearings(pose, f1, f2, max_err_rad)
    decided = decompose_upright(upright_e(yaw, t), g1, g2)
    return pose if decided is None else (decided[0], decided[1], tilt1, tilt2)


def _fitted_bearings(
    pose: Pose, f1: np.ndarray, f2: np.ndarray, max_err_rad: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bearings (n, 3) of the points the pose fits (Sampson error under ``max_err_rad``), with its
    roll/pitch corrections applied, and their squared errors (n,)."""
    yaw, t, tilt1, tilt2 = pose
    g1, g2 = f1 @ tilt_rotation(tilt1).T, f2 @ tilt_rotation(tilt2).T
    err = sampson_sq_upright(upright_e(yaw, t)[None], g1, g2)[0]
    inl = err < max_err_rad**2
    return g1.compress(inl, axis=0), g2.compress(inl, axis=0), err[inl]


def _posterior_costs(
    f1: np.ndarray, f2: np.ndarray, poses: tuple[Pose, ...], attitude_sigma_rad: tuple[float, float], max_err_rad: float
) -> list[float]:
    """The negative log posterior of each pose, up to a shared constant: its Sampson errors (capped at
    the threshold, MSAC) over a noise sigma shared by all (the smallest of their robust estimates, so
    that a worse fit does not shrink its own cost), plus ``sum (d / sigma_view)^2`` of its tilt
    corrections d."""
    thr_sq = max_err_rad**2
    errs = [pose_err_sq(pose, f1, f2, max_err_rad) for pose in poses]
    noise_sq = min(robust_sigma(e[e < thr_sq], max_err_rad) for e in errs) ** 2
    s1_sq, s2_sq = attitude_sigma_rad[0] ** 2, attitude_sigma_rad[1] ** 2
    return [
        float(np.minimum(e, thr_sq).sum() / noise_sq + d1 @ d1 / s1_sq + d2 @ d2 / s2_sq)
        for e, (_, _, d1, d2) in zip(errs, poses)
    ]


def upright_from_general(R_2_1: np.ndarray, t_2_1: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """A general pose between the level frames as (yaw, t in the corrected level frame 2, tilt
    correction of view 2): ``R_2_1 = T2^T Rz(yaw)`` with all of the tilt on view 2."""
    # T2 = Rz(yaw) R^T, its axis made horizontal by moving the yaw (T2's rotation about z changes one
    # for one with it), so T2 is exactly a tilt.
    yaw = yaw_of(R_2_1)
    for _ in range(4):
        w = cv2.Rodrigues(rot_z(yaw) @ R_2_1.T)[0][:, 0]
        yaw -= float(w[2])
    T2 = rot_z(yaw) @ R_2_1.T
    return yaw, T2 @ t_2_1, cv2.Rodrigues(T2)[0][:2, 0]


def _refine_with_attitude(
    f1: np.ndarray,
    f2: np.ndarray,
    yaw: float,
    t: np.ndarray,
    attitude_sigma_rad: tuple[float, float],
    sample_thr: float,
    max_err_rad: float,
    steps: int,
    wide_c_sigmas: float,
    tilt1: np.ndarray | None = None,
    tilt2: np.ndarray | None = None,
) -> Pose:
    """Yaw, translation direction and the roll/pitch corrections of both views under the attitude
    prior, from the sampling's wide inlier set down to the tight one: each round refines on the current
    inliers (a Cauchy loss of ``wide_c_sigmas`` noise sigmas while the threshold is widened, of
    ``_CAUCHY_NOISE_SIGMAS`` at the tight one, never wider than the round's threshold), re-selects
    them with the corrected bearings and halves the threshold, until it is ``max_err_rad`` and the
    inliers stop changing. Re-selecting with the refined model is what removes the bias a first,
    outlier-tainted inlier set leaves; the translation's sign is then judged by cheirality. Compiled."""
    rounds = _attitude_rounds_from(
        f1, f2, yaw, t, attitude_sigma_rad, sample_thr, max_err_rad, steps, tilt1, tilt2, wide_c_sigmas
    )
    return _sign_by_cheirality(rounds, f1, f2, max_err_rad)


def _attitude_rounds_from(
    f1: np.ndarray,
    f2: np.ndarray,
    yaw: float,
    t: np.ndarray,
    attitude_sigma_rad: tuple[float, float],
    sample_thr: float,
    max_err_rad: float,
    steps: int,
    tilt1: np.ndarray | None,
    tilt2: np.ndarray | None,
    wide_c_sigmas: float,
) -> Pose:
    """:func:`_attitude_rounds` from a pose (yaw and t, and the views' roll/pitch corrections, zero
    for None), as a pose; the sign of t is not judged again. The rounds start at ``sample_thr`` (the
    first round's threshold, halved each round down to ``max_err_rad``) with a Cauchy scale of
    ``wide_c_sigmas`` noise sigmas while it is wider."""
    sigmas = np.array([max(s, 1e-6) for s in attitude_sigma_rad])  # a view given as exact: held by a stiff prior
    x = np.zeros(8)  # (yaw, unit t, tilt1, tilt2): the kernel's state, updated in place
    x[0], x[1:4] = yaw, np.asarray(t, dtype=float) / np.linalg.norm(t)
    if tilt1 is not None:
        x[4:6] = tilt1
    if tilt2 is not None:
        x[6:8] = tilt2
    _attitude_rounds(x, f1, f2, sigmas, sample_thr, max_err_rad, steps, _TILT_ROUNDS, wide_c_sigmas)
    return float(np.arctan2(np.sin(x[0]), np.cos(x[0]))), x[1:4].copy(), x[4:6].copy(), x[6:8].copy()


def refine_at_threshold(
    f1: np.ndarray,
    f2: np.ndarray,
    pose: Pose,
    attitude_sigma_rad: tuple[float, float],
    max_err_rad: float,
    steps: int,
) -> Pose:
    """``pose`` (from another model: the ground homography's) refined with the roll/pitch corrections
    under the attitude prior by the same rounds, at the inlier threshold throughout (so with the
    efficient Cauchy scale); the sign of t is not judged again."""
    yaw, t, tilt1, tilt2 = pose
    return _attitude_rounds_from(
        f1, f2, yaw, t, attitude_sigma_rad, max_err_rad, max_err_rad, steps, tilt1, tilt2, _CAUCHY_NOISE_SIGMAS
    )


def _sign_by_cheirality(pose: Pose, f1: np.ndarray, f2: np.ndarray, max_err_rad: float) -> Pose:
    """The pose, or the pose with -t where t puts at least ``_SIGN_MIN_BEHIND`` of its inliers behind
    a view and -t none, judged on the corrected bearings and only by points with more parallax than
    :func:`_min_parallax_rad` (with less, the side is noise; the threshold alone left survey pair 107,
    0.7 px of parallax against 0.02 px of noise, without a voter and 178 deg off). Where both signs put
    some behind, the data do not decide and the sign is kept: a vote of all points flipped near-ties
    in a spin on the spot.

    The Sampson cost of the refinement is the same for t and -t; the sign came from the hypothesis,
    decided on the bearings as given, where a relative tilt error larger than the parallax can
    reverse the flow."""
    yaw, t, tilt1, tilt2 = pose
    g1, g2, err = _fitted_bearings(pose, f1, f2, max_err_rad)
    floor = _min_parallax_rad(err, max_err_rad)
    wrong = np.count_nonzero(behind_upright(yaw, t, g1, g2, floor)) >= _SIGN_MIN_BEHIND * len(g1)
    return (yaw, -t, tilt1, tilt2) if wrong and not np.any(behind_upright(yaw, -t, g1, g2, floor)) else pose


@kernel
def _robust_sigma_kernel(err_sq_inliers: np.ndarray, max_err_rad: float) -> float:
    """:func:`robust_sigma`, compiled (the attitude rounds call it inside their kernel)."""
    if err_sq_inliers.size == 0:
        return max_err_rad
    return max(1.4826 * np.median(np.sqrt(err_sq_inliers)), 0.01 * max_err_rad)


@kernel
def _corrected_err_sq(x: np.ndarray, f1: np.ndarray, f2: np.ndarray, max_err_rad: float) -> np.ndarray:
    """Sampson errors (N,) of the state x = (yaw, t, d1, d2) on the tilt-corrected bearings, and
    ``UNMAPPABLE_SQ`` for points with more than ``max_err_rad`` of parallax that it puts behind a view.

    A track can slide along its epipolar line the wrong way (a corner that is no point of the scene,
    where a texture meets the haze at the horizon): the Sampson error misses it and cheirality does not.
    The forward camera's pairs of ``benchmarks/relpose_flight.py`` have such tracks, and refined on,
    they move the translation (docs/relpose.md). Cheirality rejects tracks,
    not the pose: where it would reject most of the inliers, the pose is a twin (over flat ground with
    a pixel of parallax, a vertical translation with the yaw off by pi fits as well), which the pure
    rotation rule and the decomposition deal with, and the errors are left as they are."""
    T1, T2 = tilt_matrix(x[4], x[5]), tilt_matrix(x[6], x[7])
    e = upright_tuple(x[0], x[1], x[2], x[3])
    c, s = math.cos(x[0]), math.sin(x[0])
    min_det = math.sin(max_err_rad) ** 2  # less parallax than the threshold: the side is noise
    max_sq = max_err_rad * max_err_rad
    n = f1.shape[0]
    err = np.empty(n)
    behind = np.empty(n, dtype=np.bool_)
    inliers = behind_inliers = 0
    for i in range(n):
        p0, p1, p2 = rotate_row(T1, f1, i)
        q0, q1, q2 = rotate_row(T2, f2, i)
        err[i] = sampson_sq_point(e, p0, p1, p2, q0, q1, q2)
        behind[i] = point_behind(c, s, x[1], x[2], x[3], p0, p1, p2, q0, q1, q2, min_det)
        inl = err[i] < max_sq
        inliers += inl
        behind_inliers += inl and behind[i]
    if 2 * behind_inliers < inliers:
        for i in range(n):
            if behind[i]:
                err[i] = UNMAPPABLE_SQ
    return err


@kernel
def _attitude_rounds(
    x: np.ndarray,
    f1: np.ndarray,
    f2: np.ndarray,
    sigmas: np.ndarray,
    sample_thr: float,
    max_err_rad: float,
    steps: int,
    rounds: int,
    wide_c_sigmas: float,
) -> None:
    """The rounds of :func:`_refine_with_attitude` on x = (yaw, unit t, d1, d2), updated in place; x
    is put back to its start when the corrections lost most of the start's tight inliers. The Cauchy
    scale is ``wide_c_sigmas`` noise sigmas while the threshold is wider than ``max_err_rad``,
    ``_CAUCHY_NOISE_SIGMAS`` at it, and never more than the round's threshold."""
    start = x.copy()
    max_sq = max_err_rad * max_err_rad
    start_inliers = np.count_nonzero(_corrected_err_sq(x, f1, f2, max_err_rad) < max_sq)
    prior_w = np.array([1.0 / sigmas[0], 1.0 / sigmas[0], 1.0 / sigmas[1], 1.0 / sigmas[1]])
    thr = sample_thr
    previous = np.zeros(f1.shape[0], dtype=np.bool_)
    have_previous = False
    for _ in range(rounds):
        err = _corrected_err_sq(x, f1, f2, max_err_rad)
        inl = err < thr * thr
        if np.count_nonzero(inl) < 5 or steps == 0:
            break
        if thr == max_err_rad and have_previous and np.all(inl == previous):
            break
        noise = _robust_sigma_kernel(err[inl], max_err_rad)
        # A few steps per round from the warm start: the rounds go on until the inliers settle, not
        # until the steps do (they close about half the distance each; converging every round was
        # within the tie with PoseLib on the forward pairs and cost 15-40% more time, docs/relpose.md).
        c_sigmas = wide_c_sigmas if thr > max_err_rad else _CAUCHY_NOISE_SIGMAS
        gauss_newton_upright(x, f1[inl], f2[inl], min(steps, 3), True, prior_w, 1.0 / noise, min(thr, c_sigmas * noise))
        previous, have_previous = inl, True
        thr = max(max_err_rad, 0.5 * thr)
    if np.count_nonzero(_corrected_err_sq(x, f1, f2, max_err_rad) < max_sq) < 0.5 * start_inliers:
        # The corrections lost most of what the hypothesis explained (a start among outliers): keep it. A
        # few fewer tight inliers is normal: the hypothesis may fit a subset closely and the rest badly.
        x[:] = start


def robust_sigma(err_sq_inliers: np.ndarray, max_err_rad: float) -> float:
    """Noise sigma from inlier residuals (MAD), floored at 1% of the threshold."""
    return float(_robust_sigma_kernel(np.ascontiguousarray(err_sq_inliers, dtype=np.float64), float(max_err_rad)))
