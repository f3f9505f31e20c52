"""Pairing frames with attitude: the clock offset filters, interpolation at exposure, and the refusals
(stale, missing, spoiled, rebooted) that keep a frame from a wrong attitude."""

from __future__ import annotations

import math
import threading

import cv2
import numpy as np
import pytest

from mavvo.geometry.frames import R_from_euler321, euler321_from_R
from mavvo.service.clock_sync import ClockSync, Evidence
from mavvo.service.timing import FlightControllerState, TimingOptions, wait_for_pairing

OFFSET_S = 30.0  # boot clock minus host clock


class FakeClock:
    def __init__(self, realtime: bool = False) -> None:
        self.t = 0.0
        self.realtime = realtime

    def now_s(self) -> float:
        return self.t


def feed(
    state: FlightControllerState,
    clock: FakeClock,
    times_host_s,
    roll=lambda t: 0.1 * t,
    latency_s=0.004,
    yaw=lambda t: 0.0,
):
    """ATTITUDE measured at each host time, arriving ``latency_s`` later."""
    for t in times_host_s:
        clock.t = t + latency_s
        state.on_attitude(int(round((t + OFFSET_S) * 1000)), roll(t), -0.5 * roll(t), yaw(t))


def test_arrivals_alone_bound_the_offset_by_the_fastest_message():
    sync = ClockSync(window_s=10.0)
    rng = np.random.default_rng(1)
    for t in np.arange(0.0, 5.0, 0.01):
        sync.add_arrival(t + OFFSET_S, t + 0.003 + rng.exponential(0.01))
    assert sync.offset_s() == pytest.approx(OFFSET_S - 0.003, abs=5e-4)
    assert sync.offset_s() <= OFFSET_S - 0.003  # a lower bound, reached by the fastest


def test_timesync_picks_the_shortest_round_trip_and_arrivals_clamp_it():
    sync = ClockSync(window_s=10.0)
    # Asymmetric slow exchanges are off by half their round trip; the fast one is nearly exact.
    for sent, rtt, there in ((1.0, 0.2, 0.19), (2.0, 0.002, 0.001), (3.0, 0.1, 0.0)):
        sync.add_timesync(sent, sent + there + OFFSET_S, sent + rtt)
    assert sync.round_trip_s() == pytest.approx(0.002)
    assert sync.offset_s() == pytest.approx(OFFSET_S, abs=1e-3)
    # A message that arrived 1 ms after it was measured proves the offset is at least OFFSET_S + 0.01 - 0.001.
    sync.add_arrival(4.0 + OFFSET_S + 0.01, 4.001)
    assert sync.offset_s() == pytest.approx(OFFSET_S + 0.009, abs=1e-9)


def test_old_measurements_leave_the_window_so_drift_is_followed():
    sync = ClockSync(window_s=2.0)
    sync.add_arrival(0.0 + OFFSET_S + 0.5, 0.0)  # an old offset, larger
    for t in np.arange(0.1, 5.0, 0.1):
        sync.add_arrival(t + OFFSET_S, t)
    assert sync.offset_s() == pytest.approx(OFFSET_S, abs=1e-9)


def test_roll_and_pitch_are_interpolated_at_the_exposure():
    clock = FakeClock()
    state = FlightControllerState(clock)
    feed(state, clock, np.arange(0.0, 1.0, 0.01), latency_s=0.0)
    p = state.pair(0.5337)
    assert p.status == "paired"
    # Boot-clock milliseconds quantise the sample times; slow linear motion is interpolated between them.
    assert p.roll_rad == pytest.approx(0.05337, abs=1e-6)
    assert p.pitch_rad == pytest.approx(-0.5 * 0.05337, abs=1e-6)


def _turning(t: float) -> np.ndarray:
    """A vehicle tilted 20 deg and turning at a constant 1 rad/s about an axis that is neither level nor
    vertical: its Euler angles do not change linearly."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    return R_from_euler321(math.radians(20.0), 0.0, 0.0) @ cv2.Rodrigues(axis * t)[0]


def test_a_slow_stream_is_interpolated_on_the_rotation_and_its_uncertainty_grows_with_the_gap():
    clock = FakeClock()
    state = FlightControllerState(clock, TimingOptions(max_attitude_gap_s=0.5, attitude_accel_rad_s2=1.0))
    for t in (0.0, 0.5, 1.0):  # 2 Hz, as a ground station logs
        clock.t = t
        state.on_attitude(int(round((t + OFFSET_S) * 1000)), *euler321_from_R(_turning(t)))
    p = state.pair(0.25)
    truth = euler321_from_R(_turning(0.25))
    assert p.status == "paired"
    assert np.allclose([p.roll_rad, p.pitch_rad, p.yaw_rad], truth, atol=1e-9)
    # Each angle on its own would be degrees off here: the test tells the two apart.
    r0, r1 = euler321_from_R(_turning(0.0)), euler321_from_R(_turning(0.5))
    per_angle = [(a + b) / 2 for a, b in zip(r0, r1)]
    assert max(abs(a - b) for a, b in zip(per_angle[:2], truth[:2])) > math.radians(0.5)
    # a/2 (t - t0)(t1 - t): 0.5 * 1.0 * 0.25 * 0.25 at the middle, less near a sample, 0 on one.
    assert p.attitude_gap_s == pytest.approx(0.5, abs=1e-6)
    assert p.interpolation_sigma_rad == pytest.approx(0.03125, rel=1e-3)
    assert state.pair(0.6).interpolation_sigma_rad == pytest.approx(0.5 * 0.1 * 0.4, rel=1e-3)
    on_sample = state.pair(0.5)
    assert on_sample.attitude_gap_s == 0.0 and on_sample.interpolation_sigma_rad == 0.0


def test_yaw_is_interpolated_the_short_way_across_pi():
    clock = FakeClock()
    state = FlightControllerState(clock)

    def yaw(t: float) -> float:  # crosses +pi at t = 0.05
        return math.remainder(math.pi - 0.02 + 0.4 * t, math.tau)

    feed(state, clock, np.arange(0.0, 0.2, 0.01), latency_s=0.0, yaw=yaw)
    p = state.pair(0.055)
    assert (
        p.status == "paired" and abs(math.remainder(p.yaw_rad - yaw(0.055), math.tau)) < 1e-5
    )  # not pi - 0.02 + ... - 2 pi


def test_a_frame_waits_for_the_attitude_after_its_exposure_and_refuses_a_gap():
    clock = FakeClock()
    state = FlightControllerState(clock, TimingOptions(max_attitude_gap_s=0.05))
    feed(state, clock, [0.0, 0.01, 0.02], latency_s=0.0)
    assert state.pair(0.025).status == "wait"
    feed(state, clock, [0.2], latency_s=0.0)  # the stream stalled for 180 ms
    assert state.pair(0.025).status == "stale"
    assert state.pair(0.015).status == "paired"


def test_spoiled_and_repeated_attitude_is_never_interpolated():
    clock = FakeClock()
    state = FlightControllerState(clock)
    feed(state, clock, [0.0, 0.01, 0.02], latency_s=0.0)
    feed(state, clock, [0.03, 0.04, 0.05], latency_s=0.0, roll=lambda t: float("nan"))
    feed(state, clock, [0.02, 0.02], latency_s=0.0)  # a stream repeating its last sample
    assert state.counters["attitude_rejected"] == 5
    feed(state, clock, [0.08], latency_s=0.0)
    assert state.pair(0.04).status == "stale"  # 60 ms between the valid samples around it
    assert state.pair(0.015).status == "paired"


def test_nothing_is_paired_before_the_flight_controller_is_heard_or_after_it_rebooted():
    clock = FakeClock()
    state = FlightControllerState(clock)
    assert state.pair(0.0).status == "missing"
    feed(state, clock, np.arange(0.0, 1.0, 0.01))
    assert state.pair(0.5).status == "paired"
    state.on_reboot()
    assert state.pair(0.5).status == "missing" and state.counters["reboots"] == 1
    # After the reboot the boot clock restarts at zero: the new offset is learnt from the new samples.
    for t in np.arange(1.0, 1.5, 0.01):
        clock.t = t
        state.on_attitude(int(round((t - 1.0) * 1000)), 0.2, 0.0, 0.0)
    p = state.pair(1.25)
    assert p.status == "paired" and p.roll_rad == pytest.approx(0.2)


def test_range_and_height_are_given_only_when_fresh():
    clock = FakeClock()
    state = FlightControllerState(clock, TimingOptions(range_max_age_s=0.2, height_max_age_s=0.5))
    feed(state, clock, np.arange(0.0, 2.0, 0.01))
    state.on_range(int((1.0 + OFFSET_S) * 1000), 12.5)
    state.on_height(int((1.0 + OFFSET_S) * 1000), 11.0)
    p = state.pair(1.1)
    assert (p.range_m, p.height_m) == (12.5, 11.0)
    p = state.pair(1.4)
    assert p.range_m is None and p.height_m == 11.0
    assert state.pair(1.6).height_m is None
    state.on_range(int((1.5 + OFFSET_S) * 1000), None)  # out of range: no reading, not the old one
    assert state.pair(1.5).range_m is None


def test_lockstep_wait_ends_with_the_data_the_clock_or_the_end_of_input():
    """On a lockstep clock the wait is decided by simulated time alone: the sample arriving ends it with
    a pairing, the clock moved past the exposure plus attitude_wait_s ends it as stale, and so does the
    end of input; meanwhile the state says the worker waits for data (what a lockstep driver looks at
    before moving the clock)."""
    clock = FakeClock(realtime=False)
    state = FlightControllerState(clock, TimingOptions(attitude_wait_s=0.1))
    feed(state, clock, [0.0, 0.01])
    assert not state.waiting_for_data()
    result: list = []

    def pair() -> None:
        result.append(wait_for_pairing(state, 0.05))

    worker = threading.Thread(target=pair)
    worker.start()
    assert _eventually(state.waiting_for_data)
    feed(state, clock, [0.04, 0.055])  # the sample after the exposure
    worker.join(10.0)
    assert [p.status for p in result] == ["paired"] and not state.waiting_for_data()

    result.clear()
    worker = threading.Thread(target=lambda: result.append(wait_for_pairing(state, 0.2)))
    worker.start()
    assert _eventually(state.waiting_for_data)
    assert worker.is_alive()  # a stopped clock and no data: it waits, however long that takes
    clock.t = 0.31  # the driver moved the clock past the exposure plus the wait
    worker.join(10.0)
    assert [p.status for p in result] == ["stale"]

    assert wait_for_pairing(state, 0.2, lambda: True).status == "stale"  # no more input will come

    rt = FakeClock(realtime=True)
    state_rt = FlightControllerState(rt, TimingOptions(attitude_wait_s=0.1))
    feed(state_rt, rt, [0.0, 0.01])
    rt.t = 0.3  # the host clock is past the exposure plus the wait: give up at once
    assert wait_for_pairing(state_rt, 0.05).status == "stale"


def _eventually(condition, timeout_s: float = 10.0) -> bool:
    """Whether ``condition()`` holds within ``timeout_s`` of real time (a generous bound, never a measurement)."""
    import time

    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(1e-3)
    return True


def test_one_forged_attitude_stamped_ahead_is_refused_and_genuine_ones_go_on_pairing():
    """Before: one ATTITUDE stamped 1 s ahead moved the clock bound for the sync window (every frame
    then waited and was discarded) and made every genuine sample "not newer". Now it is held as a
    suspect, refused when the next message does not agree, and counted."""
    clock = FakeClock()
    state = FlightControllerState(clock, TimingOptions())
    feed(state, clock, np.arange(0.0, 2.0, 0.01))
    clock.t = 2.0
    state.on_attitude(int(round((2.0 + OFFSET_S + 1.0) * 1000)), 0.9, 0.9, 0.0)  # forged: 1 s ahead, a wrong roll
    feed(state, clock, np.arange(2.01, 3.0, 0.01))
    assert state.counters["attitude_implausible"] == 1 and state.counters["attitude_rejected"] == 0
    p = state.pair(2.505)
    assert p.status == "paired" and p.roll_rad == pytest.approx(
        0.1 * (2.505 - 0.004), abs=1e-6
    )  # the 4 ms path, as before the forgery


def test_a_real_step_of_the_clock_is_followed_once_two_messages_agree():
    """A path that became faster (or any real step) shows in every later message: accepted at the second."""
    clock = FakeClock()
    state = FlightControllerState(clock, TimingOptions())
    feed(state, clock, np.arange(0.0, 2.0, 0.01), latency_s=0.030)
    feed(state, clock, np.arange(2.0, 3.0, 0.01), latency_s=0.002)  # 28 ms faster from now on
    assert state.counters["attitude_implausible"] == 1  # only the first message after the step waited
    assert state.pair(2.5).status == "paired" and state.pair(2.5).roll_rad == pytest.approx(
        0.1 * (2.5 - 0.002), abs=1e-6
    )  # the bound: the 2 ms path


def test_a_forged_timesync_answer_does_not_move_the_offset():
    sync = ClockSync(window_s=30.0)
    for t in np.arange(0.0, 2.0, 0.01):
        sync.add_arrival(t + OFFSET_S, t + 0.004)
    assert sync.add_timesync(1.0, 1.0005 + OFFSET_S, 1.001) is Evidence.USED  # genuine: 1 ms round trip
    before = sync.offset_s()
    forged_ahead = sync.add_timesync(1.5, 1.5 + OFFSET_S + 0.8, 1.5001)  # 0.1 ms "round trip", 0.8 s off
    forged_behind = sync.add_timesync(1.6, 1.6 + OFFSET_S - 0.5, 1.6001)  # the other way
    assert forged_ahead is forged_behind is Evidence.REFUSED
    assert sync.offset_s() == before and sync.round_trip_s() == pytest.approx(0.001)


def test_samples_exactly_the_gap_limit_apart_pair():
    """ATTITUDE at exactly 20 Hz with the default 50 ms limit: every exposure between two samples pairs
    (before: 44 of 95 frames were skipped, 1.05 - 1.00 being a little over 0.05 in binary)."""
    clock = FakeClock()
    state = FlightControllerState(clock, TimingOptions(max_attitude_gap_s=0.05))
    feed(state, clock, [k * 0.05 for k in range(40)])
    statuses = [state.pair(0.0125 + k * 0.05 - 0.004).status for k in range(1, 38)]
    assert statuses == ["paired"] * 37
    wider = FlightControllerState(FakeClock(), TimingOptions(max_attitude_gap_s=0.049))
    feed(wider, wider.clock, [k * 0.05 for k in range(40)])
    assert wider.pair(1.0125 - 0.004).status == "stale"  # a limit below the gap still refuses


def test_a_frame_paired_late_takes_the_rangefinder_and_height_nearest_its_exposure():
    """A frame paired after a slow ATTITUDE stream's next sample: newer readings have arrived meanwhile;
    the ones nearest the exposure are used, and none when none is close enough."""
    clock = FakeClock()
    state = FlightControllerState(
        clock, TimingOptions(max_attitude_gap_s=0.5, range_max_age_s=0.2, height_max_age_s=0.2)
    )
    feed(state, clock, [0.0, 0.5], latency_s=0.0)
    for t, r in ((0.1, 3.1), (0.2, 3.2), (0.3, 3.3), (0.45, 3.45)):
        state.on_range(int(round((t + OFFSET_S) * 1000)), r)
        state.on_height(int(round((t + OFFSET_S) * 1000)), 10 * r)
    p = state.pair(0.21)
    assert p.status == "paired" and p.range_m == pytest.approx(3.2) and p.height_m == pytest.approx(32.0)
    assert state.pair(0.42).range_m == pytest.approx(3.45)
    state.on_range(int(round((0.46 + OFFSET_S) * 1000)), None)  # out of range now
    assert state.pair(0.47).range_m is None and state.pair(0.36).range_m == pytest.approx(3.3)


# ---------------------------------------------------------------- a clock that follows the autopilot


def _fly_clock(
    state: FlightControllerState,
    duration_s: float,
    fc_clock,
    *,
    latency_s=lambda t: 0.004,
    timesync: str | None = "px4",
    rng: np.random.Generator | None = None,
    step_s: float = 0.01,
    paused: tuple[float, float] | None = None,
):
    """ATTITUDE at 100 Hz measured at host time t and stamped ``fc_clock(t)``, arriving ``latency_s(t)``
    later (with up to 2 ms of jitter), and a TIMESYNC request each second answered as ``timesync`` does
    ("px4": stamped when handled, "ardupilot": the request's arrival estimated 5-12 ms early as its
    UART's receive-time estimate does; None: not answered). While ``paused`` (host start, end) the
    autopilot does nothing: no samples, and a request waits for the end. Returns, per TIMESYNC answer,
    whether it was accepted."""
    rng = rng or np.random.default_rng(0)
    events = []
    for t in np.arange(0.0, duration_s, step_s):
        if paused is not None and paused[0] <= t < paused[1]:
            continue
        arrive = t + latency_s(t) + rng.uniform(0, 0.002)
        events.append((arrive, "att", int(math.floor(fc_clock(t) * 1000)), 0.1 * math.sin(t)))
    if timesync is not None:
        for sent in np.arange(0.3, duration_s, 1.0):
            handled = sent + 0.001 + latency_s(sent)
            if paused is not None and paused[0] <= handled < paused[1]:
                handled = paused[1]
            early = rng.uniform(0.005, 0.012) if timesync == "ardupilot" else 0.0
            events.append((handled + latency_s(handled) + 0.001, "sync", sent, fc_clock(handled) - early))
    evidence = []
    for arrive, kind, a, b in sorted(events):
        state.clock.t = arrive
        if kind == "att":
            state.on_attitude(a, b, 0.0, 0.0)
        else:
            before = state.counters["timesync_implausible"]
            state.on_timesync(a, b)
            evidence.append(state.counters["timesync_implausible"] == before)
    return evidence


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_genuine_timesync_answers_of_ardupilot_and_px4_are_accepted(flavour):
    """ArduPilot stamps a TIMESYNC answer with its estimate of when the request's first byte arrived,
    5-12 ms early on a software autopilot; before, 125 of 130 such answers were refused."""
    state = FlightControllerState(FakeClock())
    accepted = _fly_clock(state, 60.0, lambda t: t + OFFSET_S, timesync=flavour)
    assert len(accepted) == 60 and np.mean(accepted) >= 0.95
    assert state.clock_offset_s() == pytest.approx(OFFSET_S, abs=0.005)


def _paired_roll_error(state: FlightControllerState, t_host: float) -> float:
    p = state.pair(t_host)
    assert p.status == "paired", (t_host, p.status)
    return abs(p.roll_rad - 0.1 * math.sin(t_host))


@pytest.mark.parametrize("timesync", ["ardupilot", "px4", None])
def test_a_clock_that_falls_behind_is_followed_within_a_second_or_two(timesync):
    """The autopilot's process stops for 0.9 s and its clock stands still meanwhile: from then on it is
    0.9 s behind. Before, the offset stayed on the old value for the whole window (30 s): every frame
    was skipped as stale, for good. Now a TIMESYNC answer that rules the old offset out confirms the
    step at once; without TIMESYNC the arrivals do after clock_step_confirm_s."""
    clock = FakeClock()
    state = FlightControllerState(clock)
    pause = (20.0, 20.9)

    def fc_clock(t):
        return t + OFFSET_S - (min(max(t - pause[0], 0.0), pause[1] - pause[0]))

    _fly_clock(state, 25.0, fc_clock, timesync=timesync, paused=pause)
    steps = state.take_clock_steps()
    assert len(steps) == 1 and steps[0].step_s == pytest.approx(-0.9, abs=0.01)
    assert steps[0].t_host_s < pause[1] + (1.3 if timesync else 1.1)  # re-synchronised within about a second
    assert steps[0].evidence == ("timesync" if timesync else "arrivals")
    assert state.take_clock_steps() == []  # told once
    assert state.clock_offset_s() == pytest.approx(OFFSET_S - 0.9, abs=0.005)
    # Frames after the step pair with the attitude of their own moment (roll 0.1 sin(t): 1 ms is 1e-4 rad).
    assert max(_paired_roll_error(state, t) for t in np.arange(23.2, 24.9, 0.037)) < 5e-4


def test_a_frame_from_the_pause_is_not_paired_with_the_attitude_from_before_it():
    """Mapped with the new offset, an exposure inside the pause lands on samples measured before it,
    0.9 s earlier: those are dropped with the step."""
    state = FlightControllerState(FakeClock())
    _fly_clock(state, 22.0, lambda t: t + OFFSET_S - min(max(t - 20.0, 0.0), 0.9), paused=(20.0, 20.9))
    assert state.counters["clock_steps"] == 1
    assert [state.pair(t).status for t in (20.3, 20.6, 20.85)] == ["stale"] * 3
    assert state.pair(21.5).status == "paired"


def test_a_slower_link_is_not_taken_for_a_clock_step():
    """For 4 s every message takes 80 ms longer: arrivals alone look just like the clock falling 80 ms
    behind, but the TIMESYNC round trips grow with the link's delay, so none rules the old offset out,
    and frames still pair with the attitude of their own moment."""
    state = FlightControllerState(FakeClock())
    _fly_clock(state, 24.0, lambda t: t + OFFSET_S, latency_s=lambda t: 0.084 if 20.0 <= t < 24.0 else 0.004)
    assert state.counters["clock_steps"] == 0 and state.take_clock_steps() == []
    assert state.clock_offset_s() == pytest.approx(OFFSET_S, abs=0.005)  # TIMESYNC: the truth, within a few ms
    assert max(_paired_roll_error(state, t) for t in np.arange(22.5, 23.8, 0.037)) < 5e-4


def test_the_offset_follows_a_clock_that_runs_slow():
    """A software autopilot under load loses time steadily (here 400 ppm). Before, the window's maximum
    lagged the truth by the drift over the window (12 ms over 30 s); the fitted rate follows it."""
    state = FlightControllerState(FakeClock())
    _fly_clock(state, 140.0, lambda t: OFFSET_S + t * (1 - 400e-6), timesync="ardupilot")
    truth = OFFSET_S - 400e-6 * state.clock.t
    assert state.clock_offset_s() == pytest.approx(truth - 0.004, abs=0.002)


def test_old_timesync_answers_leave_the_window_by_age():
    """An accepted answer used to stay until a newer one was accepted: one from before a step held the
    offset there for good."""
    sync = ClockSync(window_s=5.0)
    assert sync.add_timesync(0.0, OFFSET_S + 0.0005, 0.001) is Evidence.USED
    for t in np.arange(0.01, 10.0, 0.01):
        sync.add_arrival(t + OFFSET_S - 0.2, t + 0.004)  # the arrivals' bound, 0.2 s lower
    assert sync.round_trip_s() is None and sync.offset_s() == pytest.approx(OFFSET_S - 0.204, abs=1e-6)
