"""The shared vocabulary: small frozen dataclasses and closed sets (enums) that cross layers."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

if hasattr(enum, "StrEnum"):  # Python 3.11
    StrEnum = enum.StrEnum
else:

    class StrEnum(str, enum.Enum):  # type: ignore[no-redef]
        """A string enum whose str() and format() are its value (Python 3.10's missing ``enum.StrEnum``)."""

        def __str__(self) -> str:
            return str(self.value)

        def __format__(self, spec: str) -> str:
            return str(self.value).__format__(spec)


class VisionState(StrEnum):
    """What vision is doing. The service reports it (VO_STATE, STATUSTEXT, HEARTBEAT status)."""

    STANDBY = "standby"  #: the service has made no estimate yet (never in an estimate's diagnostics)
    INITIALISING = "initialising"  #: a keyframe was just made: the pose is the anchor
    TRACKING = "tracking"
    DEGRADED = "degraded"  #: a pose with reduced trust (pure rotation, no metric scale, few inliers)
    FAILED = "failed"  #: no pose from vision; nothing is sent


class StateReason(StrEnum):
    """Why the state is not ``tracking``."""

    NONE = ""
    NEW_KEYFRAME = "new_keyframe"
    # No pose from this frame (state failed); the first four are the relative pose's own failures.
    TOO_FEW_POINTS = "too_few_points"
    DEGENERATE_POINTS = "degenerate_points"
    NO_MODEL = "no_model"
    PURE_ROTATION = "pure_rotation"  # also degraded: turning on the spot, translation not observable
    TOO_FEW_INLIERS = "too_few_inliers"
    TRACKING_LOST = "tracking_lost"
    TOO_FEW_FEATURES = "too_few_features"
    # Degraded.
    FEW_INLIERS = "few_inliers"
    SCALE_HELD = "scale_held"
    SCALE_ASSUMED = "scale_assumed"
    ATTITUDE_INTERPOLATED = "attitude_interpolated"  # roll/pitch from samples far apart (a slow ATTITUDE stream)
    # The service, when estimates stop coming.
    NO_ATTITUDE = "no_attitude"
    NO_FRAMES = "no_frames"


class ScaleSource(StrEnum):
    """Where a frame's metric baseline came from (see :mod:`mavvo.odometry.scale`)."""

    RANGEFINDER = "rangefinder"
    ALTITUDE = "altitude"
    FIXED = "fixed"
    CARRIED = "carried"  #: depths carried from the previous keyframe interval
    HELD = "held"  #: the scene depth held from the last measured scale
    ASSUMED = "assumed"  #: ``scale.initial_depth_m``: no measurement yet
    NONE = "none"  #: no translation measured


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    Attributes:
        image: (H,W) uint8 grey image.
        t_exposure_s: middle of the exposure on the host clock (``time.monotonic`` on a drone, the
            simulation clock in the simulator), seconds.
        seq: frame counter of the source, starting at 0; a gap means frames were lost before mavvo.
        exposure_us: the exposure time the camera reports for this frame, microseconds; None where
            the source does not say (V4L2, GStreamer, files).
        gain: the analogue gain the camera reports for this frame (1 = none); None where not said.
    """

    image: np.ndarray
    t_exposure_s: float
    seq: int
    exposure_us: float | None = None
    gain: float | None = None


@dataclass(frozen=True)
class PairedFrame:
    """A camera frame with the flight controller's state at its exposure time, as the odometry takes it.

    Attributes:
        image: (H,W) uint8 grey image.
        t_exposure_s: middle of the exposure, seconds, on the clock the estimates are stamped with.
        seq: frame counter of the source (a gap means frames were lost).
        roll_rad, pitch_rad: ATTITUDE roll and pitch (Euler 3-2-1 of FRD body in NED) at the exposure.
        yaw_rad: ATTITUDE yaw at the exposure: sets north at initialisation and, optionally, slowly
            corrects the vision heading; NaN when unknown.
        range_m: downward rangefinder distance along the body z axis (DISTANCE_SENSOR), or None when
            there is no valid reading (out of range, stale, no sensor).
        height_m: height of the vehicle above the ground it took off from (the flight controller's
            altitude, positive up), or None when unknown.
        fc_position_ned_m: (3,) the flight controller's own estimate of the vehicle's position at the
            exposure (LOCAL_POSITION_NED, its EKF's belief), or None: where tracking is anchored when
            it starts or restarts, so the EKF sees no step.
        attitude_gap_s: time between the two ATTITUDE samples roll/pitch were interpolated between (0:
            one fell on the exposure).
        interpolation_sigma_rad: roll/pitch error the interpolation may add, 1 sigma, radians; above
            the flight controller's own (``odometry.attitude_sigma_deg``) the estimate is degraded.
        fc_armed: whether the flight controller said it was armed at the exposure (its HEARTBEAT), None
            when not heard: its yaw is a clean compass's only while disarmed (motors off).
    """

    image: np.ndarray
    t_exposure_s: float
    seq: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float = float("nan")
    range_m: float | None = None
    height_m: float | None = None
    fc_position_ned_m: np.ndarray | None = None
    attitude_gap_s: float = 0.0
    interpolation_sigma_rad: float = 0.0
    fc_armed: bool | None = None


@dataclass(frozen=True)
class VoDiagnostics:
    """How one frame's estimate came about; every count refers to this frame against its keyframe.

    Attributes:
        state: :class:`VisionState` (never ``standby``).
        reason: :class:`StateReason`, why the state is not ``tracking`` (``NONE`` when it is).
        tracks: features tracked into this frame. inliers, inlier_ratio: of the relative pose.
        parallax_px: median rotation-compensated parallax against the keyframe.
        residual_rms_px: RMS reprojection (Sampson) error of the inliers, pixels.
        scale_source: :class:`ScaleSource`.
        keyframe: a new keyframe was made from this frame.
        attitude_gap_s: between the ATTITUDE samples the frame's roll/pitch came from (0: exact).
        attitude_sigma_deg: roll/pitch uncertainty of the frame, the flight controller's and the
            interpolation's together, 1 sigma.
    """

    state: VisionState
    reason: StateReason = StateReason.NONE
    tracks: int = 0
    inliers: int = 0
    inlier_ratio: float = 0.0
    parallax_px: float = 0.0
    residual_rms_px: float = float("nan")
    scale_source: ScaleSource = ScaleSource.NONE
    keyframe: bool = False
    attitude_gap_s: float = 0.0
    attitude_sigma_deg: float = float("nan")


@dataclass(frozen=True)
class PoseEstimate:
    """The odometry's output for one frame: the camera's pose in the world frame, filtered.

    World frame: the flight controller's local NED frame (see :mod:`mavvo.odometry.pipeline`).

    Attributes:
        t_exposure_s: the frame's exposure time (same clock as :class:`PairedFrame`).
        seq: the frame's sequence number.
        p_ned_m: (3,) position of the camera centre (the vision sensor: set VISO_POS_X/Y/Z or
            EKF2_EV_POS_X/Y/Z to the camera's lever arm), metres.
        rpy_rad: (3,) body roll, pitch (from the flight controller, vision-corrected) and yaw (vision).
        v_ned_m_s: (3,) velocity of the camera centre in NED.
        covariance: (6,6) of (x, y, z, roll, pitch, yaw), m^2 and rad^2.
        v_covariance: (3,3) of the velocity, (m/s)^2.
        quality: 1..100 (higher is better), -1 when failed (then the position is the filter's
            prediction and must not be sent as a measurement).
        reset_counter: bumped once per change of the pose that is not motion (re-initialisation,
            filter restart), mod 256.
        diagnostics: :class:`VoDiagnostics`.
        drift_m: 1-sigma long-term position error since the origin (NAMED_VALUE_FLOAT ``VO_DRIFT``), at
            least the covariance's horizontal sigma.
    """

    t_exposure_s: float
    seq: int
    p_ned_m: np.ndarray
    rpy_rad: np.ndarray
    v_ned_m_s: np.ndarray
    covariance: np.ndarray
    v_covariance: np.ndarray
    quality: int
    reset_counter: int
    diagnostics: VoDiagnostics
    drift_m: float = float("nan")
