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
from mavvo.types import PairedFrame, ScaleSource, StateReason

__all__ = [
    "UNTRUSTED_SCALE_REASON",
    "Measurement",
    "NoPose",
    "keyframe_position",
    "position_noise",
    "unresolved_baseline_m",
]

_REFERENCE_DEPTH_M = 10.0  # the scene depth position_sigma_m is given for
# The motion term follows the tracks' noise within these multiples of track_noise_px: capped at 2x, the
# `faults` camera's tracks dragged by its auto-exposure (residuals up to 0.9 px) were sent with a 2 cm sigma
# while the position moved 0.1 m (one draw at 93.1% inside the 99% ellipse; 95.0% at 10x).
_TRACK_NOISE_MIN, _TRACK_NOISE_MAX = 0.5, 10.0
_STILL_PARALLAX_PX = 1.0  # median parallax below this and nothing triangulated: the camera has not moved
# An untrusted scale source -> the reason the frame is degraded.
UNTRUSTED_SCALE_REASON = {ScaleSource.HELD: StateReason.SCALE_HELD, ScaleSource.ASSUMED: StateReason.SCALE_ASSUMED}
# Frames whose keyframe goes where the filter puts them (keyframe_position).
_FILTER_PLACES_KEYFRAME = frozenset({StateReason.NONE, StateReason.FEW_INLIERS, *UNTRUSTED_SCALE_REASON.values()})
_BASELINE_FACTOR_MIN = 0.5  # a new keyframe's depths follow the filter's baseline within a factor of 2


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
        # the noise position_sigma_per_speed_s is given for). Not with the depth: a track's error
        # grows with its image motion (f x speed / depth) and moves the position by depth / f per
        # pixel, so the product is the speed's. Independent sources: they add in quadrature; a
        # height source's noise moves the position along the translation only.
        tilt_rad = frame.interpolation_sigma_rad if rp.attitude_resolved else math.hypot(*view_attitude_sigmas_rad)
        resid_px = rp.residual_rms_rad * focal_px if math.isfinite(rp.residual_rms_rad) else math.inf
        track_noise = min(max(resid_px / opt.track_noise_px, _TRACK_NOISE_MIN), _TRACK_NOISE_MAX)  # unknown: the most
        c2_m = float(np.linalg.norm(m.c2_m))
        unresolved = math.hypot(
            m.scale.spread * c2_m,
            opt.position_sigma_per_speed_s * speed_m_s * track_noise,
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


def keyframe_position(
    kf: Keyframe,
    m: Measurement,
    reason: StateReason,
    filter_p_ned_m: np.ndarray,
    view_error_m: np.ndarray,
    *,
    held_level: bool = False,
) -> tuple[np.ndarray, float]:
    """Where a new keyframe made from the measured frame goes, and the factor its baseline (and so
    the depths it carries) takes to match; ``reason`` is why the frame is degraded (NONE: tracking).

    ``held_level``: the keyframes hold their level frames as exact (the close range, docs/odometry.md):
    a tracking frame's keyframe then goes where it was measured. Its tilt error is its keyframe's, so
    the error the keyframe's tilt puts in the measured position (depth x tilt) is the one its own
    bearings carry into every later measurement the other way, and the two cancel along the chain;
    the filter's place would break that for the interval's scale error it averages.

    The keyframe goes where the filter puts the frame when that is the better estimate:
    - tracking: the raw measurement at the end of the old keyframe's reach carries that interval's
      largest error (a scale with a wide spread: its sigma says so, and the filter leans on its
      prediction), and would step every later position by it. Its depths are scaled to the
      baseline it is placed with (the filter's along the measured direction over the measured
      one), so the carried scale does not take up the error the position left behind;
    - a held or assumed scale: the measured length is a guess from the scene depth (in a turn on
      the spot, a translation the images barely resolve moved the frame 16 cm); the depths stay
      as measured, in the same guessed units;
    - few inliers: the translation rests on few points (in a fast turn, 53 inliers put a frame
      0.3 m off, and the keyframes of the turn on the spot after it stayed there); the filter
      weighed it by its inflated sigma. The depths stay as measured.
    Placed where the filter puts the frame, the keyframe also takes ``view_error_m`` (3,): the part of
    the measured position the frame's own roll/pitch error made (estimated from the filter's last
    innovation). The keyframe levels its bearings with that roll/pitch, so every later measurement
    from it carries the same error the other way; with it, the two cancel, as they do along a
    frame-to-frame chain. Without it, each keyframe left in the chain's random walk what the filter's
    gain had not taken of its frame's tilt error times the depth (at 3 m, 0.2 deg is 1 cm).
    Other degraded frames keep their raw measurement: their sigma is inflated by the quality cap,
    so the filter's estimate lags (docs/odometry.md). Without a translation (mostly a turn on the
    spot) the keyframe stays where the old one was: the filter's coasted position would let its
    velocity noise into the chain.
    """
    if m.scale is None or reason not in _FILTER_PLACES_KEYFRAME or (held_level and reason == StateReason.NONE):
        return m.p_ned_m, 1.0
    p = filter_p_ned_m + view_error_m
    if reason != StateReason.NONE:
        return p, 1.0  # a guessed length: the depths stay in its units
    d_meas = m.p_ned_m - kf.p_ned_m
    n2 = float(d_meas @ d_meas)
    if not n2 > 0:
        return p, 1.0
    # The filtered baseline along the measured direction, over the measured one.
    k = float((p - kf.p_ned_m) @ d_meas) / n2
    return p, min(max(k, _BASELINE_FACTOR_MIN), 1.0 / _BASELINE_FACTOR_MIN)
