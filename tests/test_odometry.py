"""The whole odometry on rendered flights in lockstep (deterministic, seeded): accuracy against the
truth, heading drift, hover, fast yaw spin, loss and recovery."""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np
import pytest

from mavvo.evaluation.metrics import Evaluation, PoseSeries, evaluate
from mavvo.geometry.frames import R_from_euler321
from mavvo.odometry.options import OdometryOptions
from mavvo.odometry.pipeline import Odometry
from mavvo.service.yaml_loader import build
from mavvo.sim.scenarios.loader import Scenario, load_scenario
from mavvo.sim.scenarios.paired_frames import PairedSequence
from mavvo.types import PoseEstimate


@dataclass(frozen=True)
class Run:
    estimates: tuple[PoseEstimate, ...]
    sequence: PairedSequence
    resets: int

    def good(self) -> list[PoseEstimate]:
        return [e for e in self.estimates if e.quality >= 0]

    def evaluation(self) -> Evaluation:
        est = self.good()
        t = np.array([e.t_exposure_s for e in est])
        series = PoseSeries.from_rotations(
            t, np.array([e.p_ned_m for e in est]), np.array([R_from_euler321(*e.rpy_rad) for e in est])
        )
        return evaluate(series, self.sequence.camera_truth(t))[0]

    def heading_errors_deg(self) -> np.ndarray:
        """Estimated minus true yaw, relative to the first estimate's error (the initial north error)."""
        est = self.good()
        d = np.array([e.rpy_rad[2] - self.sequence.trajectory.state(e.t_exposure_s).yaw_rad for e in est])
        return np.degrees(np.angle(np.exp(1j * (d - d[0]))))


def _run(scenario: Scenario, options: dict | None = None, duration_s: float | None = None) -> Run:
    seq = PairedSequence(scenario, duration_s=duration_s)
    vo = Odometry(scenario.camera.camera_model(), seq.R_body_cam, build(OdometryOptions, options or {}, "test"))
    out = [e for e in (vo.step(pf) for pf in seq) if e is not None]
    return Run(tuple(out), seq, vo.reset_counter)


@functools.lru_cache(maxsize=None)
def _shipped(name: str, scale_source: str = "rangefinder", duration_s: float | None = None) -> Run:
    return _run(load_scenario(name), {"scale": {"source": scale_source}}, duration_s)


def _forward() -> Run:
    """The forward camera's first 20 s (half the circle): the rangefinder's first interval, then
    carried scale. (The whole circle flies in ``mavvo sim --scenario forward``.)"""
    return _shipped("forward", "carried", 20.0)


@pytest.mark.slow  # a 270 m survey, about a minute: make soak (make test keeps the square, forward and hover flights)
def test_survey_with_rangefinder_meets_the_accuracy_goal() -> None:
    """Nadir camera, rangefinder, 0.1 deg roll/pitch noise, 270 m lawnmower at 30 m."""
    run = _shipped("survey")
    ev = run.evaluation()
    assert ev.path_length_m >= 200.0
    assert run.resets == 0 and len(run.good()) == len(run.estimates)
    assert ev.ate_se3_rmse_percent_of_path <= 1.0  # the goal; the bar is 2%
    assert np.abs(run.heading_errors_deg()).max() <= ev.path_length_m / 100.0  # 1 deg per 100 m
    assert ev.sim3_scale == pytest.approx(1.0, abs=0.01)  # metric: the rangefinder fixes the scale


def test_forward_camera_with_scale_carried_between_keyframes() -> None:
    run = _forward()
    ev = run.evaluation()
    assert run.resets == 0
    sources = {e.diagnostics.scale_source for e in run.good()}
    assert "carried" in sources and "rangefinder" in sources  # the first interval, then carried
    assert 100.0 * ev.ate_sim3_m["rmse"] / ev.path_length_m <= 2.0


def test_a_new_keyframe_is_placed_where_the_filter_puts_its_frame() -> None:
    """The keyframe switch comes at the end of the old keyframe's reach, where a frame's raw measurement
    has its interval's largest error (0.2-0.4 m in the forward flight); a keyframe placed there stepped
    every later position by it. A tracking frame's keyframe is placed at the filter's estimate, which is
    what was sent for that frame, so the next keyframe's positions continue from it (docs/odometry.md)."""
    sc = load_scenario("forward")
    seq = PairedSequence(sc, duration_s=12.0)
    vo = Odometry(
        sc.camera.camera_model(), seq.R_body_cam, build(OdometryOptions, {"scale": {"source": "rangefinder"}}, "test")
    )
    placed = []
    for pf in seq:
        est = vo.step(pf)
        if (
            est is not None and est.diagnostics.keyframe and est.diagnostics.state == "tracking"
        ):  # degraded: docs/odometry.md
            assert vo.chain.current is not None
            placed.append((est.p_ned_m, vo.chain.current.p_ned_m))
    assert len(placed) >= 3
    for sent, keyframe in placed:
        np.testing.assert_allclose(keyframe, sent, atol=1e-9)


def test_hover_stays_put() -> None:
    run = _shipped("hover")
    ev = run.evaluation()
    assert run.resets == 0
    assert ev.ate_se3_m["rmse"] <= 0.05 and ev.ate_se3_m["max"] <= 0.15
    assert np.abs(run.heading_errors_deg()).max() <= 0.2
    assert all(e.diagnostics.state == "tracking" for e in run.estimates[1:])


def test_a_height_sensors_noise_widens_the_covariance_along_the_translation_only() -> None:
    """The rangefinder's 2 cm at 10 m are 0.2% of the scale, a new reading each frame: a hover's frame
    0.3-0.7 m from its keyframe moves by that along the translation from it (horizontal), not across it
    or up and down. The sent covariance is widest along a horizontal direction."""
    run = _shipped("hover")
    widest_z, ratios = [], []
    for e in run.good()[20:]:
        w, V = np.linalg.eigh(e.covariance[:3, :3])
        widest_z.append(abs(V[2, -1]))
        ratios.append(w[-1] / w[0])
    assert np.median(widest_z) < 0.3  # the widest axis is about horizontal (measured: 0.17)
    assert (
        np.median(ratios) > 1.25
    )  # and clearly wider than the narrowest (measured: 1.45; the same in every direction: 1)


def test_fast_yaw_spin_turns_without_moving() -> None:
    """Two turns at 120 deg/s on the spot (the shipped spin without its drift): the heading follows,
    the position does not run off."""
    sc = load_scenario("yaw_spin")
    run = _run(
        dataclasses.replace(sc, trajectory=dataclasses.replace(sc.trajectory, drift_m=0.0)),
        {"scale": {"source": "rangefinder"}},
    )
    ev = run.evaluation()
    assert run.resets == 0 and all(e.quality >= 0 for e in run.estimates)
    # At 10 m; tracks blur at 120 deg/s. Measured: 0.21 m (0.09 m while the Gauss-Newton stopped short
    # of the Sampson minimum: at the minimum the essential model wins GRIC in 31 of the spin's 140 frames,
    # 21 before, and their translations are the blur's). A ground fit's spread weighted by parallax (the
    # few votes with the most, from the rotation's error, agree) let spurious translations through: 0.36 m.
    assert ev.ate_se3_m["max"] <= 0.25
    assert np.abs(run.heading_errors_deg()).max() <= 4.0  # after 720 deg
    assert any(e.diagnostics.reason == "pure_rotation" for e in run.estimates)


def test_fast_yaw_spin_with_drift_does_not_step_at_a_keyframe_made_on_few_inliers() -> None:
    """The shipped spin drifts as the hover does. A keyframe made from a frame measured on few
    inliers goes where the filter puts it: at its raw measurement, the frames of the turn on the spot
    that followed stayed 0.37 m from the last estimate (measured after: 0.11 m). The shipped seed and
    two more draws of the noise: since 2026-11-27 the shipped seed makes no keyframe on few inliers
    (draws 101 and 102 make two and one; largest steps 0.12 / 0.14 / 0.13 m when written)."""
    spin = load_scenario("yaw_spin")
    runs = [_shipped("yaw_spin")] + [
        _run(dataclasses.replace(spin, seed=s), {"scale": {"source": "rangefinder"}}) for s in (101, 102)
    ]
    few_inlier_keyframes = 0
    for run in runs:
        good = run.good()
        t = np.array([e.t_exposure_s for e in good])
        err = np.array([e.p_ned_m for e in good]) - np.array([run.sequence.trajectory.state(x).p_ned_m for x in t])
        few_inlier_keyframes += sum(e.diagnostics.reason == "few_inliers" and e.diagnostics.keyframe for e in good)
        assert np.linalg.norm(np.diff(err, axis=0), axis=1).max() <= 0.2
    assert few_inlier_keyframes >= 2, few_inlier_keyframes  # the case the test is about happened


def test_square_with_altitude_scale() -> None:
    """Flat ground, metric scale from the barometric height (biased by the simulated baro offset)."""
    run = _shipped("square", "altitude")
    ev = run.evaluation()
    # Tracking is never lost; the filter may restart once (a counted reset) where the vehicle stops at
    # the last corner and the filter, coasting without a measured translation, overshot.
    assert sum(e.diagnostics.state == "initialising" for e in run.estimates) == 1 and run.resets <= 1
    sources = {e.diagnostics.scale_source for e in run.good()[1:]}
    assert "altitude" in sources and sources <= {"altitude", "carried", "held", "none"}  # none: at rest
    assert ev.ate_se3_rmse_percent_of_path <= 2.0


@functools.lru_cache(maxsize=None)
def _textureless(coast_max_s: float = OdometryOptions().coast_max_s, trim_deg: float = 0.0) -> Run:
    scenario = build(
        Scenario,
        {
            "name": "loss",
            "seed": 3,
            "trajectory": {"type": "square", "altitude_m": 10.0, "side_m": 10.0, "speed_m_s": 2.0},
            "faults": [{"kind": "textureless_frames", "start_s": 6.0, "duration_s": 1.5}],
            "flight_controller": {"attitude_bias_deg": [trim_deg, trim_deg]},
        },
        "test",
    )
    return _run(scenario, {"coast_max_s": coast_max_s}, duration_s=12.0)


def test_a_textureless_stretch_longer_than_coast_max_s_fails_then_recovers_with_one_reset() -> None:
    run = _textureless(coast_max_s=1.0)  # the stretch lasts 1.5 s
    states = [e.diagnostics.state for e in run.estimates]
    t = np.array([e.t_exposure_s for e in run.estimates])
    failed = np.array([s == "failed" for s in states])
    assert failed.any() and np.all((t[failed] >= 6.0) & (t[failed] < 7.5 + 1e-9))
    assert np.all([e.quality == -1 for e, f in zip(run.estimates, failed) if f])
    # exactly one discontinuity, at the first frame after the stretch, and tracking again after it
    counters = np.array([e.reset_counter for e in run.estimates])
    assert run.resets == 1 and np.count_nonzero(np.diff(counters)) == 1
    first = int(np.argmax(counters == 1))
    assert states[first] == "initialising" and not failed[first:].any()
    # Re-anchored where the vehicle is now (no flight controller position here): the last good pose
    # moved on by the filter's velocity over the outage, which is nearer the truth than the pose itself;
    # its height from the rangefinder against the ground taken at the start (the square is flown at one
    # height: the start's down coordinate, within the range's noise), not dead-reckoned.
    last_good = run.estimates[int(np.nonzero(failed)[0][0]) - 1]
    anchor = run.estimates[first]
    dt = min(anchor.t_exposure_s - last_good.t_exposure_s, OdometryOptions().dead_reckon_max_s)
    np.testing.assert_allclose(anchor.p_ned_m[:2], (last_good.p_ned_m + last_good.v_ned_m_s * dt)[:2], atol=1e-6)
    assert abs(anchor.p_ned_m[2] - run.estimates[0].p_ned_m[2]) < 0.1
    moved = (
        run.sequence.trajectory.pose(anchor.t_exposure_s)[0] - run.sequence.trajectory.pose(last_good.t_exposure_s)[0]
    )
    assert np.linalg.norm((anchor.p_ned_m - last_good.p_ned_m - moved)[:2]) < 0.5 * np.linalg.norm(moved[:2])
    assert states[-1] == "tracking"


def test_a_short_textureless_stretch_is_coasted_through_without_a_reset() -> None:
    """Before: every loss of tracking re-initialised (a reset), the pose dead-reckoned at the last
    velocity; the same stretch re-initialised 0.67 m off. Now the filter coasts on the tilt's
    acceleration and the range, and tracking goes on from there."""
    run = _textureless()
    failed = np.array([e.diagnostics.state == "failed" for e in run.estimates])
    assert failed.any()
    assert run.resets == 0 and {e.reset_counter for e in run.estimates} == {0}
    first = int(np.nonzero(failed)[0][-1]) + 1  # tracking again: a keyframe where the filter coasted to
    resumed = run.estimates[first]
    assert resumed.diagnostics.keyframe and resumed.quality >= 1
    truth = run.sequence.trajectory

    def error(e: PoseEstimate) -> np.ndarray:  # against the truth, both from where they started
        return e.p_ned_m - run.estimates[0].p_ned_m - (truth.pose(e.t_exposure_s)[0] - truth.pose(0.0)[0])

    err = error(resumed)
    assert np.linalg.norm(err[:2]) < 0.1, err  # 0.01 m when written
    assert abs(err[2]) < 0.1  # the range held the height through it
    # what is sent says how far off a 1.5 s coast may be: the truth inside 3 sigma
    sigma = math.sqrt(resumed.covariance[0, 0])
    assert np.all(np.abs(err[:2]) < 3.0 * sigma) and resumed.drift_m >= sigma
    old_err = error(_textureless(coast_max_s=1.0).estimates[first])
    assert np.linalg.norm(err[:2]) < 0.5 * np.linalg.norm(old_err[:2])


def test_a_coast_takes_a_trim_error_of_the_flight_controllers_attitude_off_the_tilt() -> None:
    """The same stretch with the flight controller's roll and pitch 0.5 deg off (the tilt says the
    vehicle accelerates by 0.09 m/s^2 on each axis when it does not): measured while vision tracked for
    6 s, the bias is taken off, and tracking goes on within 0.1 m of the truth as without one (0.01 m
    both when written); taken as the tilt reads it, the 1.5 s coast ended 0.33 m off."""

    def coast_error(run: Run) -> float:
        failed = np.array([e.diagnostics.state == "failed" for e in run.estimates])
        resumed = run.estimates[int(np.nonzero(failed)[0][-1]) + 1]
        truth = run.sequence.trajectory
        moved = truth.pose(resumed.t_exposure_s)[0] - truth.pose(0.0)[0]
        return float(np.linalg.norm((resumed.p_ned_m - run.estimates[0].p_ned_m - moved)[:2]))

    trimmed = _textureless(trim_deg=0.5)
    assert trimmed.resets == 0
    assert coast_error(trimmed) < 0.1, coast_error(trimmed)


def test_no_frozen_pose_is_emitted() -> None:
    """While the drone moves, consecutive sendable estimates never repeat a position (starting from
    rest, the first frames carry no measurable translation and the filter has no velocity yet)."""
    for run in (_textureless(), _forward()):
        good = [e for e in run.estimates if e.quality >= 0 and e.diagnostics.state != "initialising"]
        p = np.array([e.p_ned_m for e in good])
        truth = run.sequence.camera_truth(np.array([e.t_exposure_s for e in good])).positions_xyz_m
        moving = np.linalg.norm(np.diff(truth, axis=0), axis=1) > 0.02  # 0.4 m/s: a measurable shift
        assert moving.sum() > 100
        assert np.all(np.linalg.norm(np.diff(p, axis=0), axis=1)[moving] > 0)


def test_estimates_are_well_formed() -> None:
    for e in _shipped("hover").estimates:
        assert e.p_ned_m.shape == (3,) and e.v_ned_m_s.shape == (3,) and e.rpy_rad.shape == (3,)
        assert e.covariance.shape == (6, 6) and np.allclose(e.covariance, e.covariance.T)
        assert np.all(np.linalg.eigvalsh(e.covariance) > 0)
        assert e.quality == -1 or 1 <= e.quality <= 100


def test_same_frames_same_estimates() -> None:
    a = _run(load_scenario("square"), duration_s=4.0)
    b = _run(load_scenario("square"), duration_s=4.0)
    assert len(a.estimates) == len(b.estimates) > 50
    for x, y in zip(a.estimates, b.estimates):
        assert (
            np.array_equal(x.p_ned_m, y.p_ned_m)
            and np.array_equal(x.covariance, y.covariance)
            and x.quality == y.quality
        )


def test_north_comes_from_the_flight_controller_heading() -> None:
    """The world frame's x is north: the first estimate's yaw is the flight controller's yaw."""
    run = _forward()
    first = run.estimates[0]
    true_yaw = run.sequence.trajectory.state(first.t_exposure_s).yaw_rad
    assert abs(first.rpy_rad[2] - true_yaw) < np.radians(3 * run.sequence.scenario.flight_controller.yaw_noise_deg)


def test_roll_pitch_interpolated_across_a_wide_gap_degrade_the_estimate_and_widen_its_covariance() -> None:
    """Frames whose roll/pitch came from samples 0.5 s apart (a 2 Hz telemetry stream): estimates go on,
    degraded (``attitude_interpolated``), with the interpolation's sigma in the roll/pitch variance;
    frames paired exactly stay tracking."""
    import dataclasses
    import math

    seq = PairedSequence(load_scenario("hover"), duration_s=3.0)
    vo = Odometry(seq.scenario.camera.camera_model(), seq.R_body_cam, OdometryOptions())
    sigma_rad = math.radians(1.5)
    out = []
    for k, pf in enumerate(seq):
        slow = k % 2 == 1
        pf = dataclasses.replace(
            pf, attitude_gap_s=0.5 if slow else 0.0, interpolation_sigma_rad=sigma_rad if slow else 0.0
        )
        e = vo.step(pf)
        if e is not None and k > 0:
            out.append((slow, e))
    slow_est = [e for s, e in out if s and e.quality >= 0]
    exact_est = [e for s, e in out if not s and e.quality >= 0]
    assert len(slow_est) >= 20 and len(exact_est) >= 20
    assert all(e.diagnostics.state == "degraded" and e.diagnostics.reason == "attitude_interpolated" for e in slow_est)
    assert all(e.diagnostics.state == "tracking" for e in exact_est)
    base_var = math.radians(OdometryOptions().attitude_sigma_deg) ** 2
    assert all(e.covariance[3, 3] == pytest.approx(base_var + sigma_rad**2) for e in slow_est)
    assert all(e.covariance[3, 3] == pytest.approx(base_var) for e in exact_est)
    assert all(
        e.diagnostics.attitude_sigma_deg == pytest.approx(math.degrees(math.sqrt(base_var + sigma_rad**2)))
        for e in slow_est
    )
    assert max(e.quality for e in slow_est) <= OdometryOptions().degraded_quality_max


def test_attitude_correction_keeps_a_noisy_flight_controller_from_costing_the_track() -> None:
    """Roll/pitch 0.5 deg off per frame (a flight controller worse than the simulated one): with
    ``odometry.ransac.attitude_correction`` the relative pose corrects them under the prior, the track
    holds and the roll/pitch sent are closer to the truth than the flight controller's. Without it this
    flight reset once and ended 0.12 m RMSE off (0.019 m with it), when written."""
    import dataclasses
    import math

    seq = PairedSequence(load_scenario("square"), duration_s=10.0)
    opts = build(OdometryOptions, {"attitude_sigma_deg": 0.5, "ransac": {"attitude_correction": True}}, "test")
    vo = Odometry(seq.scenario.camera.camera_model(), seq.R_body_cam, opts)
    rng = np.random.default_rng(1)
    out, fc_err, sent_err = [], [], []
    for pf in seq:
        truth = seq.trajectory.state(pf.t_exposure_s)
        n = np.radians(0.5) * rng.standard_normal(2)
        pf = dataclasses.replace(pf, roll_rad=pf.roll_rad + n[0], pitch_rad=pf.pitch_rad + n[1])
        e = vo.step(pf)
        if e is not None and e.quality >= 0:
            out.append(e)
            fc_err.append(math.hypot(pf.roll_rad - truth.roll_rad, pf.pitch_rad - truth.pitch_rad))
            sent_err.append(math.hypot(e.rpy_rad[0] - truth.roll_rad, e.rpy_rad[1] - truth.pitch_rad))
    run = Run(tuple(out), seq, vo.reset_counter)
    assert vo.reset_counter == 0 and len(out) > 190
    assert run.evaluation().ate_se3_m["rmse"] < 0.05
    assert np.median(sent_err) < 0.75 * np.median(fc_err)  # 0.34 against 0.53 deg when written


def test_over_a_faint_floor_a_clean_flight_controller_yaw_holds_the_heading() -> None:
    """indoor_hops' first 12 s: each keyframe's relative yaw rests on few, noisy tracks over a faint
    floor 0.4-1.5 m below, so vision's chained heading wanders; the flight controller's yaw (0.2 deg of
    noise here) pulls it by the Kalman gain of their variances. With only the time constant's pull
    (the flight controller's yaw taken as 180 deg uncertain), the heading wanders further: RMS over the
    flight, as the wander is slow (since the faint floor's tracks live longer, the largest error of the
    unpulled heading is only about twice the pulled one's; its RMS three times)."""
    sc = load_scenario("indoor_hops")
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, rolling_shutter_ms=0.0))  # 16x cheaper to render
    seq = PairedSequence(sc, duration_s=12.0)
    frames = list(seq)

    def rms_heading_error_deg(options: dict) -> float:
        vo = Odometry(sc.camera.camera_model(), seq.R_body_cam, build(OdometryOptions, options, "test"))
        est = [e for e in (vo.step(f) for f in frames) if e is not None and e.quality >= 1]
        d = np.array([e.rpy_rad[2] - seq.trajectory.state(e.t_exposure_s).yaw_rad for e in est])
        return float(np.degrees(np.sqrt(np.mean(np.angle(np.exp(1j * d)) ** 2))))

    pulled, drifting = rms_heading_error_deg({}), rms_heading_error_deg({"fc_yaw_sigma_deg": 180.0})
    assert pulled < 0.3 and drifting > 2.0 * pulled, (pulled, drifting)


def test_a_compass_that_comes_back_clean_is_heard_again_after_vision_drifted() -> None:
    """heading_source ground, armed, the forward camera's first 30 s with a magnetic disturbance that
    turns the flight controller's yaw 5 deg from 2 to 18 s: the gate rightly shuts it out, and vision's
    chained heading drifts by more than the fixed 1 deg meanwhile (a turn and a sideways step look alike
    to a forward camera). When the compass is clean again, the gate widened by the two headings' joint
    uncertainty lets it pull the heading back; the fixed gate alone would never hear it again."""
    sc = load_scenario("forward")
    seq = PairedSequence(sc, duration_s=30.0)
    disturbed = math.radians(5.0)
    frames = [
        dataclasses.replace(f, fc_armed=True, yaw_rad=f.yaw_rad + (disturbed if 2.0 <= f.t_exposure_s < 18.0 else 0.0))
        for f in seq
    ]

    def heading_errors_deg(options: dict) -> tuple[float, float]:
        """The worst heading error while disturbed, and in the last 5 s."""
        vo = Odometry(sc.camera.camera_model(), seq.R_body_cam, build(OdometryOptions, options, "test"))
        est = [e for e in (vo.step(f) for f in frames) if e is not None and e.quality >= 1]
        t = np.array([e.t_exposure_s for e in est])
        d = np.array([e.rpy_rad[2] - seq.trajectory.state(e.t_exposure_s).yaw_rad for e in est])
        d = np.degrees(np.abs(np.angle(np.exp(1j * d))))
        return float(d[t < 18.0].max()), float(d[t > 25.0].max())

    during, after = heading_errors_deg({"heading_source": "ground"})
    _, after_fixed = heading_errors_deg({"heading_source": "ground", "heading_gate_sigmas": 0.0})
    assert during < 2.5  # the disturbed compass was not followed
    assert after < 0.6 and after_fixed > 1.0, (during, after, after_fixed)


def _indoor_hops_keyframe_sigmas_deg(held_level_below_m: float) -> list[float]:
    """The roll/pitch sigma of each keyframe made over indoor_hops' first 3 s (0.3-1.5 m above the floor)."""
    sc = load_scenario("indoor_hops")
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, rolling_shutter_ms=0.0))  # 16x cheaper to render
    seq = PairedSequence(sc, duration_s=3.0)
    options = build(OdometryOptions, {"keyframes": {"held_level_below_m": held_level_below_m}}, "test")
    vo = Odometry(sc.camera.camera_model(), seq.R_body_cam, options)
    sigmas = []
    for f in seq:
        e = vo.step(f)
        if e is not None and e.diagnostics.keyframe and vo.chain.current is not None:
            sigmas.append(math.degrees(vo.chain.current.attitude_sigma_rad))
    return sigmas


def test_keyframes_hold_their_level_frame_while_the_scene_is_near() -> None:
    """docs/odometry.md, Close range: once the floor's depth is measured nearer than
    keyframes.held_level_below_m (5 m), every keyframe holds its level frame (0.01 deg), so the relative
    pose corrects the frame's view, not the keyframe's; before (the scene taken 10 m away until a depth
    is measured), and with the setting at 0, each takes the flight controller's 0.2 deg."""
    held, free = _indoor_hops_keyframe_sigmas_deg(5.0), _indoor_hops_keyframe_sigmas_deg(0.0)
    first = next(i for i, s in enumerate(held) if s < 0.1)
    assert 1 <= first <= 5 and len(held) - first >= 8
    assert held[:first] == pytest.approx([0.2] * first, abs=0.01)  # 0.2 deg and the pairing's interpolation
    assert held[first:] == pytest.approx([0.01] * (len(held) - first))
    assert len(free) >= 8 and free == pytest.approx([0.2] * len(free), abs=0.01)


def test_a_keyframe_placed_off_in_height_is_put_back_by_the_range() -> None:
    """indoor_hops' first 6 s, the current keyframe moved 4 cm up on each of eight frames in a row (as
    relative poses on slipped tracks moved it over a printed floor: the filter follows, here by a restart
    at the measurement once its gate has refused five in a row; with 2 cm steps, since the motion noise
    is no longer scaled down over a close floor, the estimate moved only 6 cm, inside the 5 cm + 2%
    checked below). The range is gated out from about 10 cm on; after step_frames of that the
    down coordinate is set to the range, and it stays within 5 cm + 2% of the height (the accuracy asked
    of a flight with a range). Before, the range won by an update weighed against vision's tight down,
    which moved it by millimetres, and the next measurement from the same keyframe put the error back."""
    sc = load_scenario("indoor_hops")
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, rolling_shutter_ms=0.0))  # 16x cheaper to render
    seq = PairedSequence(sc, duration_s=6.0)
    vo = Odometry(sc.camera.camera_model(), seq.R_body_cam, OdometryOptions())
    t_moved, errors = None, []
    for f in seq:
        e = vo.step(f)
        if e is None or e.quality < 1:
            continue
        true_down = float(seq.camera_truth(np.array([e.t_exposure_s])).positions_xyz_m[0, 2])
        errors.append((e.t_exposure_s, e.p_ned_m[2] - true_down, -true_down))
        if t_moved is None and e.t_exposure_s >= 2.0 or t_moved is not None and e.t_exposure_s < t_moved + 0.15:
            t_moved = e.t_exposure_s if t_moved is None else t_moved
            vo.chain.shift_down(-0.04)
    t, err, height = np.array(errors).T
    err -= err[0]  # the start's offset: where the first keyframe was put
    moved = (t > t_moved) & (t < t_moved + 0.25)
    assert np.max(np.abs(err[moved])) > 0.1  # the keyframe's offset reached the estimate
    after = t > t_moved + 0.5
    assert np.count_nonzero(after) > 100
    assert np.all(np.abs(err[after]) < 0.05 + 0.02 * height[after]), np.max(np.abs(err[after]))
