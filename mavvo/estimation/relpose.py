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

import numpy as np

from mavvo.estimation.attitude_refine import (
    Correction,
)
from mavvo.estimation.estimators import (
    SAMPLE_SIZE,
    PureRotation,
    UprightEssential,
)
from mavvo.estimation.model_selection import Fit, general_if_attitude_is_worse, rotation_fit, select_model
from mavvo.estimation.ransac import lo_ransac
from mavvo.estimation.relpose_types import (
    CameraRelpose,
    RelposeFailure,
    RelposeModel,
    RelposeOptions,
    RelposeStats,
    UprightRelpose,
)
from mavvo.geometry import as_bearing_pair
from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.frames import as_rotation, rot_z
from mavvo.geometry.refine import tilt_rotation
from mavvo.geometry.residuals import rotation_sq
from mavvo.jit import kernel

__all__ = ["estimate_upright_relpose", "estimate_relpose_known_gravity"]

# With roll/pitch uncertain, hypotheses are scored allowing this many sigmas of relative tilt error.
_TILT_SIGMAS = 2.0


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


@kernel
def _all_alike(f1: np.ndarray, f2: np.ndarray, tol: float) -> bool:
    """True when every row of f1 is within ``tol`` of f1's first row, and so for f2 (one point, repeated)."""
    for f in (f1, f2):
        for i in range(1, f.shape[0]):
            if abs(f[i, 0] - f[0, 0]) + abs(f[i, 1] - f[0, 1]) + abs(f[i, 2] - f[0, 2]) > tol:
                return False
    return True


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
    opt = _with_confidence(options or RelposeOptions(), confidence)
    f1, f2 = as_bearing_pair(f1_lvl, f2_lvl, names=("f1_lvl", "f2_lvl"))
    if not (np.isfinite(max_err_rad) and max_err_rad > 0):
        raise ValueError(f"max_err_rad: expected a positive angle, got {max_err_rad}")
    n = len(f1)
    s = SAMPLE_SIZE[opt.minimal_solver]
    if n < s:
        return _failure(RelposeFailure.TOO_FEW_POINTS, n)
    if _all_alike(f1, f2, 1e-9):
        return _failure(RelposeFailure.DEGENERATE_POINTS, n)

    attitude_sigma_rad, sample_thr = _attitude_sigmas(attitude_sigma_rad, opt, max_err_rad)

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
        rotation = _pure_rotation(f1, f2, opt, sample_thr, rng, s)
        if rotation is None:
            return _failure(RelposeFailure.NO_MODEL, n, rs.iterations, RelposeStats(rs))
        fit = rotation
    else:
        fit, essential, sigma, gric = select_model(
            f1, f2, run, opt, max_err_rad, rng, attitude_sigma_rad, sample_thr, yaw_prior_rad
        )
        if attitude_sigma_rad is not None and fit.model != RelposeModel.ROTATION:
            fit = general_if_attitude_is_worse(
                f1, f2, fit, essential, attitude_sigma_rad, max_err_rad, seed, run.inliers
            )
    final = RelposeStats(rs, sigma, gric, time.thread_time() - t_refine)
    return _result(fit, thr_sq, rs.iterations, final)


def _with_confidence(opt: RelposeOptions, confidence: float | None) -> RelposeOptions:
    """``opt`` with the deprecated ``confidence`` keyword of 0.1.0's first releases in place, warned of."""
    if confidence is None:
        return opt
    warnings.warn(
        "estimate_upright_relpose(confidence=...) is deprecated: pass options=RelposeOptions(confidence=...)",
        DeprecationWarning,
        stacklevel=3,
    )
    return dataclasses.replace(opt, confidence=confidence)  # checked where the option is declared


def _pure_rotation(
    f1: np.ndarray, f2: np.ndarray, opt: RelposeOptions, sample_thr: float, rng: np.random.Generator, min_inliers: int
) -> Fit | None:
    """Where no essential model was found: a pure rotation by the same loop, or None."""
    rot = lo_ransac(
        PureRotation(f1, f2), dataclasses.replace(opt, lo_rounds=2, local_optimization=True), sample_thr, rng
    )
    if rot.model is None or np.count_nonzero(rot.inliers) < min_inliers:
        return None
    return rotation_fit(rot.model[0], rotation_sq(rot.model[0], f1, f2))


def _attitude_sigmas(
    attitude_sigma_rad: tuple[float, float] | None, opt: RelposeOptions, max_err_rad: float
) -> tuple[tuple[float, float] | None, float]:
    """The views' roll/pitch sigmas to refine under (as given, else ``opt.tilt_sigma_deg`` for both;
    None where both are 0: roll/pitch taken as exact), and the threshold hypotheses are scored with.
    ValueError for a negative or non-finite sigma."""
    if attitude_sigma_rad is None and opt.tilt_sigma_rad is not None:
        attitude_sigma_rad = (opt.tilt_sigma_rad, opt.tilt_sigma_rad)
    if attitude_sigma_rad is not None and not all(np.isfinite(x) and x >= 0 for x in attitude_sigma_rad):
        raise ValueError(f"attitude_sigma_rad: expected two angles >= 0, got {attitude_sigma_rad}")
    if attitude_sigma_rad is None or max(attitude_sigma_rad) <= 0:
        return None, max_err_rad
    # A hypothesis from roll/pitch off by d1 and d2 misplaces every bearing by up to their relative error.
    return attitude_sigma_rad, math.hypot(max_err_rad, _TILT_SIGMAS * math.hypot(*attitude_sigma_rad))


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


def _result(fit: Fit, thr_sq: float, iterations: int, stats: RelposeStats) -> UprightRelpose:
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
