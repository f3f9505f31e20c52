"""The fields mavvo sends: covariance layout, frames of ODOMETRY, text limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mavvo.geometry.frames import R_from_euler321
from mavvo.service import messages
from mavvo.types import PoseEstimate, StateReason, VisionState, VoDiagnostics


def estimate(yaw_rad=0.0, v=(1.0, 0.0, 0.0), quality=80, reset=3):
    cov = np.zeros((6, 6))
    cov[np.triu_indices(6)] = np.arange(1, 22)  # entry k+1 at the k-th upper-triangle place, row-major
    cov = cov + np.triu(cov, 1).T
    return PoseEstimate(
        t_exposure_s=12.3456789,
        seq=7,
        p_ned_m=np.array([1.0, 2.0, -3.0]),
        rpy_rad=np.array([0.1, -0.05, yaw_rad]),
        v_ned_m_s=np.array(v),
        covariance=cov,
        v_covariance=np.diag([0.01, 0.02, 0.03]),
        quality=quality,
        reset_counter=reset,
        diagnostics=VoDiagnostics("tracking"),
    )


def test_vision_position_estimate_carries_the_upper_triangle_row_major():
    f = messages.vision_position_estimate(estimate())
    assert f["usec"] == 12345679 and (f["x"], f["y"], f["z"]) == (1.0, 2.0, -3.0)
    assert f["covariance"] == [float(k) for k in range(1, 22)]
    # The diagonal (x y z roll pitch yaw variances) sits at 0, 6, 11, 15, 18, 20, where ArduPilot reads it.
    cov = estimate().covariance
    assert [f["covariance"][i] for i in (0, 6, 11, 15, 18, 20)] == list(np.diag(cov))
    assert f["reset_counter"] == 3 and messages.vision_position_estimate(estimate(reset=259))["reset_counter"] == 3


def test_odometry_velocity_is_in_the_body_frame():
    est = estimate(yaw_rad=math.pi / 2, v=(0.0, 2.0, 0.0))  # flying east, nose east: forward in the body
    f = messages.odometry(est)
    R = R_from_euler321(*est.rpy_rad)
    assert np.allclose([f["vx"], f["vy"], f["vz"]], R.T @ est.v_ned_m_s)
    assert f["vx"] == pytest.approx(2.0 * math.cos(0.05) * math.cos(0.0), rel=0.01)
    assert (f["frame_id"], f["child_frame_id"], f["estimator_type"], f["quality"]) == (20, 12, 2, 80)
    w, x, y, z = f["q"]
    assert w == pytest.approx(math.cos(0.5 * math.acos((np.trace(R) - 1) / 2)), abs=1e-9)
    assert all(math.isnan(v) for v in (f["rollspeed"], f["pitchspeed"], f["yawspeed"]))


def test_statustext_is_prefixed_and_fits_mavlink():
    t = messages.statustext(VisionState.FAILED, "tracking_lost because of a very long explanation of what went wrong")  # type: ignore[arg-type]
    assert t["text"].startswith(b"mavvo: failed (") and len(t["text"]) == 50
    assert messages.statustext(VisionState.TRACKING, StateReason.NONE)["text"] == b"mavvo: tracking"
    assert messages.statustext(VisionState.DEGRADED, StateReason.SCALE_HELD)["text"] == b"mavvo: degraded (scale_held)"


@pytest.mark.parametrize(
    "state, severity",  # MAV_SEVERITY: 2 CRITICAL, 4 WARNING, 6 INFO
    [
        (VisionState.FAILED, 2),
        (VisionState.DEGRADED, 4),
        (VisionState.TRACKING, 6),
        (VisionState.INITIALISING, 6),
        (VisionState.STANDBY, 6),
    ],
)
def test_statustext_severity_follows_the_state(state, severity):
    assert messages.statustext(state, StateReason.NONE)["severity"] == severity


def test_every_state_has_a_code_and_the_codes_are_the_documented_ones():
    assert messages.STATE_CODES == {"standby": -1, "initialising": 0, "tracking": 1, "degraded": 2, "failed": 3}
    assert set(messages.STATE_CODES) == set(VisionState)


def test_every_relpose_failure_is_a_state_reason():
    from mavvo.estimation.relpose_types import RelposeFailure

    assert {r.value for r in RelposeFailure} <= {r.value for r in StateReason}


def test_named_value_names_are_checked():
    assert messages.named_value_float(5, "VO_QUAL", 80)["name"] == b"VO_QUAL"
    with pytest.raises(ValueError, match="longer than 10"):
        messages.named_value_float(5, "VO_QUALITY_X", 1.0)


def test_held_back_state_changes_never_hide_a_failure():
    failed_then_tracking = [(VisionState.FAILED, StateReason.NO_FRAMES), (VisionState.TRACKING, StateReason.NONE)]
    t = messages.statustext_merged(failed_then_tracking)
    assert t["text"] == b"mavvo: failed (no_frames) then tracking" and t["severity"] == 2
    # A single change, or one that only got better, is said as it is.
    assert (
        messages.statustext_merged([(VisionState.DEGRADED, StateReason.FEW_INLIERS)])["text"]
        == b"mavvo: degraded (few_inliers)"
    )
    got_worse = [(VisionState.DEGRADED, StateReason.FEW_INLIERS), (VisionState.FAILED, StateReason.TRACKING_LOST)]
    assert messages.statustext_merged(got_worse) == messages.statustext(VisionState.FAILED, StateReason.TRACKING_LOST)


def test_odometry_speaks_the_autopilots_dialect():
    est = estimate()
    ardupilot = messages.odometry(est, "ardupilot")
    px4 = messages.odometry(est, "px4", "vio")
    # MAV_FRAME: 20 LOCAL_FRD (ArduPilot), 1 LOCAL_NED (PX4: mavvo's frame is north-aligned); 12 BODY_FRD.
    assert (ardupilot["frame_id"], ardupilot["child_frame_id"], ardupilot["estimator_type"]) == (20, 12, 2)
    assert (px4["frame_id"], px4["child_frame_id"], px4["estimator_type"]) == (1, 12, 3)
    # MAV_AUTOPILOT: 12 PX4, 3 ArduPilot; configured beats detected.
    assert messages.autopilot_of(12, "auto") == "px4" and messages.autopilot_of(3, "auto") == "ardupilot"
    assert messages.autopilot_of(None, "auto") == "ardupilot" and messages.autopilot_of(3, "px4") == "px4"
    assert messages.odometry(estimate(quality=-1))["quality"] == -1  # the one sent when vision fails
