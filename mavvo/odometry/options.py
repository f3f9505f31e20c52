"""Everything the visual odometry (:class:`mavvo.odometry.pipeline.Odometry`) can be told: the
``odometry:`` section of the settings, each key documented beside its default."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from mavvo.estimation.relpose_types import RelposeOptions
from mavvo.odometry.filter import FilterOptions
from mavvo.odometry.frontend import FrontendOptions
from mavvo.odometry.height import HeightOptions
from mavvo.odometry.keyframes import KeyframeOptions
from mavvo.odometry.scale import ScaleOptions
from mavvo.options import bounded

__all__ = ["OdometryOptions"]


@dataclass(frozen=True)
class OdometryOptions:
    """Everything :class:`Odometry` can be told; the defaults suit a 640x480 camera at 20 frames/s."""

    frontend: FrontendOptions = field(default_factory=FrontendOptions)
    ransac: RelposeOptions = field(default_factory=RelposeOptions)
    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    scale: ScaleOptions = field(default_factory=ScaleOptions)
    filter: FilterOptions = field(default_factory=FilterOptions)
    height: HeightOptions = field(default_factory=HeightOptions)
    min_tracks: int = bounded(30, "fewer tracks shared with the keyframe: tracking is lost", ge=5, le=5000)
    min_inliers: int = bounded(20, "fewer inliers: no pose from this frame", ge=5, le=5000)
    good_inliers: int = bounded(120, "inliers for full quality", ge=5, le=5000)
    max_failed_frames: int = bounded(5, "frames in a row without a pose before the keyframe is given up", ge=1, le=1000)
    position_sigma_m: float = bounded(
        0.0008,
        "vision position noise from the image at full quality with the scene 10 m away (it scales with the depth, down to a fifth of it); the other terms: docs/odometry.md",
        gt=0,
        le=100,
    )
    position_sigma_per_speed_s: float = bounded(
        0.003,
        "vision position noise per m/s of speed with the tracks' noise at track_noise_px (the translation's direction and length errors grow with the motion and the noise, at any depth; counted from half to ten times this noise), seconds",
        ge=0,
        le=10,
    )
    track_noise_px: float = bounded(
        0.1,
        "the tracks' noise (RMS of the relative pose's inlier residuals) position_sigma_per_speed_s is given for",
        gt=0,
        le=10,
    )
    yaw_sigma_deg: float = bounded(0.3, "vision yaw noise at full quality", gt=0, le=180)
    attitude_sigma_deg: float = bounded(0.2, "roll/pitch uncertainty reported in the covariance", gt=0, le=90)
    heading_correction_time_s: float = bounded(
        10.0,
        "pull the vision heading toward the flight controller's yaw with this time constant (0: vision's heading alone) ...",
        ge=0,
        le=3600,
    )
    fc_yaw_sigma_deg: float = bounded(
        0.5,
        "... and faster where vision's heading is the less certain: the flight controller's yaw error that does not average out between keyframes (EKF noise, a compass within heading_gate_deg)",
        gt=0,
        le=180,
    )
    heading_source: Literal["ground", "follow", "vision"] = bounded(
        "ground",
        "... when: ground: while the flight controller is disarmed (motors off, the compass clean), and in flight only while its yaw agrees with vision's within heading_gate_deg; follow: always (a GPS or other trustworthy yaw); vision: never after north is taken (EK3_SRC1_YAW 6: its yaw is mavvo's own)",
    )
    heading_gate_deg: float = bounded(
        1.0,
        "heading_source ground, armed: a flight controller's yaw further than this from vision's is a disturbed compass and is left alone ...",
        ge=0,
        le=180,
    )
    heading_gate_sigmas: float = bounded(
        2.0,
        "... or further than this many sigmas of their difference, where that is wider: vision's heading uncertainty grows while the compass is not heard, so a vision that drifted is pulled back and not locked out",
        ge=0,
        le=10,
    )
    degraded_quality_max: int = bounded(50, "quality cap while degraded", ge=1, le=100)
    anchor_sigma_m: float = bounded(
        0.3,
        "how far the flight controller's own position estimate, where tracking is (re)started, may be from the truth (VO_DRIFT)",
        gt=0,
        le=100,
    )
    coast_max_s: float = bounded(
        3.0,
        "vision lost for at most this long (a plain patch of floor under a low camera): tracking goes on where the filter coasted to (the tilt's acceleration, the range's height), no reset; longer: re-initialised",
        ge=0,
        le=60,
    )
    dead_reckon_max_s: float = bounded(
        2.0,
        "re-initialising without the flight controller's position: move the last good pose on by the filter's velocity over at most this long",
        ge=0,
        le=60,
    )
    max_speed_m_s: float = bounded(
        10.0, "the vehicle's top speed: how uncertain a pose held over an outage is", gt=0, le=100
    )
    drift_per_m: float = bounded(0.02, "long-term drift (VO_DRIFT) per metre flown, 1 sigma", ge=0, le=1)
    heading_sigma_deg: float = bounded(
        2.0,
        "heading uncertainty behind VO_DRIFT (the flight controller's yaw followed; without it vision's grows)",
        ge=0,
        le=180,
    )
