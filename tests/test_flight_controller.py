"""The simulated flight controller speaks valid MAVLink 2 to a plain pymavlink client on loopback."""

from __future__ import annotations

import math
import socket
import threading

import numpy as np
import pytest
from conftest import free_port

from mavvo.sim.flight_controller.autopilot import SimFlightController
from mavvo.sim.flight_controller.spec import FlightControllerSpec
from mavvo.sim.world.clock import LockstepClock, RealClock
from mavvo.sim.world.faults import FaultSchedule, FaultSpec
from mavvo.sim.world.trajectories import FigureEightSpec, HoverSpec, make_trajectory

ATTITUDE = 30
SYSTEM_TIME = 2
DISTANCE_SENSOR = 132


class Link:
    """A lockstep flight controller and a client connected to it over UDP on 127.0.0.1."""

    def __init__(self, mavutil, spec=FlightControllerSpec(), faults=(), trajectory=None, seed=0):
        port = free_port()
        self.clock = LockstepClock()
        self.fc = SimFlightController(
            f"udpin:127.0.0.1:{port}",
            trajectory or make_trajectory(HoverSpec()),
            self.clock,
            spec,
            FaultSchedule(tuple(faults)),
            seed=seed,
        )
        self.client = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        self.mav = mavutil.mavlink
        self.client.mav.heartbeat_send(self.mav.MAV_TYPE_GCS, self.mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def run(self, t_s: float) -> list:
        """Advance the simulation to t_s in 0.1 s steps (a lockstep burst must fit the socket buffer)
        and return everything the client received, in order."""
        out = []
        steps = np.arange(self.clock.now_s(), t_s, 0.1)[1:].tolist() + [t_s]
        for t in steps:
            self.fc.advance_to(t)
            self.clock.advance_to(t)
            while (m := self.client.recv_match(blocking=False)) is not None:  # loopback UDP delivers at once
                out.append(m)
        return out

    def set_interval(self, msg_id: int, interval_us: float) -> None:
        self.client.mav.command_long_send(
            1, 1, self.mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us, 0, 0, 0, 0, 0
        )

    def close(self):
        self.client.close()
        self.fc.close()


@pytest.fixture
def link(mavutil):
    links = []

    def make(**kw):
        links.append(Link(mavutil, **kw))
        return links[-1]

    yield make
    for x in links:
        x.close()


def _of(msgs, kind):
    return [m for m in msgs if m.get_type() == kind]


def test_heartbeat_only_until_asked_then_attitude_at_the_requested_rate(link):
    L = link()
    first = L.run(3.0)
    hb = _of(first, "HEARTBEAT")
    assert {m.get_type() for m in first} == {"HEARTBEAT"}
    assert len(hb) >= 2
    assert hb[0].type == L.mav.MAV_TYPE_QUADROTOR and hb[0].autopilot == L.mav.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb[0].get_srcSystem() == 1 and hb[0].get_msgbuf()[0] == 0xFD  # MAVLink 2 framing

    L.set_interval(ATTITUDE, 20000)
    msgs = L.run(5.0)
    ack = _of(msgs, "COMMAND_ACK")
    assert (
        len(ack) == 1
        and ack[0].command == L.mav.MAV_CMD_SET_MESSAGE_INTERVAL
        and ack[0].result == L.mav.MAV_RESULT_ACCEPTED
    )
    att = _of(msgs, "ATTITUDE")
    assert 99 <= len(att) <= 101  # 2 s at 50 Hz
    dt = np.diff([m.time_boot_ms for m in att])
    assert np.all((dt >= 19) & (dt <= 21))

    L.set_interval(ATTITUDE, 0)  # 0: the default rate
    att = _of(L.run(7.0), "ATTITUDE")
    assert 99 <= len(att) <= 101
    L.set_interval(ATTITUDE, -1)  # -1: off
    L.run(7.5)
    assert _of(L.run(9.0), "ATTITUDE") == []


def test_attitude_noise_bias_latency_and_boot_clock(link):
    spec = FlightControllerSpec(
        attitude_noise_deg=0.2,
        attitude_bias_deg=(0.5, -0.3),
        attitude_latency_ms=30.0,
        boot_offset_s=100.0,
        clock_drift_ppm=1000.0,
    )
    traj = make_trajectory(FigureEightSpec())
    L = link(spec=spec, trajectory=traj, seed=3)
    L.set_interval(ATTITUDE, 10000)
    att = _of(L.run(10.0), "ATTITUDE")
    assert len(att) > 900
    # the measurement time is (time_boot_ms / 1000 - offset) / (1 + drift)
    t_meas = np.array([(m.time_boot_ms / 1000.0 - 100.0) / 1.001 for m in att])
    truth = [traj.state(t) for t in t_meas]
    err_roll = np.degrees([m.roll - s.roll_rad for m, s in zip(att, truth)])
    err_pitch = np.degrees([m.pitch - s.pitch_rad for m, s in zip(att, truth)])
    assert np.mean(err_roll) == pytest.approx(0.5, abs=0.03) and np.std(err_roll) == pytest.approx(0.2, rel=0.1)
    assert np.mean(err_pitch) == pytest.approx(-0.3, abs=0.03) and np.std(err_pitch) == pytest.approx(0.2, rel=0.1)
    # stamped with the measurement time, which is 30 ms before the send time
    assert att[-1].time_boot_ms == pytest.approx((100.0 + (10.0 - 0.030) * 1.001) * 1000, abs=2)


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_timesync_reply_on_the_boot_clock(link, autopilot):
    """PX4 stamps the answer when it handles the request; ArduPilot with its UART's estimate of the
    request's arrival, 5-12 ms early (``timesync_early_ms``)."""
    L = link(spec=FlightControllerSpec(boot_offset_s=42.0, autopilot=autopilot))
    L.run(1.0)
    L.client.mav.timesync_send(0, 123456789)
    ts = _of(L.run(2.0), "TIMESYNC")
    assert len(ts) == 1
    assert ts[0].ts1 == 123456789
    early_ns = (0.0, 0.0) if autopilot == "px4" else (5e6, 12e6)
    assert 43.0e9 - early_ns[1] - 2e6 <= ts[0].tc1 <= 43.0e9 - early_ns[0] + 2e6


def test_reboot_restarts_the_boot_clock_and_stops_streams(link):
    L = link(spec=FlightControllerSpec(boot_offset_s=50.0), faults=[FaultSpec("reboot", 4.05, 2.0)])
    L.set_interval(SYSTEM_TIME, 100000)
    before = L.run(4.02)
    assert _of(before, "SYSTEM_TIME")[-1].time_boot_ms == pytest.approx(54_000, abs=1)
    down = L.run(6.0)
    assert down == []  # nothing while down
    after = L.run(9.0)
    assert len(_of(after, "HEARTBEAT")) == 3 and _of(after, "SYSTEM_TIME") == []  # heartbeats only
    L.set_interval(SYSTEM_TIME, 100000)
    again = _of(L.run(10.0), "SYSTEM_TIME")
    assert again and again[0].time_boot_ms < 4_000  # booted at t = 6.05 s


def test_distance_sensor_and_altitude(link):
    L = link(
        spec=FlightControllerSpec(rangefinder_noise_m=0.0, baro_noise_m=0.0),
        trajectory=make_trajectory(HoverSpec(altitude_m=12.0, drift_m=0.0)),
    )
    L.set_interval(DISTANCE_SENSOR, 0)
    L.set_interval(32, 0)
    L.set_interval(33, 0)
    msgs = L.run(3.0)
    ds = _of(msgs, "DISTANCE_SENSOR")
    assert len(ds) >= 25 and all(m.current_distance == 1200 for m in ds)
    assert ds[0].orientation == L.mav.MAV_SENSOR_ROTATION_PITCH_270
    lp = _of(msgs, "LOCAL_POSITION_NED")
    gp = _of(msgs, "GLOBAL_POSITION_INT")
    assert lp and gp
    bias = L.fc._baro_bias_m
    assert lp[-1].z == pytest.approx(-(12.0 + bias), abs=1e-4)
    assert gp[-1].relative_alt == pytest.approx((12.0 + bias) * 1000, abs=1)


def test_faults_nan_stale_and_corrupt_attitude(link):
    faults = [
        FaultSpec("nan_attitude", 1.0, 0.5),
        FaultSpec("stale_attitude", 2.0, 0.5),
        FaultSpec("corrupt_bytes", 3.0, 0.5),
        FaultSpec("link_silence", 4.0, 0.5),
    ]
    L = link(faults=faults)
    L.set_interval(ATTITUDE, 20000)
    att = _of(L.run(5.0), "ATTITUDE")
    # send time from the stamp: default boot offset 30 s and latency 5 ms; the stamp truncates to 1 ms
    send_t = np.array([(m.time_boot_ms / 1000.0 - 30.0) + 0.005 for m in att])
    nan = np.array([math.isnan(m.roll) for m in att])
    clear = (np.abs(send_t - 1.0) > 0.002) & (np.abs(send_t - 1.5) > 0.002)
    assert np.all(nan[clear] == ((send_t > 1.0) & (send_t < 1.5))[clear]) and nan.sum() >= 24
    # sent in [2.0, 2.5): the sample sent at 1.98 s (measured at 1.975 s) again and again
    assert not any(1.98 < m.time_boot_ms / 1000.0 - 30.0 < 2.49 for m in att)
    repeats = np.sum(np.diff([m.time_boot_ms for m in att]) == 0)
    assert repeats == 25
    assert not np.any((send_t > 3.002) & (send_t < 3.498))  # corrupted: dropped by the client's checksum
    assert not np.any((send_t > 4.002) & (send_t < 4.498))  # silence
    assert L.client.mav.total_receive_errors >= 25


def test_records_what_it_receives_and_saves_a_tlog(link, mavutil, tmp_path):
    L = link()
    L.run(0.5)
    for i in range(5):
        L.client.mav.vision_position_estimate_send(1000 * i, 1.0 + i, 2.0, -3.0, 0.01, 0.02, 0.3, [0.1] * 21, 7)
        L.run(0.6 + 0.1 * i)
    L.client.mav.statustext_send(L.mav.MAV_SEVERITY_INFO, b"mavvo: hello")
    L.run(2.0)
    vpe = [r for r in L.fc.received if r.type == "VISION_POSITION_ESTIMATE"]
    assert [r.msg.x for r in vpe] == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert [r.t_s for r in vpe] == pytest.approx([0.5, 0.6, 0.7, 0.8, 0.9])  # sent while the clock stood there
    assert vpe[0].msg.reset_counter == 7 and vpe[0].msg.covariance[0] == pytest.approx(0.1)
    path = L.fc.save_tlog(tmp_path / "fc.tlog")
    log = mavutil.mavlink_connection(str(path))
    back = []
    while (m := log.recv_match(type=["VISION_POSITION_ESTIMATE", "STATUSTEXT"])) is not None:
        back.append(m)
    assert [m.x for m in back if m.get_type() == "VISION_POSITION_ESTIMATE"] == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert back[-1].text == "mavvo: hello"
    assert back[0]._timestamp == pytest.approx(0.5)


def test_lockstep_bytes_repeat_for_a_seed(link):
    def bytes_of(seed):
        L = link(seed=seed, spec=FlightControllerSpec(attitude_noise_deg=0.3))
        L.set_interval(ATTITUDE, 0)
        return b"".join(bytes(m.get_msgbuf()) for m in L.run(2.0) if m.get_type() == "ATTITUDE")

    a, b, c = bytes_of(11), bytes_of(11), bytes_of(12)
    assert len(a) > 1000 and a == b and a != c


def test_real_time_over_tcp(mavutil):
    port = free_port(socket.SOCK_STREAM)
    clock = RealClock()
    fc = SimFlightController(f"tcpin:127.0.0.1:{port}", make_trajectory(HoverSpec()), clock)
    stop = threading.Event()

    def serve():
        while not stop.is_set():
            fc.advance_to(clock.now_s())
            stop.wait(0.002)

    th = threading.Thread(target=serve)
    th.start()
    try:
        client = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255, source_component=190)
        assert client.recv_match(type="HEARTBEAT", blocking=True, timeout=5) is not None
        client.mav.command_long_send(
            1, 1, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, ATTITUDE, 40000, 0, 0, 0, 0, 0
        )
        att = []
        while len(att) < 20:
            m = client.recv_match(type="ATTITUDE", blocking=True, timeout=5)
            assert m is not None
            att.append(m)
        dt = np.diff([m.time_boot_ms for m in att])
        assert np.median(dt) == pytest.approx(40, abs=1)
        client.close()
    finally:
        stop.set()
        th.join()
        fc.close()
