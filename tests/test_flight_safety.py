"""What the autopilot fuses stays right: judged by the simulated flight controller's own estimator,
with no alignment, through resets, restarts, an EKF yaw that settles after boot, and on the ground."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mavvo.odometry.options import OdometryOptions
from mavvo.odometry.pipeline import Odometry
from mavvo.service.daemon import Daemon
from mavvo.service.settings import ServiceConfig
from mavvo.service.timing import FlightControllerState, TimingOptions
from mavvo.sim.flight_controller.estimator import EstimatorSpec, SimEstimator
from mavvo.sim.scenarios.flight import Simulation
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.service_run import config_for, run_daemon_in_sim
from mavvo.sim.world.camera import SimCamera


class FixedClock:
    realtime = False
    t = 0.0

    def now_s(self) -> float:
        return self.t


# ------------------------------------------------------------------------------------------ units


def test_the_simulated_ekf_snaps_on_a_new_reset_counter_and_fuses_otherwise():
    est = SimEstimator(EstimatorSpec(imu_drift_m_s_per_sqrt_s=0.0), np.zeros(3), np.random.default_rng(0))
    est.propagate(1.0, np.zeros(3))
    est.fuse_vision(1.0, 0.0, 0.0, reset_counter=7)  # the first sample: taken as it is, not a step
    est.fuse_vision(1.05, 1.0, 0.0, reset_counter=7)
    assert est.position_ne_m[0] == pytest.approx(EstimatorSpec().position_gain)  # fused, not snapped
    est.fuse_vision(1.1, 5.0, 2.0, reset_counter=8)
    assert np.allclose(est.position_ne_m, [5.0, 2.0])  # a new counter: the sent position, at once
    assert len(est.steps) == 1 and est.steps[0].step_m == pytest.approx(math.hypot(5.0 - 0.3, 2.0))
    assert est.vision_healthy(1.3) and not est.vision_healthy(1.45)  # ArduPilot's 300 ms


def _attitude_stream(state: FlightControllerState, yaw_error, seconds: float, yaw_rate=0.2, roll=0.3):
    """100 Hz ATTITUDE of a vehicle turning steadily while banked, with the EKF's yaw error added."""
    for k in range(int(seconds * 100)):
        t = k * 0.01
        true_yaw = yaw_rate * t
        # Body rates of a steady turn at bank `roll`: the Euler yaw rate spread over q and r.
        q, r = yaw_rate * math.sin(roll), yaw_rate * math.cos(roll)
        state.on_attitude(int(t * 1000), roll, 0.0, math.remainder(true_yaw + yaw_error(t), math.tau), t, (0.0, q, r))


def test_fc_yaw_counts_as_settled_only_once_it_follows_its_gyro():
    converging = FlightControllerState(FixedClock(), TimingOptions())
    _attitude_stream(converging, lambda t: math.radians(-10.0) * math.exp(-t / 5.0), 5.0)
    assert not converging.yaw_settled  # still moving 0.7 deg/s against its gyro after 5 s
    steady = FlightControllerState(FixedClock(), TimingOptions())
    _attitude_stream(steady, lambda t: math.radians(3.0), 3.0)  # a constant offset is settled: nothing to wait for
    assert steady.yaw_settled
    later = FlightControllerState(FixedClock(), TimingOptions())
    _attitude_stream(later, lambda t: math.radians(-10.0) * math.exp(-t / 5.0), 25.0)
    assert later.yaw_settled


def test_reinitialisation_is_anchored_at_the_flight_controllers_position():
    from mavvo.sim.scenarios.paired_frames import PairedSequence

    sc = dataclasses.replace(load_scenario("hover"), duration_s=3.0)
    frames = list(PairedSequence(sc))
    odo = Odometry(sc.camera.camera_model(), sc.camera.R_body_cam(), OdometryOptions(), reset_counter=250)
    first = None
    for f in frames[:20]:
        first = first or odo.step(f)
    odo.restart()  # tracking given up (a loss shorter than coast_max_s would be coasted through instead)
    there = np.array([3.0, -4.0, -10.0])
    est = odo.step(dataclasses.replace(frames[20], fc_position_ned_m=there))
    assert first is not None and first.reset_counter == 250
    # Horizontally where the flight controller believes; the height from the rangefinder against the
    # ground taken at the first start (a hover: where it started, within the range's noise).
    assert np.allclose(est.p_ned_m[:2], there[:2]) and est.reset_counter == 251
    assert abs(est.p_ned_m[2] - first.p_ned_m[2]) < 0.1
    assert math.sqrt(est.covariance[0, 0]) < 0.1  # the EKF's own belief: no step, the stream's sigma
    assert est.drift_m >= OdometryOptions().anchor_sigma_m  # but only as true as that belief


# ------------------------------------------------------------------------------------ simulated


@pytest.fixture(scope="module")
def faults_run():
    return run_daemon_in_sim(load_scenario("faults"))


@pytest.mark.slow  # the whole faults scenario, 36 s: make soak (make test keeps test_service's fault run)
def test_faults_scenario_is_what_the_vehicle_can_fly_on(faults_run):
    run = faults_run
    v = run.safety
    # Its outages (dark and textureless frames, 1 and 2 s; the link's silence, the reboot) are coasted
    # through: no reset, no step (before coasting: three re-initialisations).
    assert run.resets == 0 and not v.reset_steps_m
    # The goal: 1% of the path (0.61% when written; lockstep repeats bit for bit).
    assert v.fc_end_error_m < 0.01 * v.path_length_m, (v.fc_end_error_m, v.path_length_m)
    # Median NEES 1.12 when written (the frame-to-frame measurement noise of docs/odometry.md).
    assert 0.3 <= v.nees_median <= 3.0, v.nees_median
    assert v.drift_within_3x_fraction >= 0.95


@pytest.mark.slow  # the whole faults scenario again, 36 s: make soak
def test_faults_scenario_reinitialised_instead_of_coasted_makes_no_step_for_the_ekf():
    """The re-initialisations coasting now spares the faults scenario, forced back (coast_max_s 0): each
    anchored where the flight controller's EKF believes the vehicle is, so none moves its estimate by
    more than 0.3 m plus 10% of the motion during the outage."""
    base = ServiceConfig()
    reinit = dataclasses.replace(base, odometry=dataclasses.replace(base.odometry, coast_max_s=0.0))
    run = run_daemon_in_sim(load_scenario("faults"), reinit)
    v = run.safety
    assert run.resets >= 1 and v.reset_steps_m
    assert v.reset_step_excess_m <= 0.0, (v.reset_steps_m, v.reset_step_excess_m)
    assert v.fc_end_error_m < 0.01 * v.path_length_m, (v.fc_end_error_m, v.path_length_m)


def test_with_a_rangefinder_the_sent_height_stays_where_the_truth_is(faults_run):
    """The down coordinate sent, against the truth's, relative to the first estimate (the anchor's own
    offset, the barometer's, aside), through the faults scenario's outages. Before the range measured
    it, its three re-initialisations dead-reckoned it and it drifted 0.19 m; then 0.06 m; now the
    outages are coasted through with the range fused while vision sees nothing."""
    p = np.array([m.z for m in faults_run.vision_messages])
    truth = faults_run.truth.positions_xyz_m[:, 2]
    assert len(p) == len(truth)
    drift = np.abs((p - p[0]) - (truth - truth[0]))
    assert drift.max() < 0.1, drift.max()


@pytest.mark.slow
def test_faults_scenario_keeps_95_percent_of_windows_inside_the_99_percent_ellipse(faults_run):
    """95.7% when written (93.8% before the relative pose left tracks behind a view out of its inliers
    and weighed the rest with a Cauchy loss; lockstep repeats bit for bit). Over five draws of the
    noise 95.0-98.9% (docs/service.md; 92.9% in the worst while the motion term counted the tracks'
    noise only up to twice track_noise_px): the first frame after the 0.5 s without frames and the
    rangefinder's scale slowing into corners are what is left."""
    assert faults_run.safety.nees_inside_99_fraction >= 0.95, faults_run.safety.nees_inside_99_fraction


def test_a_drifting_spin_on_the_spot_is_sent_with_a_covariance_that_covers_the_drift():
    """Keyframes made in a turn on the spot stay where the last one was, each within what its
    parallax could hide; that adds up (``Keyframe.unmeasured_m``) until a translation is measured.
    Counting each on its own, 75% of the 1 s windows were inside the 99% ellipse (median NEES 5.7);
    with the sum 97.2% (2.0), and with it also in the frames measured from such a keyframe 98.6% (1.3)."""
    v = run_daemon_in_sim(load_scenario("yaw_spin")).safety
    assert 0.3 <= v.nees_median <= 3.0, v.nees_median
    assert v.nees_inside_99_fraction >= 0.95, v.nees_inside_99_fraction
    assert v.drift_within_3x_fraction >= 0.95, v.drift_within_3x_fraction


def test_a_service_restart_in_flight_is_a_non_event_for_the_ekf(tmp_path):
    sc = load_scenario("square")
    sim = Simulation(sc, "udpin:127.0.0.1:0")
    host, port = sim.fc.address
    cfg = config_for(sc, ServiceConfig(), f"udpout:{host}:{port}")
    cfg = dataclasses.replace(cfg, service=dataclasses.replace(cfg.service, state_file=str(tmp_path / "state.json")))

    def camera(until_s: float) -> SimCamera:
        return SimCamera(
            sc.camera,
            sim.world,
            sim.trajectory,
            sim.clock,
            faults=sim.faults,
            seed=1,
            advance=sim.advance_to,
            duration_s=until_s,
        )

    try:
        Daemon(cfg, clock=sim.clock, source=camera(12.0)).run()  # flies, then dies at 12 s
        second = camera(20.0)
        second.skip_to(13.0)  # systemd restarts it a second later
        Daemon(cfg, clock=sim.clock, source=second).run()
        sim.fc.poll()
    finally:
        sim.close()
    counters = [r.msg.reset_counter for r in sim.fc.received if r.type == "VISION_POSITION_ESTIMATE"]
    assert len(set(counters)) == 2 and counters[0] != counters[-1]  # the new process did not reuse the counter
    steps = sim.fc.estimator.steps
    assert len(steps) == 1 and steps[0].step_m < 0.3, steps


def test_heading_is_taken_from_the_fc_once_its_yaw_has_settled():
    sc = load_scenario("square")
    sc = dataclasses.replace(
        sc,
        trajectory=dataclasses.replace(sc.trajectory, yaw_deg=30.0),
        duration_s=28.0,
        flight_controller=dataclasses.replace(sc.flight_controller, boot_offset_s=0.0),  # mavvo starts with the FC
    )
    run = run_daemon_in_sim(sc)
    assert run.safety.heading_end_error_deg < 1.0 and run.safety.heading_median_error_deg < 1.0
    # Control: starting at once, with the heading never following the flight controller's, north is off.
    base = ServiceConfig()
    blind = dataclasses.replace(
        base,
        service=dataclasses.replace(base.service, heading_wait_max_s=0.0),
        odometry=dataclasses.replace(base.odometry, heading_correction_time_s=0.0),
    )
    off = run_daemon_in_sim(dataclasses.replace(sc, duration_s=7.0), blind)  # the error is there from the start
    assert off.safety.heading_end_error_deg > 5.0


def _corner_errors_m(run, scenario) -> list[float]:
    """The simulated EKF's horizontal error (no alignment) at each corner of a square, averaged over
    the dwell there: where a vehicle steering on it would have put the corner."""
    from mavvo.sim.world.trajectories import make_trajectory

    traj = make_trajectory(scenario.trajectory)
    e = run.fc_error_ne_m
    states = [traj.state(t) for t in e[:, 0]]
    dwell = np.array([np.linalg.norm(s.v_ned_m_s) < 0.01 and -s.p_ned_m[2] > 9.9 for s in states])
    idx = np.flatnonzero(dwell)
    corners = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    return [float(np.linalg.norm(e[c, 1:], axis=1).mean()) for c in corners if len(c)]


# The scenario's own seed runs in `make soak`; 102, the draw that once failed, runs in `make test`.
@pytest.mark.parametrize("seed", [pytest.param(None, marks=pytest.mark.slow), 102])
def test_north_is_taken_on_the_ground_and_held_against_a_disturbed_compass(seed):
    """A compass 3-4.5 deg off once the motors run (and the flight controller's yaw with it). Before,
    the heading followed that yaw in flight (10 s) and the square turned with it: corners 1.1-1.6 m off
    (real flights: 1.0-2.3 m). Now north is taken while disarmed and vision's heading carries the flight.
    Seed 102: while one keyframe lasted the take-off climb's 2-3x zoom, its relative yaw came out 1-2 deg
    off, vision's heading variance opened the gate to the disturbed compass, and the heading ended
    3.8 deg off with corners 2.1 m off (now 0.26 deg, 0.10 m: a keyframe per quarter of the depth)."""
    sc = dataclasses.replace(load_scenario("square_compass"), duration_s=42.0)  # take-off and three corners
    if seed is not None:
        sc = dataclasses.replace(sc, seed=seed)
    run = run_daemon_in_sim(sc)
    corners = _corner_errors_m(run, sc)
    assert len(corners) == 3 and max(corners) < 0.5, corners
    assert run.safety.heading_median_error_deg < 1.0


@pytest.mark.slow
def test_following_the_disturbed_compass_in_flight_turns_the_square():
    """The control of the test above: the same flight with the heading following the flight
    controller's yaw in flight puts the corners more than 1 m off."""
    sc = load_scenario("square_compass")
    base = ServiceConfig()
    follow = dataclasses.replace(base, odometry=dataclasses.replace(base.odometry, heading_source="follow"))
    followed = _corner_errors_m(run_daemon_in_sim(dataclasses.replace(sc, duration_s=42.0), follow), sc)  # 3 corners
    assert max(followed) > 1.0, followed


def test_on_the_ground_before_take_off_the_sent_sigma_stays_small():
    from mavvo.sim.world.trajectories import HoverSpec

    # Standing on its landing gear: the camera 0.3 m above the ground, not moving at all.
    sc = dataclasses.replace(
        load_scenario("hover"), trajectory=HoverSpec(altitude_m=0.3, drift_m=0.0, duration_s=10.0), duration_s=10.0
    )
    run = run_daemon_in_sim(sc)
    sigma = np.array([math.sqrt(m.covariance[0]) for m in run.vision_messages])
    assert len(sigma) > 100, "the vehicle on the ground should be tracked"
    assert sigma.max() < 0.1, sigma.max()
    # ... and the position it keeps sending stays where it stands.
    p = np.array([[m.x, m.y] for m in run.vision_messages])
    assert np.abs(p - p[0]).max() < 0.05


def test_the_autopilots_word_that_its_yaw_is_aligned_ends_the_wait():
    """A yaw a disturbed compass keeps moving against the gyro (0.3 deg/s) never passes the gyro test:
    the first estimate waited for service.heading_wait_max_s (real flights: 22.5 s, and 30 s then "north
    may be off"). EKF_STATUS_REPORT's attitude flag (ArduPilot: yaw aligned) with the compass inside its
    gate for yaw_settle_window_s settles it; a flag that drops starts the count again."""
    state = FlightControllerState(FixedClock(), TimingOptions(yaw_settle_window_s=1.5))
    clock = state.clock
    for k in range(400):  # 4 s at 100 Hz, the yaw wandering at 0.3 deg/s against a still gyro
        clock.t = k * 0.01
        state.on_attitude(30_000 + k * 10, 0.0, 0.0, math.radians(0.3 * clock.t), body_rates_rad_s=(0.0, 0.0, 0.0))
        if k % 50 == 0:
            state.on_ekf_status(k < 100 or k >= 150, 0.2)  # the flag drops between 1.0 and 1.5 s
    # Good from 1.5 s on: settled by the report at 3.0 s, for exposures from then on.
    assert state.yaw_settled and state.pair(3.0).yaw_settled and not state.pair(2.9).yaw_settled
    untold = FlightControllerState(FixedClock(), TimingOptions(yaw_settle_window_s=1.5))
    for k in range(400):
        untold.clock.t = k * 0.01
        untold.on_attitude(
            30_000 + k * 10, 0.0, 0.0, math.radians(0.3 * untold.clock.t), body_rates_rad_s=(0.0, 0.0, 0.0)
        )
        if k % 50 == 0:
            untold.on_ekf_status(True, 1.5)  # the compass outside its gate: not a word to trust
    assert not untold.yaw_settled
