"""What the relative pose takes and gives (:mod:`mavvo.estimation.relpose`): its options, its result,
why it failed, how it came about."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Mapping

import numpy as np

from mavvo.estimation.estimators import MinimalSolver, NonminimalSolver
from mavvo.estimation.ransac import RansacOptions, RansacStats
from mavvo.options import bounded
from mavvo.types import StrEnum

__all__ = [
    "CameraRelpose",
    "ModelChoice",
    "RelposeFailure",
    "RelposeModel",
    "RelposeOptions",
    "RelposeStats",
    "UprightRelpose",
]

ModelChoice = Literal["auto", "essential", "ground"]


class RelposeModel(StrEnum):
    """The model a relative pose was found with."""

    ESSENTIAL = "essential"  #: the upright essential matrix (any scene)
    GROUND = "ground"  #: the ground-plane homography (every inlier on the horizontal ground)
    ROTATION = "rotation"  #: a pure rotation: no translation observable
    GENERAL = "general"  #: the 5-point without gravity: roll/pitch were worse than their sigma
    NONE = "none"  #: no pose


class RelposeFailure(StrEnum):
    """Why :func:`estimate_upright_relpose` found no pose with a translation direction."""

    NONE = ""
    TOO_FEW_POINTS = "too_few_points"
    DEGENERATE_POINTS = "degenerate_points"
    NO_MODEL = "no_model"
    PURE_ROTATION = "pure_rotation"  #: ``R_2_1`` holds the yaw, ``t_2_1`` is zero


@dataclass(frozen=True)
class RelposeOptions(RansacOptions):
    """The relative pose's robust estimation (:func:`estimate_upright_relpose`, ``docs/relpose.md``).

    The loop's settings (:class:`~mavvo.estimation.ransac.RansacOptions`) and the models'; the
    ``odometry.ransac`` section of the service's configuration; the defaults suit the service.
    """

    max_err_px: float = bounded(
        1.5,
        "inlier threshold on the Sampson error, pixels (as an angle: divided by the mean focal length)",
        gt=0,
        le=100,
    )
    minimal_solver: MinimalSolver = bounded(
        "3pt", "hypothesis generator: 3pt (batched, fast), 4pt or linear5pt (one sample per call)"
    )
    lo_steps: int = bounded(3, "Gauss-Newton steps per local optimisation", ge=0, le=100)
    refine_steps: int = bounded(8, "Gauss-Newton steps of the final refinement (0: none)", ge=0, le=100)
    nonminimal_solver: NonminimalSolver = bounded(
        "none",
        "re-fit each new best model on its inliers with the 4pt or linear5pt least squares (kept when it scores better)",
    )
    model: ModelChoice = bounded(
        "auto",
        "auto: essential matrix or ground homography by GRIC; essential or ground forces one (pure rotation is always checked)",
    )
    tilt_sigma_deg: float = bounded(
        0.0,
        "let vision correct roll/pitch of both views within this sigma, degrees (0: off; the corrections are reported)",
        ge=0,
        le=30,
    )
    ground_samples: int = bounded(
        16,
        "most 2-point samples for the ground model among the essential inliers (the stopping rule mostly needs a few)",
        ge=1,
        le=10000,
    )
    min_parallax_ratio: float = bounded(
        1.0,
        "median inlier parallax below this many thresholds (or, when less, this many times 1.5 x what noise alone leaves a pure rotation: 3 noise sigmas at 400 inliers, 10 at 15): a pure rotation (translation not observable; 0: GRIC alone decides)",
        ge=0,
        le=100,
    )
    yaw_prior_tolerance_deg: float = bounded(
        30.0,
        "with a yaw prior, hypotheses further from it are dropped (a nadir camera over flat ground sees a twin at yaw + 180 deg)",
        gt=0,
        le=180,
    )
    attitude_correction: bool = bounded(
        True,
        "the odometry corrects roll/pitch of both views under odometry.attitude_sigma_deg (docs/relpose.md: roll/pitch that are not exact)",
    )

    @property
    def tilt_sigma_rad(self) -> float | None:
        """``tilt_sigma_deg`` in radians, None when off."""
        return math.radians(self.tilt_sigma_deg) if self.tilt_sigma_deg > 0 else None


@dataclass(frozen=True)
class RelposeStats:
    """How the estimate came about.

    Attributes:
        sampling: :class:`~mavvo.estimation.ransac.RansacStats` of the essential model's LO-RANSAC
            (samples, hypotheses, local optimisations, the best inlier ratio, CPU time per phase).
        noise_sigma_rad: robust estimate of the bearing noise from the inlier residuals.
        gric: GRIC score of each model considered (lower is better).
        time_refine_s: CPU time of the final refinement and model selection.
    """

    sampling: RansacStats = field(default_factory=RansacStats)
    noise_sigma_rad: float = float("nan")
    gric: Mapping[str, float] = field(default_factory=dict)  # keyed by RelposeModel (a str)
    time_refine_s: float = 0.0

    @property
    def sample_inlier_ratio(self) -> float:
        """The best inlier ratio during sampling (what drove the stopping rule)."""
        return self.sampling.inlier_ratio

    @property
    def required_iterations(self) -> int:
        """Samples the stopping rule asked for at the end."""
        return self.sampling.required_iterations

    @property
    def local_optimizations(self) -> int:
        return self.sampling.local_optimizations


@dataclass(frozen=True)
class UprightRelpose:
    """Relative pose between two level frames.

    Attributes:
        success: a pose with a translation direction was found.
        reason: :class:`RelposeFailure` (``NONE`` on success; ``PURE_ROTATION``: ``R_2_1`` holds the
            estimated yaw and ``t_2_1`` is zero).
        model: :class:`RelposeModel` (for ``general``, the tilt corrections say by how much roll/pitch
            were off).
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
        attitude_corrected: vision corrected roll/pitch; False when they were kept as given (too little
            parallax for the corrections to fit significantly better, or no attitude sigma): then their error moves
            the translation by the scene's depth times it.
        attitude_resolved: the corrections were made with enough parallax to tell a tilt from a
            translation. Corrected without it (they fitted significantly better), their error is about
            the prior's, and it moves the translation as if they had been kept as given.
        stats: :class:`RelposeStats`.
    """

    success: bool
    reason: RelposeFailure
    model: RelposeModel
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
    attitude_corrected: bool = False
    attitude_resolved: bool = False


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
