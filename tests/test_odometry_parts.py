"""The odometry's parts on synthetic data with exact truth: triangulation and scale, keyframes, filter."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mavvo.estimation.relpose import _failure
from mavvo.estimation.relpose_types import RelposeFailure
from mavvo.geometry.frames import rot_z
from mavvo.odometry.filter import FilterOptions, PoseFilter, Update, wrap_angle
from mavvo.odometry.keyframes import Keyframe, KeyframeOptions, carry_depths, keyframe_reason, sight_change
from mavvo.odometry.measurement import Measurement, keyframe_position, position_noise
from mavvo.odometry.pipeline import Odometry
from mavvo.odometry.scale import (
    ScaleEstimate,
    ScaleOptions,
    estimate_scale,
    ground_depth,
    scale_from_scene_depth,
    triangulate_unit,
)
from mavvo.odometry.tilt_motion import TiltMotion, tilt_acceleration_lvl_m_s2
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.world.twoview import make_scene
from mavvo.types import PairedFrame, ScaleSource, StateReason


def _unit_geometry(scene):
    """Triangulation of a scene with its unit translation: points, parallax, c2 (unit)."""
    lam1, lam2, par, valid = triangulate_unit(scene.f1_lvl, scene.f2_lvl, scene.R_2_1, scene.t_2_1, math.radians(0.05))
    return lam1, lam2, par, valid, -scene.R_2_1.T @ scene.t_2_1


def test_triangulation_recovers_depths_in_baseline_units() -> None:
    scene = make_scene(np.random.default_rng(0), 50, motion="sideways", mount="oblique")
    lam1, lam2, _, valid, _ = _unit_geometry(scene)
    X = scene.points_ned  # camera 1 at the origin; depth along each ray is the distance
    assert valid.all()
    np.testing.assert_allclose(lam1 * scene.baseline_m, np.linalg.norm(X, axis=1), rtol=1e-9)
    assert np.all(lam2 > 0)


@pytest.mark.parametrize("source", ["rangefinder", "altitude", "fixed"])
def test_ground_sources_give_the_metric_baseline(source: str) -> None:
    rng = np.random.default_rng(1)
    scene = make_scene(
        rng, 200, motion="sideways", mount="nadir", structure="ground", distance_m=12.0, max_tilt_rad=0.0
    )
    lam1, _, par, valid, c2 = _unit_geometry(scene)
    pts = lam1[valid, None] * scene.f1_lvl[valid]
    height2 = 12.0 - (scene.baseline_m * c2)[2]  # camera 2's height above the ground (z down)
    opt = ScaleOptions(source=source, fixed_height_m=height2)
    s = estimate_scale(
        opt,
        points_lvl=pts,
        parallax_rad=par[valid],
        c2_lvl1=c2,
        down_lvl2=np.array([0.0, 0.0, 1.0]),
        range_m=height2,
        height_m=height2,
        carried_depth_m=np.zeros(0),
        depth_unit=np.zeros(0),
        first_interval=False,
    )
    assert s is not None and s.source == source
    assert s.baseline_m == pytest.approx(scene.baseline_m, rel=1e-9)


def test_carried_scale_and_the_fallback_order() -> None:
    rng = np.random.default_rng(2)
    scene = make_scene(rng, 100, motion="forward", mount="forward", distance_m=15.0)
    lam1, _, par, valid, c2 = _unit_geometry(scene)
    pts = lam1[valid, None] * scene.f1_lvl[valid]
    metric = lam1[valid] * scene.baseline_m * rng.choice([1.0, 1.0, 1.0, 5.0], valid.sum())  # a quarter wrong
    common = dict(
        points_lvl=pts, parallax_rad=par[valid], c2_lvl1=c2, down_lvl2=np.array([0.0, 0.0, 1.0]), height_m=None
    )
    # No range: the rangefinder source falls back to the carried depths, outliers outvoted.
    s = estimate_scale(
        ScaleOptions(source="rangefinder"),
        range_m=None,
        carried_depth_m=metric,
        depth_unit=lam1[valid],
        first_interval=False,
        **common,
    )
    assert s is not None and s.source == "carried" and s.baseline_m == pytest.approx(scene.baseline_m, rel=1e-9)
    # Carried with nothing carried yet: nothing, unless a rangefinder reading is there in the first interval.
    none = dict(carried_depth_m=np.zeros(0), depth_unit=np.zeros(0))
    assert estimate_scale(ScaleOptions(source="carried"), range_m=None, first_interval=True, **none, **common) is None
    assert estimate_scale(ScaleOptions(source="carried"), range_m=3.0, first_interval=False, **none, **common) is None
    got = estimate_scale(ScaleOptions(source="carried"), range_m=3.0, first_interval=True, **none, **common)
    assert got is not None and got.source == "rangefinder"
    held = scale_from_scene_depth(pts, 30.0, "held", 12)
    assert held is not None and np.median(np.linalg.norm(pts, axis=1)) * held.baseline_m == pytest.approx(30.0)
    assert scale_from_scene_depth(pts[:5], 30.0, "held", 12) is None


def test_a_ground_fit_that_is_no_plane_gives_no_scale_and_the_carried_depths_take_over() -> None:
    """A forward camera's few ground points, badly triangulated: their depths spread tens of times the
    median (the forward scenario saw spreads of 8-53 where a good fit has 0.03-0.09) and the
    rangefinder scale from them was 10-80x off; the keyframe placed with it moved 350 m. Such a fit is
    refused and the next source in the order answers (here: flat ground seen obliquely, its depths spoiled)."""
    rng = np.random.default_rng(4)
    scene = make_scene(rng, 200, motion="forward", mount="oblique", structure="ground", distance_m=15.0)
    lam1, _, par, valid, c2 = _unit_geometry(scene)
    pts = lam1[valid, None] * scene.f1_lvl[valid]
    below = pts[:, 2] > 0
    assert np.count_nonzero(below) >= 12
    spoiled = pts.copy()
    spoiled[below, 2] *= np.exp(rng.normal(0.0, 3.0, np.count_nonzero(below)))  # depths all over the place
    _, spread = ground_depth(spoiled, par[valid] ** 2, 12)
    assert spread > 0.5
    common = dict(
        parallax_rad=par[valid],
        c2_lvl1=c2,
        down_lvl2=np.array([0.0, 0.0, 1.0]),
        range_m=3.0,
        height_m=None,
        carried_depth_m=lam1[valid] * scene.baseline_m,
        depth_unit=lam1[valid],
        first_interval=False,
    )
    good = estimate_scale(ScaleOptions(source="rangefinder"), points_lvl=pts, **common)
    assert good is not None and good.source == "rangefinder"  # a plane: the rangefinder answers
    s = estimate_scale(ScaleOptions(source="rangefinder"), points_lvl=spoiled, **common)
    assert s is not None and s.source == "carried" and s.baseline_m == pytest.approx(scene.baseline_m, rel=1e-9)
    loose = estimate_scale(ScaleOptions(source="rangefinder", max_ground_spread=100.0), points_lvl=spoiled, **common)
    assert loose is not None and loose.source == "rangefinder"  # the bound is what refused it


def test_a_height_sources_noise_over_the_height_is_part_of_the_scales_uncertainty() -> None:
    """A fresh rangefinder reading each frame: 2 cm of noise is 4% of the scale at 0.5 m and 0.2% at
    10 m. Near the ground that, not the ground fit's spread, is what moves the positions; it is kept
    apart from the fit's spread (it moves a position along the translation only)."""
    rng = np.random.default_rng(5)
    scene = make_scene(rng, 200, motion="sideways", mount="nadir", structure="ground", distance_m=10.0)
    lam1, _, par, valid, c2 = _unit_geometry(scene)
    pts = lam1[valid, None] * scene.f1_lvl[valid]
    common = dict(
        points_lvl=pts,
        parallax_rad=par[valid],
        c2_lvl1=c2,
        down_lvl2=np.array([0.0, 0.0, 1.0]),
        height_m=None,
        carried_depth_m=np.zeros(0),
        depth_unit=np.zeros(0),
        first_interval=False,
    )
    _, fit_spread = ground_depth(pts, par[valid] ** 2, 12)
    for range_m in (0.5, 10.0):
        s = estimate_scale(ScaleOptions(source="rangefinder", rangefinder_sigma_m=0.02), range_m=range_m, **common)
        assert s is not None and s.sensor_spread == pytest.approx(0.02 / range_m, rel=1e-9)
        assert s.spread == pytest.approx(fit_spread, rel=1e-9)
    exact = estimate_scale(ScaleOptions(source="rangefinder", rangefinder_sigma_m=0.0), range_m=0.5, **common)
    assert exact is not None and exact.spread == pytest.approx(fit_spread, rel=1e-9) and exact.sensor_spread == 0.0


def test_ground_depth_outvotes_raised_objects() -> None:
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-5, 5, (300, 2)), np.full(300, 10.0)])
    pts[:100, 2] = rng.uniform(4.0, 8.0, 100)  # a third on boxes, closer to the camera
    d, _ = ground_depth(pts, np.ones(300), 12)
    assert d == pytest.approx(10.0)
    assert ground_depth(pts[:5], np.ones(5), 12) is None


def test_keyframe_rules_and_pose_composition() -> None:
    opt = KeyframeOptions(parallax_px=40.0, min_survival=0.5, min_inliers=60)
    assert keyframe_reason(opt, parallax_px=41.0, survival=0.9, inliers=200) == "parallax"
    assert keyframe_reason(opt, parallax_px=10.0, survival=0.4, inliers=200) == "survival"
    assert keyframe_reason(opt, parallax_px=10.0, survival=0.9, inliers=59) == "inliers"
    assert keyframe_reason(opt, parallax_px=10.0, survival=0.9, inliers=200) == ""
    assert keyframe_reason(opt, parallax_px=10.0, survival=0.9, inliers=200, depth_change=-0.3) == "depth"
    assert keyframe_reason(opt, parallax_px=10.0, survival=0.9, inliers=200, depth_change=0.2) == ""
    # A nadir keyframe's bearings around straight down; the camera 2 m up and 1 m aside over ground 5 m
    # below: it moved 2 m away from the scene along the mean line of sight, 0.4 of the depth.
    rng = np.random.default_rng(11)
    down = np.column_stack([rng.uniform(-0.3, 0.3, (200, 2)), np.ones(200)])
    down[:, :2] -= down[:, :2].mean(axis=0)
    down /= np.linalg.norm(down, axis=1)[:, None]
    assert sight_change(down, np.array([1.0, 0.0, -2.0]), 5.0) == pytest.approx(-0.4, abs=1e-3)  # mean ~ down
    assert sight_change(down, np.array([1.0, 0.0, -2.0]), 0.0) == 0.0
    kf = Keyframe(
        0, 0.0, np.arange(3), np.eye(3), np.full(3, np.nan), np.array([1.0, 2.0, -3.0]), math.radians(90.0), 0.0
    )
    p, yaw = kf.pose_of(np.array([1.0, 0.0, 0.5]), math.radians(30.0))
    np.testing.assert_allclose(p, [1.0, 3.0, -2.5], atol=1e-12)  # level x of a heading-east frame is east
    assert yaw == pytest.approx(math.radians(60.0))
    i_kf, i_cur = kf.match(np.array([1, 2, 7]))
    assert list(i_kf) == [1, 2] and list(i_cur) == [0, 1]


def test_depths_carry_through_a_pure_rotation() -> None:
    f = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
    kf = Keyframe(0, 0.0, np.arange(3), f, np.array([10.0, 5.0, np.nan]), np.zeros(3), 0.0, 0.0)
    R = rot_z(0.3)
    out = carry_depths(
        kf, np.arange(3), np.array([2, 0, 1]), 4, R, np.zeros(3), np.full(3, np.nan), np.zeros(3), math.radians(1.0)
    )
    np.testing.assert_allclose(out[[2, 0]], [10.0, 5.0])
    assert np.isnan(out[1]) and np.isnan(out[3])
    # A new triangulation with enough parallax wins over the moved one.
    out = carry_depths(
        kf,
        np.arange(3),
        np.arange(3),
        3,
        R,
        np.zeros(3),
        np.array([7.0, 6.0, 4.0]),
        np.radians([2.0, 0.5, 2.0]),
        math.radians(1.0),
    )
    np.testing.assert_allclose(out, [7.0, 5.0, 4.0])


def test_filter_follows_constant_velocity_and_rejects_a_jump() -> None:
    rng = np.random.default_rng(4)
    f = PoseFilter(FilterOptions(max_rejections=3, accel_sigma_m_s2=0.5))
    f.reset(0.0, np.zeros(3), 3.1, pos_cov_m2=0.05**2 * np.eye(3), yaw_sigma_rad=0.01)
    v = np.array([2.0, -1.0, 0.5])
    for k in range(1, 101):
        t = 0.05 * k
        f.predict(t)
        # the yaw wraps through +-pi on the way
        assert (
            f.update(
                v * t + rng.normal(0, 0.02, 3),
                wrap_angle(3.1 + 0.2 * t),
                pos_cov_m2=0.02**2 * np.eye(3),
                yaw_sigma_rad=0.005,
            )
            == Update.FUSED
        )
    np.testing.assert_allclose(f.velocity_ned_m_s, v, atol=0.05)
    assert abs(wrap_angle(f.yaw_rad - (3.1 + 0.2 * 5.0))) < 0.01
    p_before = f.position_ned_m
    f.predict(5.05)
    assert (
        f.update(v * 5.05 + [10.0, 0, 0], 3.1 + 0.2 * 5.05, pos_cov_m2=0.02**2 * np.eye(3), yaw_sigma_rad=0.005)
        == Update.REJECTED
    )
    assert np.linalg.norm(f.position_ned_m - (p_before + 0.05 * v)) < 0.05  # coasted, not jumped
    assert (
        f.update(v * 5.05 + [10.0, 0, 0], 3.1 + 0.2 * 5.05, pos_cov_m2=0.02**2 * np.eye(3), yaw_sigma_rad=0.005)
        == Update.REJECTED
    )
    assert (
        f.update(v * 5.05 + [10.0, 0, 0], 3.1 + 0.2 * 5.05, pos_cov_m2=0.02**2 * np.eye(3), yaw_sigma_rad=0.005)
        == Update.RESTARTED
    )  # third: believed
    np.testing.assert_allclose(f.position_ned_m, v * 5.05 + [10.0, 0, 0])
    assert np.all(np.linalg.eigvalsh(f.position_covariance) > 0)


def test_the_tilt_gives_a_multirotors_horizontal_acceleration() -> None:
    """Against the simulator's quadrotor (its attitude made from its acceleration, thrust along the body's
    z): over a hopping flight, the tilt's acceleration is the trajectory's to within what the vertical
    acceleration's share of the thrust leaves (a few percent); 5 deg nose down is g tan 5 deg forward."""
    from mavvo.sim.world.trajectories import make_trajectory

    a = tilt_acceleration_lvl_m_s2(0.0, math.radians(-5.0))
    np.testing.assert_allclose(a, [9.80665 * math.tan(math.radians(5.0)), 0.0, 0.0], atol=1e-12)
    traj = make_trajectory(load_scenario("indoor_hops").trajectory)
    err, true = [], []
    for t in np.arange(0.5, 25.0, 0.1):
        st = traj.state(float(t))
        a_ned = rot_z(st.yaw_rad) @ tilt_acceleration_lvl_m_s2(st.roll_rad, st.pitch_rad)
        err.append(a_ned[:2] - st.a_ned_m_s2[:2])
        true.append(st.a_ned_m_s2[:2])
    rms_err, rms_true = np.sqrt(np.mean(np.square(err))), np.sqrt(np.mean(np.square(true)))
    assert rms_true > 0.2 and rms_err < 0.1 * rms_true, (rms_err, rms_true)


def _brake_north(tm: TiltMotion, rng: np.random.Generator, pitch_bias_rad: float = 0.0) -> float:
    """Fly ``tm`` north at 0.6 m/s for 2 s, then brake to a stop at 0.6 m/s^2, vision measuring the
    position at 50 Hz (5 mm noise) throughout; the true velocity at the end (0)."""
    brake = math.atan(0.6 / 9.80665)  # nose up: braking a vehicle flying north
    p, v, last_a = 0.0, 0.6, 0.0
    for k in range(152):
        t = 0.02 * k
        a = -0.6 if 100 < k <= 150 else 0.0  # the acceleration at the frame; between frames, the mean
        p += v * 0.02 + 0.25 * (a + last_a) * 0.02**2 if k else 0.0
        v += 0.5 * (a + last_a) * 0.02
        last_a = a
        tm.step(t, 0.0, (brake if a else 0.0) + pitch_bias_rad, 0.0)
        tm.measured(np.array([p, 0.0]) + rng.normal(0.0, 0.005, 2), np.eye(2) * 0.005**2)
    return v


def test_tilt_motion_follows_a_braking_without_a_constant_velocity_filters_lag() -> None:
    """Vision's positions and the tilt's acceleration together: at the stop the velocity is within
    0.03 m/s of the truth, where a constant-velocity filter lags by 0.1-0.2 m/s (docs/odometry.md,
    Coasting); the positions alone, differenced over 0.1 s, give it 0.07 m/s off at 1 sigma."""
    tm = TiltMotion()
    v_true = _brake_north(tm, np.random.default_rng(4))
    assert abs(v_true) < 1e-9 and abs(tm.v_ne_m_s[0] - v_true) < 0.03 and abs(tm.v_ne_m_s[1]) < 0.03


def test_tilt_motion_measures_a_trim_error_and_takes_it_off_the_acceleration() -> None:
    """A flight controller whose pitch reads 0.5 deg nose down too many (the tilt says 0.086 m/s^2
    forward while the vehicle hovers) over a still position for 20 s, turning at 9 deg/s: the bias is
    found in the level frame (within 0.01 m/s^2), and the acceleration a coast would integrate is the
    truth's (0) within as much, where the biased tilt's is 0.086 m/s^2."""
    bias = math.radians(-0.5)
    g_bias = -9.80665 * math.tan(bias)  # forward, in the level frame
    rng = np.random.default_rng(5)
    tm = TiltMotion()
    for k in range(1000):
        yaw = math.radians(9.0) * 0.02 * k
        tm.step(0.02 * k, 0.0, bias, yaw)
        tm.measured(np.array([1.0, 2.0]) + rng.normal(0.0, 0.005, 2), np.eye(2) * 0.005**2)
    np.testing.assert_allclose(tm.bias_lvl_m_s2, [g_bias, 0.0], atol=0.01)
    # The velocity is vision's 5 mm noise filtered: about 0.01 m/s at 1 sigma (0.003-0.016 over seeds 0-4).
    assert np.linalg.norm(tm.accel_ned_m_s2) < 0.01 and np.linalg.norm(tm.v_ne_m_s) < 0.03
    # The same braking as above with the trim error, measured for 3 s: the stop still within 0.03 m/s.
    tm = TiltMotion()
    v_true = _brake_north(tm, np.random.default_rng(4), pitch_bias_rad=bias)
    assert abs(tm.v_ne_m_s[0] - v_true) < 0.03


def test_tilt_motion_steps_match_filterpys_kalman_filter() -> None:
    """Each axis's predict and update, written out in scalars, give what filterpy's KalmanFilter gives
    for the same F, B, Q, H, R (heading fixed, the measurement's covariance isotropic), irregular times."""
    from filterpy.kalman import KalmanFilter

    from mavvo.odometry.tilt_motion import ACCEL_PSD_M2_S3 as q
    from mavvo.odometry.tilt_motion import BIAS_PSD_M2_S5 as q_b

    rng = np.random.default_rng(6)
    tm = TiltMotion()
    ref = KalmanFilter(dim_x=3, dim_z=1)  # north: [p, v, b]
    ref.H = np.array([[1.0, 0.0, 0.0]])
    ref.x = np.zeros((3, 1))
    ref.P = np.diag([0.0, tm._vv, tm._bb])
    t, last_a = 0.0, None
    for k in range(80):
        dt = float(rng.uniform(0.01, 0.05)) if k else 0.0
        t += dt
        pitch = float(rng.normal(0.0, 0.05))
        tm.step(t, 0.0, pitch, 0.0)
        a = -9.80665 * math.tan(pitch)
        mean = a if last_a is None else 0.5 * (a + last_a)
        last_a = a
        if dt > 0:
            h = 0.5 * dt * dt
            ref.F = np.array([[1.0, dt, -h], [0.0, 1.0, -dt], [0.0, 0.0, 1.0]])
            ref.B = np.array([[h], [dt], [0.0]])
            ref.Q = np.array([[q * dt**3 / 3, q * h, 0.0], [q * h, q * dt, 0.0], [0.0, 0.0, q_b * dt]])
            ref.predict(u=np.array([[mean]]))
        if k % 3 != 2:  # a frame now and then without a position
            r = float(rng.uniform(1e-5, 1e-3))
            z = np.array([ref.x[0, 0] + rng.normal(0.0, math.sqrt(r)), tm._p[1]])  # inside the gate
            tm.measured(z, np.diag([r, r]))
            if k == 0:  # the first position starts the filter's position (no update)
                ref.x[0, 0], ref.P[0, 0] = z[0], r
            else:
                ref.update(np.array([[z[0]]]), R=np.array([[r]]))
        np.testing.assert_allclose([tm._p[0], tm._v[0], tm._b[0]], ref.x[:, 0], rtol=1e-9, atol=1e-12)
        P = [[tm._pp, tm._pv, tm._pb], [tm._pv, tm._vv, tm._vb], [tm._pb, tm._vb, tm._bb]]
        np.testing.assert_allclose(P, ref.P, rtol=1e-9, atol=1e-15)


def test_a_known_acceleration_moves_the_filter_exactly_and_a_coast_sets_what_is_known() -> None:
    f = PoseFilter()
    f.reset(0.0, np.zeros(3), 0.0, v_ned_m_s=np.array([1.0, 0.0, 0.0]), pos_cov_m2=np.eye(3) * 1e-4, yaw_sigma_rad=0.01)
    a = np.array([-0.5, 0.2, 0.0])
    for k in range(1, 11):  # ten steps of 0.1 s: the same as one of 1 s for a constant acceleration
        f.predict(0.1 * k, a)
    np.testing.assert_allclose(f.position_ned_m, [1.0 - 0.25, 0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(f.velocity_ned_m_s, [0.5, 0.2, 0.0], atol=1e-12)
    cov = np.diag([0.04, 0.04, 0.001])
    f.set_position_covariance(cov)
    f.set_horizontal_velocity(np.array([0.3, -0.1]))
    np.testing.assert_allclose(f.position_covariance, cov)
    np.testing.assert_allclose(f.velocity_ned_m_s, [0.3, -0.1, 0.0])
    P = f._P
    assert np.all(P[0:3, 3:] == 0.0) and np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)


def test_filter_steps_match_filterpys_kalman_filter() -> None:
    """The predict/update steps written out in the filter give what filterpy's KalmanFilter gives for
    the same F, Q, H, R (filterpy: the reference, in the test dependencies only), position-and-yaw,
    yaw-only and height (down-only) updates mixed, irregular times."""
    from filterpy.kalman import KalmanFilter

    from mavvo.odometry.filter import _H

    rng = np.random.default_rng(12)
    opt = FilterOptions(max_rejections=1000, gate_probability=0.999999)
    f = PoseFilter(opt)
    f.reset(0.0, np.array([1.0, -2.0, 0.5]), 0.3, pos_cov_m2=0.05**2 * np.eye(3), yaw_sigma_rad=0.02)
    ref = KalmanFilter(dim_x=8, dim_z=4)
    ref.x = f._x.copy()
    ref.P = f._P.copy()
    t = 0.0
    for k in range(60):
        dt = float(rng.uniform(0.02, 0.2))
        t += dt
        f.predict(t)
        F = np.eye(8)
        F[0, 3] = F[1, 4] = F[2, 5] = F[6, 7] = dt
        q = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        Q = np.zeros((8, 8))
        for i in range(3):
            Q[np.ix_([i, i + 3], [i, i + 3])] = q * opt.accel_sigma_m_s2**2
        Q[6:8, 6:8] = q * opt.yaw_accel_sigma_rad_s2**2
        ref.predict(F=F, Q=Q)
        yaw = float(ref.x[6, 0] + rng.normal(0, 0.02))
        sp, sy = float(rng.uniform(0.01, 0.1)), float(rng.uniform(0.005, 0.05))
        A = rng.normal(0.0, sp, (3, 3))
        C = A @ A.T + sp**2 * np.eye(3)  # a full position covariance: errors along some directions more
        R = np.zeros((4, 4))
        R[:3, :3], R[3, 3] = C, sy**2
        if k % 5 == 4:  # a height from a rangefinder: the down coordinate alone
            down = float(ref.x[2, 0] + rng.normal(0, 0.03))
            assert f.update_down(down, 0.03) == Update.FUSED
            ref.update(np.array([[down]]), R=np.array([[0.03**2]]), H=_H[2:3])
        elif k % 4 == 3:
            assert f.update(None, yaw, pos_cov_m2=C, yaw_sigma_rad=sy) == Update.FUSED
            ref.update(np.array([[yaw]]), R=np.array([[sy**2]]), H=_H[3:4])
        else:
            p = ref.x[0:3, 0] + rng.normal(0, 0.05, 3)
            assert f.update(p, yaw, pos_cov_m2=C, yaw_sigma_rad=sy) == Update.FUSED
            ref.update(np.array([[*p, yaw]]).T, R=R, H=_H)
        np.testing.assert_allclose(f._x, ref.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(f._P, ref.P, rtol=1e-8, atol=1e-14)
    assert np.linalg.norm(f.velocity_ned_m_s) > 0  # the velocity was estimated, not left at its start


@pytest.mark.parametrize(
    "probability, dof, table",  # chi-square quantiles as printed in statistics tables
    [(0.999, 4, 18.467), (0.999, 1, 10.828), (0.95, 3, 7.815), (0.99, 2, 9.210), (0.95, 1, 3.841)],
)
def test_chi2_quantile_matches_the_tables(probability, dof, table):
    from mavvo.odometry.filter import chi2_quantile

    assert chi2_quantile(probability, dof) == pytest.approx(table, abs=1e-3)


def test_the_filter_estimates_one_sources_part_of_the_last_measurements_error() -> None:
    """PoseFilter.error_share_m: a position measured with two independent errors n1, n2 (covariances R1,
    R2) from a prior off by its own covariance P. The share it gives for R2 is the least-squares
    estimate of n2 from the innovation: over seeded draws, n2 regressed on it has a slope of 1 in each
    direction, and what is left has the variance R2 - R2 (P + R1 + R2)^-1 R2 (per axis, the diagonal
    covariances here); a direction R2 does not move gets nothing; a rejected update leaves no share."""
    rng = np.random.default_rng(31)
    s_p, s1, s2 = np.array([0.01, 0.01, 0.01]), np.array([0.02, 0.005, 0.01]), np.array([0.015, 0.015, 0.0])
    R1, R2 = np.diag(s1**2), np.diag(s2**2)
    est, true = [], []
    for _ in range(4000):
        f = PoseFilter(FilterOptions(gate_probability=0.999999))
        f.reset(0.0, np.zeros(3), 0.0, pos_cov_m2=np.diag(s_p**2), yaw_sigma_rad=0.01)
        p_true = rng.normal(0.0, s_p)  # the filter's estimate (zero) is off by this
        n1, n2 = rng.normal(0.0, s1), rng.normal(0.0, s2)
        assert f.update(p_true + n1 + n2, 0.0, pos_cov_m2=R1 + R2, yaw_sigma_rad=0.01) == Update.FUSED
        est.append(f.error_share_m(R2))
        true.append(n2)
    e, n = np.array(est), np.array(true)
    for axis in (0, 1):
        slope = float(e[:, axis] @ n[:, axis] / (e[:, axis] @ e[:, axis]))
        assert slope == pytest.approx(1.0, abs=0.08)
        left = s2[axis] ** 2 - s2[axis] ** 4 / (s_p[axis] ** 2 + s1[axis] ** 2 + s2[axis] ** 2)
        assert float(np.var(n[:, axis] - e[:, axis])) == pytest.approx(left, rel=0.1)
    assert np.all(e[:, 2] == 0.0)
    far = f.update(np.array([10.0, 0.0, 0.0]), 0.0, pos_cov_m2=R1 + R2, yaw_sigma_rad=0.01)
    assert far == Update.REJECTED
    assert np.all(f.error_share_m(R2) == 0.0)


def test_gate_uses_the_measurement_size():
    """A yaw-only update 3.5 sigma off is beyond the 1-dof gate (10.83) though inside the 4-dof one
    (18.47): it is rejected. The same yaw error with a position that agrees passes the 4-dof gate."""
    f = PoseFilter(FilterOptions(max_rejections=10))
    f.reset(0.0, np.zeros(3), 0.0, pos_cov_m2=0.01**2 * np.eye(3), yaw_sigma_rad=1e-4)
    sigma = 0.01
    off = 3.5 * np.hypot(sigma, 1e-4)
    assert f.update(None, off, pos_cov_m2=0.01**2 * np.eye(3), yaw_sigma_rad=sigma) == Update.REJECTED
    assert f.update(np.zeros(3), off, pos_cov_m2=0.01**2 * np.eye(3), yaw_sigma_rad=sigma) == Update.FUSED


def test_a_new_keyframe_goes_where_the_filter_puts_its_frame_when_that_is_the_better_estimate() -> None:
    """docs/odometry.md, Keyframes: a tracking frame's keyframe goes where the filter puts the frame and
    its depths follow the baseline that leaves it (the filtered baseline along the measured direction
    over the measured one, within 0.5-2); with a held scale (a guessed length) or few inliers the
    filter's position and the depths as measured; placed by the filter, it also takes the part of the
    measurement its frame's own tilt made; other degraded frames, and frames without a measured
    translation, keep the measurement. In the close range (the keyframes' level frames held) a tracking
    frame's keyframe keeps its measurement too."""
    sc = load_scenario("forward")
    vo = Odometry(sc.camera.camera_model(), sc.camera.R_body_cam())
    kf = Keyframe(0, 0.0, np.arange(3), np.eye(3), np.full(3, np.nan), np.array([1.0, 2.0, -5.0]), 0.0, 0.0)
    scale = ScaleEstimate(4.0, ScaleSource.RANGEFINDER, 40, 0.3)

    def measured(p_ned_m: list[float], with_scale: bool = True) -> Measurement:
        return Measurement(
            np.array(p_ned_m),
            0.0,
            None,
            scale if with_scale else None,
            np.zeros(3),
            50.0,
            np.zeros(0),
            np.zeros(0),
            (0.0, 0.0),
            (np.zeros((0, 3)), np.zeros((0, 3))),
        )  # type: ignore[arg-type]

    def filtered_at(p_ned_m: list[float]) -> None:
        vo.filter.reset(1.0, np.array(p_ned_m), 0.0, pos_cov_m2=0.1**2 * np.eye(3), yaw_sigma_rad=0.01)

    tracking = StateReason.NONE
    none, view = np.zeros(3), np.array([0.02, -0.01, 0.0])  # the part of the measurement the frame's tilt made
    filtered_at([4.0, 2.5, -5.0])
    p, k = keyframe_position(kf, measured([5.0, 2.0, -5.0]), tracking, vo.filter.position_ned_m, none)
    np.testing.assert_allclose(p, [4.0, 2.5, -5.0])
    assert k == pytest.approx(3.0 / 4.0)  # 3 m of the filter's 3 m north, 0.5 m east along the measured 4 m north
    p, k = keyframe_position(kf, measured([5.0, 2.0, -5.0]), tracking, vo.filter.position_ned_m, view)
    np.testing.assert_allclose(p, [4.02, 2.49, -5.0])  # with it: the keyframe levels with that tilt
    assert k == pytest.approx(3.02 / 4.0)
    for guessed in (StateReason.SCALE_HELD, StateReason.FEW_INLIERS):
        p, k = keyframe_position(kf, measured([5.0, 2.0, -5.0]), guessed, vo.filter.position_ned_m, view)
        np.testing.assert_allclose(p, [4.02, 2.49, -5.0])
        assert k == 1.0
    p, k = keyframe_position(
        kf, measured([5.0, 2.0, -5.0]), StateReason.ATTITUDE_INTERPOLATED, vo.filter.position_ned_m, view
    )
    np.testing.assert_allclose(p, [5.0, 2.0, -5.0])
    assert k == 1.0
    p, k = keyframe_position(kf, measured([1.0, 2.0, -5.0], with_scale=False), tracking, vo.filter.position_ned_m, view)
    np.testing.assert_allclose(p, [1.0, 2.0, -5.0])
    assert k == 1.0
    # The close range (held level frames): a tracking frame's keyframe where it was measured, k = 1;
    # a guessed length or few inliers still go where the filter puts them.
    p, k = keyframe_position(kf, measured([5.0, 2.0, -5.0]), tracking, vo.filter.position_ned_m, view, held_level=True)
    np.testing.assert_allclose(p, [5.0, 2.0, -5.0])
    assert k == 1.0
    for guessed in (StateReason.SCALE_HELD, StateReason.FEW_INLIERS):
        p, k = keyframe_position(
            kf, measured([5.0, 2.0, -5.0]), guessed, vo.filter.position_ned_m, view, held_level=True
        )
        np.testing.assert_allclose(p, [4.02, 2.49, -5.0])
        assert k == 1.0
    filtered_at([21.0, 2.0, -5.0])  # 20 m where 4 m were measured: the factor stops at 2
    assert keyframe_position(kf, measured([5.0, 2.0, -5.0]), tracking, vo.filter.position_ned_m, none)[
        1
    ] == pytest.approx(2.0)
    filtered_at([1.5, 2.0, -5.0])
    assert keyframe_position(kf, measured([5.0, 2.0, -5.0]), tracking, vo.filter.position_ned_m, none)[
        1
    ] == pytest.approx(0.5)


def test_the_close_range_is_entered_below_its_depth_and_left_only_well_beyond_it() -> None:
    """docs/odometry.md, Close range: a keyframe holds its level frame when the scene is nearer than
    keyframes.held_level_below_m (5 m); a chain that holds lets go only beyond held_level_release (1.4)
    times that, 7 m: at the top of `indoor_carpet`'s 3 m hops the triangulated depth read 3.0-4.8 m, and
    each switch out and back in cost the chain."""
    sc = load_scenario("indoor_carpet")
    vo = Odometry(sc.camera.camera_model(), sc.camera.R_body_cam())
    kf = Keyframe(0, 0.0, np.arange(3), np.eye(3), np.full(3, np.nan), np.zeros(3), 0.0, 0.0, math.radians(0.2))
    held_kf = dataclasses.replace(kf, attitude_sigma_rad=math.radians(0.01))
    for depth_m, from_free, from_held in (
        (4.9, True, True),
        (5.1, False, True),
        (6.9, False, True),
        (7.1, False, False),
    ):
        vo._scene_depth_m = depth_m
        assert (vo._holds_level(kf), vo._holds_level(held_kf)) == (from_free, from_held), depth_m


def test_the_position_noise_follows_the_tracks_noise_and_a_height_sources_along_the_translation() -> None:
    """docs/odometry.md, Covariance. At 3 m/s the motion term is position_sigma_per_speed_s * 3 m/s
    times the tracks' noise over track_noise_px (0.1 px), counted from half to ten times it: 4.5 mm for
    tracks at 0.02 px, 45 mm at 0.5 px, 90 mm at 1 px and more or an unknown noise. The same over a floor
    0.5 m below as with the scene 10 m away (a track's error grows with its image motion, f x speed /
    depth, and a pixel moves the position by depth / f): only the image-noise term shrinks with the
    depth, to a fifth. A height source's 1% moves a frame 4 m north of its keyframe by 4 cm north and
    not at all east or down; the votes' spread (here 0) would count everywhere."""
    sc = load_scenario("square")
    vo = Odometry(sc.camera.camera_model(), sc.camera.R_body_cam())
    opt = vo.options
    kf = Keyframe(0, 0.0, np.arange(3), np.eye(3), np.full(3, np.nan), np.array([1.0, 2.0, -10.0]), 0.0, 0.0)
    frame = PairedFrame(np.zeros((4, 4), np.uint8), 1.0, 1, 0.0, 0.0)
    rp = dataclasses.replace(
        _failure(RelposeFailure.NO_MODEL, 40), success=True, reason=RelposeFailure.NONE, attitude_resolved=True
    )

    def noise(track_noise_px: float, sensor_spread: float, depth_m: float) -> np.ndarray:
        m = Measurement(
            np.array([5.0, 2.0, -10.0]),
            0.0,
            dataclasses.replace(rp, residual_rms_rad=track_noise_px / vo._focal_px),
            ScaleEstimate(1.0, ScaleSource.RANGEFINDER, 40, 0.0, sensor_spread),
            np.array([4.0, 0.0, 0.0]),
            50.0,
            np.zeros(0),
            np.zeros(0),
            (0.0, 0.0),
            (np.zeros((0, 3)), np.zeros((0, 3))),
        )
        p, cov = position_noise(
            opt,
            frame,
            kf,
            m,
            depth_m=depth_m,
            focal_px=vo._focal_px,
            speed_m_s=3.0,
            view_attitude_sigmas_rad=(0.0, 0.0),
        )
        assert p is not None
        return cov

    # The image-noise floor: position_sigma_m with the scene 10 m away, a fifth of it at 0.5 m.
    for depth_m, floor_sq in ((10.0, opt.position_sigma_m**2), (0.5, (opt.position_sigma_m / 5) ** 2)):
        for track_px, factor in ((0.02, 0.5), (0.1, 1.0), (0.5, 5.0), (1.0, 10.0), (3.0, 10.0), (math.nan, 10.0)):
            expected = floor_sq + (opt.position_sigma_per_speed_s * 3.0 * factor) ** 2
            np.testing.assert_allclose(
                noise(track_px, 0.0, depth_m), expected * np.eye(3), rtol=1e-9, atol=1e-15, err_msg=f"{depth_m} m"
            )
    extra = noise(0.1, 0.01, 10.0) - noise(0.1, 0.0, 10.0)
    np.testing.assert_allclose(extra, np.diag([0.04**2, 0.0, 0.0]), atol=1e-12)


def test_a_keyframe_matches_the_ids_it_shares_with_a_frame():
    """Against numpy's intersection, on increasing ids as the frontend gives them: lost tracks, new
    ones, none shared, all shared."""
    rng = np.random.default_rng(12)
    for kf_ids, cur_ids in [
        (np.sort(rng.choice(500, 200, replace=False)), np.sort(rng.choice(500, 220, replace=False))),
        (np.arange(10), np.arange(10, 20)),
        (np.arange(10), np.arange(10)),
        (np.array([3, 7, 9]), np.array([1, 7, 8, 9, 12])),
    ]:
        kf = Keyframe(0, 0.0, kf_ids, np.zeros((len(kf_ids), 3)), np.zeros(len(kf_ids)), np.zeros(3), 0.0, 0.0)
        i_kf, i_cur = kf.match(cur_ids)
        _, want_kf, want_cur = np.intersect1d(kf_ids, cur_ids, return_indices=True)
        assert np.array_equal(i_kf, want_kf) and np.array_equal(i_cur, want_cur)
        assert np.array_equal(kf_ids[i_kf], cur_ids[i_cur])


def test_height_from_the_range_is_fused_a_glitch_rejected_and_a_step_of_the_ground_followed() -> None:
    """Hovering 1.00 m above a floor: the range measures the down coordinate (the filter's drifted 0.3 m
    is pulled back); one range 0.4 m short (a glitch) is rejected; a table 0.7 m high slid under the
    vehicle is, after step_frames ranges in a row, the ground stepping: the down coordinate stays."""
    from mavvo.odometry.height import HeightAnchor, HeightOptions

    anchor = HeightAnchor(HeightOptions(step_frames=5))
    f = PoseFilter(FilterOptions())
    f.reset(0.0, np.array([0.0, 0.0, -1.0]), 0.0, pos_cov_m2=0.01 * np.eye(3), yaw_sigma_rad=0.01)
    tilt = math.radians(10.0)
    h = anchor.height_m(1.0 / (math.cos(tilt) * math.cos(tilt)), tilt, tilt)  # tilt-compensated
    assert h == pytest.approx(1.0) and anchor.height_m(2.0, math.radians(40.0), 0.0) is None
    assert anchor.start(-1.0, h, first=True) == -1.0 and anchor.ground_down_m == pytest.approx(0.0)
    f._x[2, 0] = -1.3  # vision's sum of translations drifted 0.3 m up
    for k in range(40):
        f.predict(0.05 * (k + 1))
        f._x[5, 0] = 0.0
        assert anchor.fuse(f, 1.0) is Update.FUSED
    assert f.position_ned_m[2] == pytest.approx(-1.0, abs=0.01)
    assert anchor.fuse(f, 0.6) is Update.REJECTED  # the glitch: rejected, nothing moved
    assert anchor.fuse(f, 1.0) is Update.FUSED
    assert f.position_ned_m[2] == pytest.approx(-1.0, abs=0.01)
    for _ in range(5):  # the table: 0.3 m below the vehicle now
        assert anchor.fuse(f, 0.3) is Update.REJECTED
    assert anchor.steps == 1 and anchor.ground_down_m == pytest.approx(-0.7, abs=0.01)
    assert anchor.fuse(f, 0.3) is Update.FUSED and f.position_ned_m[2] == pytest.approx(-1.0, abs=0.01)
    # A restart after tracking was lost starts at the measured height, not where vision left it.
    assert anchor.start(-1.5, 0.3, first=False) == pytest.approx(-1.0, abs=0.01)


def test_a_range_that_drifts_away_smoothly_is_the_estimate_lagging_not_the_ground_stepping() -> None:
    """A climb the filter has not followed: the range moves 2 cm per frame, the estimate stays. Before,
    five rejections in a row moved the ground by the lag (the sent height then kept that error)."""
    from mavvo.odometry.height import HeightAnchor, HeightOptions

    anchor = HeightAnchor(HeightOptions(step_frames=5))
    f = PoseFilter(FilterOptions())
    f.reset(0.0, np.array([0.0, 0.0, -1.0]), 0.0, pos_cov_m2=1e-4 * np.eye(3), yaw_sigma_rad=0.01)
    anchor.start(-1.0, 1.0, first=True)
    h, pulled = 1.0, []
    for k in range(30):
        h += 0.02
        f.predict(0.02 * (k + 1))
        f._x[2, 0], f._x[5, 0] = -1.0, 0.0  # the estimate does not climb
        anchor.fuse(f, h)
        pulled.append(-1.0 - f.position_ned_m[2])
    assert anchor.steps == 0 and anchor.ground_down_m == pytest.approx(0.0)
    assert max(pulled) > 0.1  # the range won: the estimate was pulled up toward the measured height


def test_while_tracking_the_range_refines_the_ground_then_corrects_the_keyframes_height() -> None:
    """The first keyframe defines the frame: its first range (1.05 m, 5 cm long) sets the ground with a
    range's variance, and n more true ranges (1.00 m) leave it where the n + 1 ranges' mean, weighted by
    their inverse variances, puts it.
    A new keyframe placed 10 cm high with a variance of (10 cm)^2 on top; vision's down is its
    keyframe's plus an exact relative part. Each range now moves the keyframe by K y,
    K = P / (P + sigma^2), and leaves P sigma^2 / (P + sigma^2) (sigma 3 cm + 1% of 1 m): a scalar Kalman
    filter, whose n updates leave an offset e at e sigma^2 / (sigma^2 + n P)."""
    from mavvo.odometry.height import HeightAnchor, HeightOptions

    anchor = HeightAnchor(HeightOptions())
    f = PoseFilter(FilterOptions())
    f.reset(0.0, np.array([0.0, 0.0, -1.0]), 0.0, pos_cov_m2=1e-6 * np.eye(3), yaw_sigma_rad=0.01)
    assert anchor.start(-1.0, 1.05, first=True) == -1.0
    n = 9
    for _ in range(n):
        assert anchor.fuse(f, 1.0, tracking=True) is Update.FUSED and anchor.correction_m == 0.0
    assert f.position_ned_m[2] == -1.0  # the frame's down is its definition
    w0, w = 1 / 0.0405**2, 1 / 0.04**2  # each range's sigma: 3 cm + 1% of its height
    assert anchor.ground_down_m == pytest.approx(0.05 * w0 / (w0 + n * w), rel=1e-9)
    e0 = -0.1 - anchor.ground_down_m  # the keyframe's offset against the ground as it stands
    anchor.keyframe_pushed(0.1**2)
    P, R, keyframe_down = anchor.keyframe_var_m2, 0.04**2, -1.1
    for k in range(n):
        f.predict(0.02 * (k + 1))
        f._x[2, 0] = keyframe_down  # vision's measurement from the keyframe, fused
        assert anchor.fuse(f, 1.0, tracking=True) is Update.FUSED
        if k == 0:
            assert anchor.correction_m == pytest.approx(-e0 * P / (P + R), rel=1e-9)
            assert anchor.keyframe_var_m2 == pytest.approx(P * R / (P + R), rel=1e-9)
        keyframe_down += anchor.correction_m  # the caller moves the keyframe by as much
    assert keyframe_down - (anchor.ground_down_m - 1.0) == pytest.approx(e0 * R / (R + n * P), rel=1e-6)
    before = float(f.position_ned_m[2])
    assert anchor.fuse(f, 0.6, tracking=True) is Update.REJECTED  # a glitch moves nothing
    assert anchor.correction_m == 0.0 and f.position_ned_m[2] == before
