"""What mavvo tells the flight controller, as plain field dictionaries (pure; :mod:`mavvo.service.link` encodes).

- VISION_POSITION_ESTIMATE: ``usec`` is the exposure time on the host clock (the clock mavvo answers
  TIMESYNC with), x/y/z the camera centre in metres NED, roll/pitch/yaw of the body in radians,
  ``covariance`` the upper triangle of the 6x6 (x y z roll pitch yaw), row-major, and ``reset_counter``.
- VISION_SPEED_ESTIMATE: velocity NED, its 3x3 covariance row-major, ``reset_counter``.
- ODOMETRY: ``frame_id`` 20 (MAV_FRAME_LOCAL_FRD), ``child_frame_id`` 12 (MAV_FRAME_BODY_FRD), the
  quaternion w x y z of the body, velocity in the body frame, angular rates unknown (NaN),
  ``estimator_type`` 2 (VISION), ``quality`` 1..100.
- STATUSTEXT on state changes, ``mavvo:`` prefixed; NAMED_VALUE_FLOAT health values (``VO_STATE``:
  :data:`STATE_CODES`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mavvo.geometry.frames import R_from_euler321, quat_wxyz_from_R
from mavvo.types import PoseEstimate, StateReason, VisionState

MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12
MAV_ESTIMATOR_TYPE_VISION = 2
MAV_SEVERITY_CRITICAL = 2
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6

_TRIU6 = np.triu_indices(6)
_STATUSTEXT_MAX = 50
# NAMED_VALUE_FLOAT VO_STATE for each state (every VisionState has one).
STATE_CODES = {VisionState.STANDBY: -1, VisionState.INITIALISING: 0, VisionState.TRACKING: 1, VisionState.DEGRADED: 2, VisionState.FAILED: 3}
_SEVERITY = {
    VisionState.STANDBY: MAV_SEVERITY_INFO, VisionState.INITIALISING: MAV_SEVERITY_INFO, VisionState.TRACKING: MAV_SEVERITY_INFO,
    VisionState.DEGRADED: MAV_SEVERITY_WARNING, VisionState.FAILED: MAV_SEVERITY_CRITICAL,
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
        "usec": usec(est.t_exposure_s), "x": float(p[0]), "y": float(p[1]), "z": float(p[2]),
        "roll": float(rpy[0]), "pitch": float(rpy[1]), "yaw": float(rpy[2]),
        "covariance": upper_triangle(est.covariance), "reset_counter": est.reset_counter % 256,
    }


def vision_speed_estimate(est: PoseEstimate) -> dict[str, Any]:
    v = est.v_ned_m_s
    return {
        "usec": usec(est.t_exposure_s), "x": float(v[0]), "y": float(v[1]), "z": float(v[2]),
        "covariance": [float(c) for c in np.asarray(est.v_covariance, dtype=float).ravel()],
        "reset_counter": est.reset_counter % 256,
    }


def odometry(est: PoseEstimate) -> dict[str, Any]:
    R_ned_body = R_from_euler321(*est.rpy_rad)
    v_body = R_ned_body.T @ est.v_ned_m_s
    v_cov = np.full((6, 6), math.nan)
    v_cov[:3, :3] = R_ned_body.T @ est.v_covariance @ R_ned_body
    p = est.p_ned_m
    return {
        "time_usec": usec(est.t_exposure_s), "frame_id": MAV_FRAME_LOCAL_FRD, "child_frame_id": MAV_FRAME_BODY_FRD,
        "x": float(p[0]), "y": float(p[1]), "z": float(p[2]), "q": [float(c) for c in quat_wxyz_from_R(R_ned_body)],
        "vx": float(v_body[0]), "vy": float(v_body[1]), "vz": float(v_body[2]),
        "rollspeed": math.nan, "pitchspeed": math.nan, "yawspeed": math.nan,
        "pose_covariance": upper_triangle(est.covariance), "velocity_covariance": upper_triangle(v_cov),
        "reset_counter": est.reset_counter % 256, "estimator_type": MAV_ESTIMATOR_TYPE_VISION, "quality": int(est.quality),
    }


def statustext(state: VisionState, reason: StateReason) -> dict[str, Any]:
    """The STATUSTEXT for entering ``state`` (``mavvo:`` prefixed, cut to MAVLink's 50 characters):
    severity CRITICAL when vision failed, WARNING when degraded, INFO otherwise."""
    text = f"mavvo: {state}" + (f" ({reason})" if reason else "")
    return {"severity": _SEVERITY[state], "text": text[:_STATUSTEXT_MAX].encode("ascii", "replace")}


def named_value_float(t_boot_ms: int, name: str, value: float) -> dict[str, Any]:
    """One health value; ``name`` at most 10 characters."""
    if len(name) > 10:
        raise ValueError(f"named_value_float: name {name!r} longer than 10 characters")
    return {"time_boot_ms": int(t_boot_ms) & 0xFFFFFFFF, "name": name.encode("ascii"), "value": float(value)}
