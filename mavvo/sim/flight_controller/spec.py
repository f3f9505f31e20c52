"""The simulated flight controller's settings: sensors, clock, identity and home (a scenario's
``flight_controller:`` keys)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from mavvo.options import bounded
from mavvo.sim.flight_controller.estimator import EstimatorSpec


@dataclass(frozen=True)
class FlightControllerSpec:
    """The simulated flight controller's sensors, clock, identity and position estimator."""

    system_id: int = bounded(1, "MAVLink system id", ge=1, le=255)
    attitude_default_rate_hz: float = bounded(50.0, "ATTITUDE rate when an interval of 0 (default) is requested", gt=0)
    stream_default_rate_hz: float = bounded(10.0, "default rate of the other streams", gt=0)
    attitude_noise_deg: float = bounded(0.1, "roll/pitch noise (1 sigma, per sample)", ge=0)
    attitude_bias_deg: tuple[float, float] = bounded((0.0, 0.0), "roll and pitch bias")
    yaw_noise_deg: float = bounded(0.1, "yaw noise (1 sigma, per sample; an EKF's yaw output is smooth)", ge=0)
    attitude_latency_ms: float = bounded(5.0, "from measurement to sending", ge=0)
    boot_offset_s: float = bounded(30.0, "boot clock at the start of the simulation", ge=0)
    clock_drift_ppm: float = bounded(0.0, "boot clock rate error against the host clock")
    timesync_early_ms: tuple[float, float] = bounded(
        (5.0, 12.0),
        "ArduPilot only: a TIMESYNC answer is stamped this long (uniform between the two) before the request arrived, as measured on a software autopilot",
    )
    rangefinder: bool = bounded(True, "send DISTANCE_SENSOR from a downward laser")
    rangefinder_min_m: float = bounded(0.2, "shortest range", ge=0)
    rangefinder_max_m: float = bounded(40.0, "longest range (beyond: reported as max + 1 cm)", gt=0)
    rangefinder_noise_m: float = bounded(0.02, "range noise (1 sigma)", ge=0)
    rangefinder_dropout: float = bounded(
        0.0, "fraction of readings with no return (a dark or shiny floor): reported out of range", ge=0, lt=1
    )
    baro_noise_m: float = bounded(0.1, "barometric altitude noise (1 sigma)", ge=0)
    home_lat_deg: float = bounded(47.397742, "home latitude", ge=-90, le=90)
    home_lon_deg: float = bounded(8.545594, "home longitude", ge=-180, le=180)
    home_alt_m: float = bounded(488.0, "home altitude above mean sea level")
    estimator: EstimatorSpec = field(default_factory=EstimatorSpec)
    autopilot: Literal["ardupilot", "px4"] = bounded(
        "ardupilot", "which autopilot it says it is (HEARTBEAT) and whose parameters it serves"
    )
    armed: bool = bounded(True, "HEARTBEAT says armed (mavvo preflight --fix refuses to write parameters then) ...")
    arm_at_s: float = bounded(0.0, "... from this simulation time on (before it: disarmed, motors off)", ge=0)
    params: tuple[tuple[str, float], ...] = bounded(
        (), "parameters that differ from the vision-ready defaults of its autopilot, as [NAME, value] pairs"
    )
    ekf_origin: bool = bounded(True, "the EKF has an origin (GPS_GLOBAL_ORIGIN answers a request)")


# Parameters a flight controller set up for mavvo holds (what docs/service.md and preflight ask for).
VISION_READY_PARAMS: dict[str, dict[str, float]] = {
    "ardupilot": {
        "AHRS_EKF_TYPE": 3,
        "VISO_TYPE": 1,
        "VISO_DELAY_MS": 30,
        "VISO_POS_X": 0.0,
        "VISO_POS_Y": 0.0,
        "VISO_POS_Z": 0.0,
        "EK3_SRC1_POSXY": 6,
        "EK3_SRC1_VELXY": 6,
        "EK3_SRC1_POSZ": 1,
        "EK3_SRC1_YAW": 1,
        "GPS1_TYPE": 0,  # no GPS
        "SERIAL2_PROTOCOL": 2,
    },
    "px4": {
        "EKF2_EV_CTRL": 11,
        "EKF2_EV_DELAY": 30,
        "EKF2_HGT_REF": 1,
        "EKF2_EV_POS_X": 0.0,
        "EKF2_EV_POS_Y": 0.0,
        "EKF2_EV_POS_Z": 0.0,
        "MAV_1_CONFIG": 102,
    },
}
