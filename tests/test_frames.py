"""Rotations, Euler 3-2-1 and level-frame derotation."""

import numpy as np
import pytest

from mavvo.geometry.frames import (
    R_BODY_CAM_FORWARD,
    R_BODY_CAM_NADIR,
    R_from_euler321,
    R_lvl_cam,
    angle_between_rad,
    derotate,
    euler321_from_R,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle_rad,
)


def test_elementary_rotations_turn_the_right_way() -> None:
    np.testing.assert_allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-15)


def test_euler321_round_trip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(500):
        rpy = (rng.uniform(-np.pi, np.pi), rng.uniform(-1.5, 1.5), rng.uniform(-np.pi, np.pi))
        R = R_from_euler321(*rpy)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(euler321_from_R(R), rpy, atol=1e-9)


def test_euler321_matches_the_aerospace_convention() -> None:
    # Nose up by 10 deg: the body x axis points up, i.e. negative NED z.
    R = R_from_euler321(0.0, np.radians(10), 0.0)
    assert (R @ [1, 0, 0])[2] == pytest.approx(-np.sin(np.radians(10)))
    # Right wing down by 10 deg: the body y axis points down.
    R = R_from_euler321(np.radians(10), 0.0, 0.0)
    assert (R @ [0, 1, 0])[2] == pytest.approx(np.sin(np.radians(10)))
    # Heading east: the nose points along NED y.
    np.testing.assert_allclose(R_from_euler321(0, 0, np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_gimbal_lock_keeps_the_rotation() -> None:
    R = R_from_euler321(0.3, np.pi / 2, -0.4)
    np.testing.assert_allclose(R_from_euler321(*euler321_from_R(R)), R, atol=1e-12)


def test_mountings_point_where_they_say() -> None:
    for R in (R_BODY_CAM_NADIR, R_BODY_CAM_FORWARD):
        assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_array_equal(R_BODY_CAM_NADIR @ [0, 0, 1], [0, 0, 1])  # optical axis down
    np.testing.assert_array_equal(R_BODY_CAM_NADIR @ [0, -1, 0], [1, 0, 0])  # image top to the nose
    np.testing.assert_array_equal(R_BODY_CAM_FORWARD @ [0, 0, 1], [1, 0, 0])  # optical axis forward


def test_level_frame_removes_roll_and_pitch_but_keeps_heading() -> None:
    rng = np.random.default_rng(2)
    for _ in range(100):
        roll, pitch, yaw = rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-np.pi, np.pi)
        R_ned_cam = R_from_euler321(roll, pitch, yaw) @ R_BODY_CAM_NADIR
        f_cam = rng.normal(size=(5, 3))
        f_lvl = derotate(f_cam, R_lvl_cam(roll, pitch, R_BODY_CAM_NADIR))
        # The level frame differs from NED by the heading only.
        np.testing.assert_allclose(f_lvl @ rot_z(yaw).T, f_cam @ R_ned_cam.T, atol=1e-12)


def test_angles_are_precise_when_small() -> None:
    assert rotation_angle_rad(rot_z(1e-9), np.eye(3)) == pytest.approx(1e-9, rel=1e-6)
    assert angle_between_rad(np.array([1.0, 0, 0]), np.array([1.0, 1e-10, 0])) == pytest.approx(1e-10, rel=1e-6)
    assert rotation_angle_rad(rot_x(2.0), rot_x(-0.5)) == pytest.approx(2.5)


def test_bad_input_names_the_argument() -> None:
    with pytest.raises(ValueError, match=r"f_cam: expected an \(N,3\)"):
        derotate(np.zeros((3, 2)), np.eye(3))
    with pytest.raises(ValueError, match="R_body_cam: expected a rotation matrix"):
        R_lvl_cam(0.0, 0.0, np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match=r"R_ned_body: expected a finite \(3,3\)"):
        euler321_from_R(np.full((3, 3), np.nan))
