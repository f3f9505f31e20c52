"""What mavvo tells the flight controller, as plain field dictionaries (pure; :mod:`mavvo.service.link` encodes).

- VISION_POSITION_ESTIMATE: ``usec`` is the exposure time on the host clock (the clock mavvo answers
  TIMESYNC with), x/y/z the camera centre in metres NED, roll/pitch/yaw of the body in radians,
  ``covariance`` the upper triangle of the 6x6 (x y z roll pitch yaw), row-major, and ``reset_counter``.
- VISION_SPEED_ESTIMATE: velocity NED, its 3x3 covariance row-major, ``reset_counter``.
- ODOMETRY: ``frame_id`` 20 (MAV_FRAME_LOCAL_FRD) for ArduPilot, 1 (MAV_FRAME_LOCAL_NED: mavvo's
  frame is north-aligned) for PX4; ``child_frame_id`` 12 (MAV_FRAME_BODY_FRD), the quaternion w x y z
  of the body, velocity in the body frame, angular rates unknown (NaN), ``estimator_type`` 2 (VISION)
  or 3 (VIO), ``quality`` 1..100, and -1 on the one sent when vision fails.
- STATUSTEXT on state changes, ``mavvo:`` prefixed; NAMED_VALUE_FLOAT health values (``VO_STATE``:
  :data:`STATE_CODES`).
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np

from mavvo.geometry.frames import R_from_euler321, quat_wxyz_from_R
from mavvo.types import PoseEstimate, StateReason, VisionState

Autopilot = Literal["auto", "ardupilot", "px4"]
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12
MAV_ESTIMATOR_TYPE_VISION = 2
MAV_ESTIMATOR_TYPE_VIO = 3
MAV_SEVERITY_CRITICAL = 2
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6

_TRIU6 = np.triu_indices(6)
_STATUSTEXT_MAX = 50
# NAMED_VALUE_FLOAT VO_STATE for each state (every VisionState has one).
STATE_CODES = {
    VisionState.STANDBY: -1,
    VisionState.INITIALISING: 0,
    VisionState.TRACKING: 1,
    VisionState.DEGRADED: 2,
    VisionState.FAILED: 3,
}
_SEVERITY_RANK = {
    VisionState.STANDBY: 0,
    VisionState.INITIALISING: 0,
    VisionState.TRACKING: 0,
    VisionState.DEGRADED: 1,
    VisionState.FAILED: 2,
}
_SEVERITY = {
    VisionState.STANDBY: MAV_SEVERITY_INFO,
    VisionState.INITIALISING: MAV_SEVERITY_INFO,
    VisionState.TRACKING: MAV_SEVERITY_INFO,
    VisionState.DEGRADED: MAV_SEVERITY_WARNING,
    VisionState.FAILED: MAV_SEVERITY_CRITICAL,
}


def upper_triangle(cov: np.ndarray) -> list[float]:
    """The 21 upper-triangle entries of a (6,6) covariance, row-major (MAVLink's layout)."""
    return [float(v) for v in np.asarray(cov, dtype=float)[_TRIU6]]


def usec(t_s: float) -> int:
    """Host seconds to MAVLink microseconds."""
    return int(round(t_s * 1e6))


def vision_position_estimate(est: PoseEstimate) -> dict[str, Any]:
    p, rpy = est.p_ned_m, est.rpy_rad
    return {
        "usec": usec(est.t_exposure_s),
        "x": float(p[0]),
        "y": float(p[1]),
        "z": float(p[2]),
        "roll": float(rpy[0]),
        "pitch": float(rpy[1]),
        "yaw": float(rpy[2]),
        "covariance": upper_triangle(est.covariance),
        "reset_counter": est.reset_counter % 256,
    }


def vision_speed_estimate(est: PoseEstimate) -> dict[str, Any]:
    v = est.v_ned_m_s
    return {
        "usec": usec(est.t_exposure_s),
        "x": float(v[0]),
        "y": float(v[1]),
        "z": float(v[2]),
        "covariance": [float(c) for c in np.asarray(est.v_covariance, dtype=float).ravel()],
        "reset_counter": est.reset_counter % 256,
    }


def autopilot_of(heartbeat_autopilot: int | None, configured: Autopilot) -> Literal["ardupilot", "px4"]:
    """The dialect to speak: as configured, else from the flight controller's HEARTBEAT ``autopilot``
    (ArduPilot when unknown: it is the stricter reader of ODOMETRY frames)."""
    if configured != "auto":
        return configured
    return "px4" if heartbeat_autopilot == MAV_AUTOPILOT_PX4 else "ardupilot"


def odometry(
    est: PoseEstimate,
    autopilot: Literal["ardupilot", "px4"] = "ardupilot",
    estimator_type: Literal["vision", "vio"] = "vision",
) -> dict[str, Any]:
    R_ned_body = R_from_euler321(*est.rpy_rad)
    v_body = R_ned_body.T @ est.v_ned_m_s
    v_cov = np.full((6, 6), math.nan)
    v_cov[:3, :3] = R_ned_body.T @ est.v_covariance @ R_ned_body
    p = est.p_ned_m
    return {
        "time_usec": usec(est.t_exposure_s),
        "frame_id": MAV_FRAME_LOCAL_NED if autopilot == "px4" else MAV_FRAME_LOCAL_FRD,
        "child_frame_id": MAV_FRAME_BODY_FRD,
        "x": float(p[0]),
        "y": float(p[1]),
        "z": float(p[2]),
        "q": [float(c) for c in quat_wxyz_from_R(R_ned_body)],
        "vx": float(v_body[0]),
        "vy": float(v_body[1]),
        "vz": float(v_body[2]),
        "rollspeed": math.nan,
        "pitchspeed": math.nan,
        "yawspeed": math.nan,
        "pose_covariance": upper_triangle(est.covariance),
        "velocity_covariance": upper_triangle(v_cov),
        "reset_counter": est.reset_counter % 256,
        "estimator_type": MAV_ESTIMATOR_TYPE_VIO if estimator_type == "vio" else MAV_ESTIMATOR_TYPE_VISION,
        "quality": max(int(est.quality), -1),
    }


def statustext(state: VisionState, reason: StateReason) -> dict[str, Any]:
    """The STATUSTEXT for entering ``state`` (``mavvo:`` prefixed, cut to MAVLink's 50 characters):
    severity CRITICAL when vision failed, WARNING when degraded, INFO otherwise."""
    return statustext_line(f"mavvo: {state}" + (f" ({reason})" if reason else ""), _SEVERITY[state])


def statustext_merged(changes: list[tuple[VisionState, StateReason]]) -> dict[str, Any]:
    """One STATUSTEXT for the state changes a rate limit held back, in order: the latest state always,
    and the worst one before it when that was worse (a short failure is never hidden by the recovery
    that followed), with the worst one's severity."""
    state, reason = changes[-1]
    worst = max(changes, key=lambda c: _SEVERITY_RANK[c[0]])
    if _SEVERITY_RANK[worst[0]] <= _SEVERITY_RANK[state]:
        return statustext(state, reason)
    first = f"{worst[0]}" + (f" ({worst[1]})" if worst[1] else "")
    return statustext_line(f"mavvo: {first} then {state}" + (f" ({reason})" if reason else ""), _SEVERITY[worst[0]])


def statustext_line(text: str, severity: int = MAV_SEVERITY_INFO) -> dict[str, Any]:
    """A STATUSTEXT of free text (cut to MAVLink's 50 characters)."""
    return {"severity": severity, "text": text[:_STATUSTEXT_MAX].encode("ascii", "replace")}


def named_value_float(t_boot_ms: int, name: str, value: float) -> dict[str, Any]:
    """One health value; ``name`` at most 10 characters."""
    if len(name) > 10:
        raise ValueError(f"named_value_float: name {name!r} longer than 10 characters")
    return {"time_boot_ms": int(t_boot_ms) & 0xFFFFFFFF, "name": name.encode("ascii"), "value": float(value)}
