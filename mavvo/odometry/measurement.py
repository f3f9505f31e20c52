"""One frame's measurement against its keyframe, and how uncertain its position is (docs/odometry.md,
Covariance): the pieces the odometry (:mod:`mavvo.odometry.pipeline`) fuses."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mavvo.estimation.relpose_types import RelposeFailure, UprightRelpose
from mavvo.odometry.keyframes import Keyframe
from mavvo.odometry.options import OdometryOptions
from mavvo.odometry.scale import ScaleEstimate
from mavvo.types import PairedFrame, StateReason

__all__ = ["Measurement", "NoPose", "position_noise", "unresolved_baseline_m"]

_REFERENCE_DEPTH_M = 10.0  # the scene depth position_sigma_m is given for
# The motion term follows the tracks' noise within these multiples of track_noise_px: capped at 2x, the
# `faults` camera's tracks dragged by its auto-exposure (residuals up to 0.9 px) were sent with a 2 cm sigma
# while the position moved 0.1 m (one draw at 93.1% inside the 99% ellipse; 95.0% at 10x).
_TRACK_NOISE_MIN, _TRACK_NOISE_MAX = 0.5, 10.0
_STILL_PARALLAX_PX = 1.0  # median parallax below this and nothing triangulated: the camera has not moved


@dataclass(frozen=True)
class NoPose:
    """Why a frame has no pose against its keyframe."""

    reason: StateReason


@dataclass
class Measurement:
    """A frame's pose against its keyframe, placed in the world (NED, metres, radians)."""

    p_ned_m: np.ndarray
    yaw_rad: float
    relpose: UprightRelpose
    scale: ScaleEstimate | None
    c2_m: np.ndarray  # (3,) the frame's camera centre in the keyframe's level frame, metres
    parallax_px: float
    depth2_m: np.ndarray  # (matched,) metric depths along the current bearings, NaN where none
    parallax_rad: np.ndarray  # (matched,)
    roll_pitch_rad: tuple[float, float]  # the frame's, corrected by vision (the relative pose's tilt of view 2)
    # (K,3) each: the inliers' corrected level bearings in the keyframe's view and the frame's, for the
    # relative yaw's variance, worked out only when the frame becomes a keyframe (heading.relative_yaw_var).
    inlier_bearings: tuple[np.ndarray, np.ndarray]


def _along(direction: np.ndarray, sigma_m: float) -> np.ndarray:
    """(3,3) covariance of an error of ``sigma_m`` (1 sigma) along ``direction`` (none where it is zero)."""
    n_sq = float(direction @ direction)
    if n_sq == 0.0 or sigma_m == 0.0:
        return np.zeros((3, 3))
    return (sigma_m**2 / n_sq) * np.outer(direction, direction)


def unresolved_baseline_m(kf: Keyframe, m: Measurement, depth_m: float, focal_px: float) -> float:
    """How far a frame placed at its keyframe for want of a measured translation may be from it
    (1 sigma, m): the baseline the parallax left after the rotation stands for at the scene's
    depth ``depth_m``, and what the keyframe's own place did not measure (``Keyframe.unmeasured_m``)."""
    return math.hypot(depth_m * m.parallax_px / focal_px, kf.unmeasured_m)


def position_noise(
    opt: OdometryOptions,
    frame: PairedFrame,
    kf: Keyframe,
    m: Measurement,
    *,
    depth_m: float,
    focal_px: float,
    speed_m_s: float,
    view_attitude_sigmas_rad: tuple[float, float],
) -> tuple[np.ndarray | None, np.ndarray]:
    """The position to fuse (None: the translation is not measured) and its noise covariance (3,3)
    m^2 at full quality, the scene ``depth_m`` away, the vehicle at ``speed_m_s``."""
    rp = m.relpose
    p_meas: np.ndarray | None = m.p_ned_m
    along_m, along_dir = 0.0, np.zeros(3)
    if m.scale is not None:
        # Roll/pitch the relative pose kept as given, or corrected with too little parallax to tell
        # a tilt from a translation, turn every bearing by about their error: the translation moves
        # by depth times it. Resolved ones leave what the pairing's interpolation may add.
        # The motion's errors grow with the tracks' noise (the relative pose's residuals, over
        # the noise position_sigma_per_speed_s is given for). Independent sources: they add in
        # quadrature; a height source's noise moves the position along the translation only.
        tilt_rad = frame.interpolation_sigma_rad if rp.attitude_resolved else math.hypot(*view_attitude_sigmas_rad)
        resid_px = rp.residual_rms_rad * focal_px if math.isfinite(rp.residual_rms_rad) else math.inf
        track_noise = min(max(resid_px / opt.track_noise_px, _TRACK_NOISE_MIN), _TRACK_NOISE_MAX)  # unknown: the most
        c2_m = float(np.linalg.norm(m.c2_m))
        unresolved = math.hypot(
            m.scale.spread * c2_m,
            opt.position_sigma_per_speed_s * speed_m_s * track_noise * min(max(depth_m / _REFERENCE_DEPTH_M, 0.2), 1.0),
            depth_m * tilt_rad,
            kf.unmeasured_m,  # measured from a keyframe whose own place was not
        )
        along_m, along_dir = m.scale.sensor_spread * c2_m, m.p_ned_m - kf.p_ned_m
    elif rp.reason == RelposeFailure.PURE_ROTATION or m.parallax_px < _STILL_PARALLAX_PX:
        # No parallax the images resolve (the relative pose says pure rotation, or under a pixel
        # with nothing triangulated): the frame is where its keyframe is.
        unresolved = unresolved_baseline_m(kf, m, depth_m, focal_px)
    else:
        # Parallax, but too few points to triangulate: the translation is not measured.
        p_meas, unresolved = None, 0.0
    iso_m = math.hypot(opt.position_sigma_m * max(depth_m / _REFERENCE_DEPTH_M, 0.2), unresolved)
    return p_meas, iso_m**2 * np.eye(3) + _along(along_dir, along_m)
