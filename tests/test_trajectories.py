"""Trajectories: the truth is consistent (velocity and acceleration are the derivatives of position, the
attitude produces the acceleration, the body rates are the derivative of the attitude)."""

from __future__ import annotations

import numpy as np
import pytest

from mavvo.geometry.frames import rotation_angle_rad
from mavvo.sim.world.trajectories import (
    GRAVITY_M_S2,
    TRAJECTORY_SPECS,
    LawnmowerSpec,
    SquareSpec,
    TakeoffLandingSpec,
    YawSpinSpec,
    make_trajectory,
)


@pytest.mark.parametrize("name", sorted(TRAJECTORY_SPECS))
@pytest.mark.parametrize("yaw", ["fixed", "velocity"])
def test_truth_is_consistent(name, yaw):
    spec_cls = TRAJECTORY_SPECS[name]
    spec = spec_cls(yaw=yaw) if "yaw" in spec_cls.__dataclass_fields__ else spec_cls()
    traj = make_trajectory(spec)
    h = 1e-4
    for t in np.linspace(h, traj.duration_s - h, 157):
        s = traj.state(t)
        before, after = traj.state(t - h), traj.state(t + h)
        np.testing.assert_allclose((after.p_ned_m - before.p_ned_m) / (2 * h), s.v_ned_m_s, atol=1e-5)
        np.testing.assert_allclose((after.v_ned_m_s - before.v_ned_m_s) / (2 * h), s.a_ned_m_s2, atol=1e-4)
        # thrust along body up: the specific force has no component along body x or y
        f_body = s.R_ned_body.T @ (s.a_ned_m_s2 - [0.0, 0.0, GRAVITY_M_S2])
        np.testing.assert_allclose(f_body[:2], 0.0, atol=1e-9)
        assert f_body[2] < 0
        # body rates integrate to the attitude change
        w = s.omega_body_rad_s
        assert rotation_angle_rad(after.R_ned_body, before.R_ned_body @ _expm(w * 2 * h)) < 1e-7


@pytest.mark.parametrize("name", sorted(n for n, c in TRAJECTORY_SPECS.items() if "yaw" in c.__dataclass_fields__))
def test_nose_along_the_path(name):
    traj = make_trajectory(TRAJECTORY_SPECS[name](yaw="velocity"))
    states = [traj.state(t) for t in np.linspace(0.0, traj.duration_s, 157)]
    moving = [s for s in states if np.hypot(*s.v_ned_m_s[:2]) > 0.5]
    assert len(moving) >= 20, "the trajectory hardly moves: nothing to check"
    errors = [
        abs((s.yaw_rad - np.arctan2(s.v_ned_m_s[1], s.v_ned_m_s[0]) + np.pi) % (2 * np.pi) - np.pi) for s in moving
    ]
    assert max(errors) < 1e-6


def _expm(w: np.ndarray) -> np.ndarray:
    a = np.linalg.norm(w)
    if a < 1e-15:
        return np.eye(3)
    k = w / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def test_waypoint_paths_start_and_end_at_rest_and_have_the_right_length():
    sq = make_trajectory(SquareSpec(side_m=20.0, laps=2))
    assert sq.path_length_m() == pytest.approx(160.0, rel=1e-3)
    lm = make_trajectory(LawnmowerSpec(leg_m=60.0, spacing_m=10.0, legs=4))
    assert lm.path_length_m() == pytest.approx(4 * 60 + 3 * 10, rel=1e-3)
    for traj in (sq, lm):
        for t in (0.0, traj.duration_s):
            s = traj.state(t)
            np.testing.assert_allclose(s.v_ned_m_s, 0.0, atol=1e-12)
            np.testing.assert_allclose(s.a_ned_m_s2, 0.0, atol=1e-12)


def test_speed_limit_and_altitudes():
    spec = LawnmowerSpec(speed_m_s=4.0, altitude_m=30.0)
    traj = make_trajectory(spec)
    speeds = [np.linalg.norm(traj.state(t).v_ned_m_s) for t in np.linspace(0, traj.duration_s, 3001)]
    assert max(speeds) <= 4.0 + 1e-9
    assert max(speeds) > 3.9
    tl = make_trajectory(TakeoffLandingSpec(altitude_m=12.0, start_height_m=0.3))
    heights = [-tl.state(t).p_ned_m[2] for t in np.linspace(0, tl.duration_s, 500)]
    assert min(heights) == pytest.approx(0.3) and max(heights) == pytest.approx(12.0)


def test_yaw_spin_turns_in_place_at_its_rate():
    traj = make_trajectory(YawSpinSpec(rate_deg_s=120.0, turns=2.0, ramp_s=1.0))
    mid = traj.state(traj.duration_s / 2)
    assert np.degrees(mid.omega_body_rad_s[2]) == pytest.approx(120.0, rel=1e-6)
    np.testing.assert_allclose(mid.p_ned_m, [0.0, 0.0, -10.0])
    assert traj.duration_s == pytest.approx(720.0 / 120.0 + 1.0)
