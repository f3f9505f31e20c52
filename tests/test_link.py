"""The MAVLink link against the simulated flight controller over real sockets on 127.0.0.1 (and a
pseudo-terminal for serial): identity, streams, TIMESYNC, and surviving reboots, corrupt bytes,
silence and an unplugged serial port."""

from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import pytest

from mavvo.errors import ConfigError
from mavvo.service.link import Link, SystemStatus
from mavvo.service.link_options import LinkOptions, parse_url, read_signing_key
from mavvo.service.timing import MonotonicClock
from mavvo.sim.flight_controller.autopilot import SimFlightController
from mavvo.sim.flight_controller.spec import FlightControllerSpec
from mavvo.sim.world.clock import RealClock
from mavvo.sim.world.faults import FaultSchedule, FaultSpec
from mavvo.sim.world.trajectories import HoverSpec, make_trajectory
from tests.conftest import wait_for


class Recorder:
    """A LinkListener that keeps what it is told."""

    def __init__(self) -> None:
        self.attitude: list[tuple[float, int]] = []  # (arrival monotonic, time_boot_ms)
        self.ranges: list[float | None] = []
        self.heights: list[float] = []
        self.local_positions: list[tuple[float, float, float]] = []
        self.timesync: list[tuple[float, float]] = []
        self.reboots = 0

    def on_attitude(self, t_fc_ms, roll_rad, pitch_rad, yaw_rad, t_arrival_host_s=None, body_rates_rad_s=None):
        self.attitude.append((time.monotonic(), t_fc_ms))

    def on_local_position(self, t_fc_ms, p_ned_m, v_ned_m_s, t_arrival_host_s=None):
        self.local_positions.append(p_ned_m)

    def on_range(self, t_fc_ms, range_m, t_arrival_host_s=None):
        self.ranges.append(range_m)

    def on_height(self, t_fc_ms, height_m, t_arrival_host_s=None):
        self.heights.append(height_m)

    def on_timesync(self, t_sent_host_s, t_fc_s, t_arrival_host_s=None):
        self.timesync.append((t_sent_host_s, t_fc_s))

    def on_reboot(self):
        self.reboots += 1

    def on_armed(self, armed, t_arrival_host_s=None):
        self.armed = armed

    def on_ekf_status(self, attitude_good, compass_ratio, t_arrival_host_s=None):
        self.ekf = (attitude_good, compass_ratio)

    def wants_timesync(self):
        return False


class Running:
    """A real-time simulated flight controller on a UDP port and a Link to it, each in a thread."""

    def __init__(self, faults=(), **link_options) -> None:
        self.clock = RealClock()
        self.fc = SimFlightController(
            "udpin:127.0.0.1:0",
            make_trajectory(HoverSpec()),
            self.clock,
            FlightControllerSpec(),
            FaultSchedule(tuple(faults)),
        )
        host, port = self.fc.address
        self.listener = Recorder()
        self.link = Link(
            LinkOptions(url=f"udpout:{host}:{port}", **link_options),
            MonotonicClock(),
            self.listener,
            lambda: SystemStatus.ACTIVE,
        )
        self.stop = threading.Event()
        self.threads = [
            threading.Thread(target=self._serve, daemon=True),
            threading.Thread(target=self.link.run, args=(self.stop,), daemon=True),
        ]
        for t in self.threads:
            t.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            self.fc.advance_to(self.clock.now_s())
            time.sleep(0.002)

    def sim_time(self) -> float:
        return self.clock.now_s()

    def wait_for(self, done, timeout_s: float = 60.0) -> bool:
        """Until ``done()`` holds, at most ``timeout_s`` (generous: the machine may be loaded)."""
        return wait_for(done, timeout_s)

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(5)
        self.fc.close()


@pytest.fixture
def running():
    made = []

    def make(**kw):
        made.append(Running(**kw))
        return made[-1]

    yield make
    for r in made:
        r.close()


def test_identity_streams_and_clock(running):
    r = running()
    heard = lambda: [m for m in r.fc.received if m.type == "HEARTBEAT"]  # noqa: E731
    assert r.wait_for(
        lambda: (
            heard()
            and len(r.listener.attitude) > 60
            and r.listener.ranges
            and r.listener.heights
            and r.listener.timesync
        )
    )
    hb = heard()
    m = hb[-1]
    assert (m.msg.get_srcSystem(), m.msg.get_srcComponent()) == (1, 197)
    assert (m.msg.type, m.msg.autopilot, m.msg.system_status) == (18, 8, 4)  # ONBOARD_CONTROLLER, INVALID, ACTIVE
    assert m.raw[0] == 0xFD  # MAVLink 2
    att = r.listener.attitude
    assert len(att) > 50 and r.listener.ranges and r.listener.heights
    # The requested 100 Hz on the flight controller's boot clock (a datagram lost under load makes
    # one longer interval, not a different median).
    assert np.median(np.diff([t_fc for _, t_fc in att])) == 10
    assert r.listener.heights[-1] == pytest.approx(10.0, abs=2.0)  # the hover's height above home
    # TIMESYNC: the flight controller's boot clock is 30 s ahead of the simulation clock.
    assert r.listener.timesync
    sent, fc = r.listener.timesync[-1]
    true_offset = 30.0 + (0.0 - r.clock._t0)  # boot = 30 + (monotonic - t0)
    assert fc - sent == pytest.approx(true_offset, abs=0.1)  # within the round trip on a loaded machine


def test_reboot_corrupt_bytes_and_silence_are_survived(running):
    r = running(silence_timeout_s=1.0, request_retry_s=0.5)
    # The faults start once the link hears the streams, however long that takes on a loaded machine.
    assert r.wait_for(lambda: len(r.listener.attitude) > 20)
    t0 = r.sim_time() + 0.5
    r.fc.faults = FaultSchedule(
        (
            FaultSpec("reboot", t0, 0.5),
            FaultSpec("corrupt_bytes", t0 + 1.5, 0.5),
            FaultSpec("link_silence", t0 + 3.0, 2.0),
        )
    )
    # Each step waits for its event (generously), then checks what it left.
    assert r.wait_for(lambda: any(ms < 2000 for _, ms in r.listener.attitude)), (
        "streams were requested again after the reboot"
    )
    assert r.listener.reboots == 1 and r.link.counters["reboots"] == 1
    assert r.wait_for(lambda: r.link.counters["bad_data"] > 0), "corrupt bytes were not counted"
    assert r.wait_for(lambda: r.sim_time() >= t0 + 3.0)
    n_at_silence = len(r.listener.attitude)
    assert r.wait_for(lambda: r.link.counters["reconnects"] >= 1 and len(r.listener.attitude) > n_at_silence + 50), (
        "attitude flows again after the silence"
    )
    assert r.listener.reboots == 1
    assert r.link.connected.is_set()


def test_signed_link_signs_what_it_sends(tmp_path):
    key = tmp_path / "mavlink.key"
    key.write_text("my passphrase\n")
    os.chmod(key, 0o600)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        s.settimeout(5)
        link = Link(
            LinkOptions(url=f"udpout:127.0.0.1:{s.getsockname()[1]}", signing_key_file=str(key)),
            MonotonicClock(),
            Recorder(),
        )
        stop = threading.Event()
        t = threading.Thread(target=link.run, args=(stop,), daemon=True)
        t.start()
        try:
            data, _ = s.recvfrom(300)
        finally:
            stop.set()
            t.join(5)
    assert data[0] == 0xFD and data[2] & 0x01, "MAVLink 2 with the signed flag"
    assert len(data) == 10 + data[1] + 2 + 13  # header, payload, checksum, 13-byte signature


def test_signing_key_forms_and_permissions(tmp_path):
    hexkey = tmp_path / "hex"
    hexkey.write_text("ab" * 32 + "\n")
    os.chmod(hexkey, 0o600)
    assert read_signing_key(hexkey) == bytes([0xAB]) * 32
    loose = tmp_path / "loose"
    loose.write_text("secret")
    os.chmod(loose, 0o640)
    with pytest.raises(ConfigError, match="expected mode 0600 or stricter.*got 0640"):
        read_signing_key(loose)
    with pytest.raises(ConfigError, match="cannot read"):
        read_signing_key(tmp_path / "absent")


def test_connection_strings():
    assert parse_url("/dev/ttyAMA0:921600") == ("/dev/ttyAMA0", 921600)
    assert parse_url("serial:/dev/ttyACM0:115200") == ("/dev/ttyACM0", 115200)
    assert parse_url("udpin:0.0.0.0:14550") == ("udpin:0.0.0.0:14550", None)
    assert parse_url("tcp:127.0.0.1:5760") == ("tcp:127.0.0.1:5760", None)
    for bad in ("/dev/ttyAMA0", "COM3", "udp:1.2.3.4:5", "tcp:host:port"):
        with pytest.raises(ConfigError, match="link.url"):
            parse_url(bad)


def test_serial_port_unplugged_and_back(mavutil):
    """A pseudo-terminal stands in for the flight controller's UART: closing its other end is an
    unplugged cable; the link reconnects when a new one appears at the same path."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    listener = Recorder()
    link = Link(
        LinkOptions(url=f"{path}:115200", silence_timeout_s=1.0, fc_system_id=1), MonotonicClock(), listener
    )  # pinned: one HEARTBEAT chooses it
    stop = threading.Event()
    t = threading.Thread(target=link.run, args=(stop,), daemon=True)
    t.start()
    fc = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        assert link.connected.wait(5)
        os.write(master, fc.heartbeat_encode(2, 3, 0, 0, 4).pack(fc))
        for i in range(20):
            os.write(master, fc.attitude_encode(1000 + 10 * i, 0.1, 0.0, 0.0, 0, 0, 0).pack(fc))
            time.sleep(0.005)
        deadline = time.monotonic() + 5
        while len(listener.attitude) < 20 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(listener.attitude) == 20
        got = os.read(master, 1000)  # what mavvo wrote: its HEARTBEAT, at least
        assert b"\xfd" in got
        os.close(master)  # unplugged
        deadline = time.monotonic() + 10
        while link.counters["reconnects"] == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert link.counters["reconnects"] >= 1
    finally:
        stop.set()
        t.join(10)
        os.close(slave)
    assert not t.is_alive()


def test_mavlink2_whoever_imported_pymavlink_first():
    """A program that imported pymavlink (MAVLink 1 by default) before mavvo still gets MAVLink 2:
    VISION_POSITION_ESTIMATE keeps its covariance and reset_counter."""
    import subprocess
    import sys

    code = (
        "import os; os.environ.pop('MAVLINK20', None)\n"
        "from pymavlink import mavutil as early\n"
        "assert early.mavlink.WIRE_PROTOCOL_VERSION == '1.0', early.mavlink.WIRE_PROTOCOL_VERSION\n"
        "from mavvo.service.mavlink import mavutil\n"
        "mu = mavutil()\n"
        "m = mu.mavlink.MAVLink(None, srcSystem=1, srcComponent=197)\n"
        "buf = m.vision_position_estimate_encode(1, 0, 0, 0, 0, 0, 0, [0.0] * 21, 7).pack(m)\n"
        "print(mu.mavlink.WIRE_PROTOCOL_VERSION, hex(buf[0]), buf[-3])\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MAVLINK20"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 0, out.stderr
    version, magic, reset_counter = out.stdout.split()
    assert (version, magic, reset_counter) == ("2.0", "0xfd", "7")  # MAVLink 2 frame, reset_counter last in the payload


def test_send_after_the_link_stopped_writes_nowhere():
    """A late send() (a worker finishing its frame after the stop) must not write into the closed wake
    pipe's descriptor, which the system may already have given to another file."""
    link = Link(LinkOptions(url="udpout:127.0.0.1:9"), MonotonicClock(), Recorder())
    stop = threading.Event()
    stop.set()
    link.run(stop)  # stops at once, closing its descriptors
    r, w = os.pipe()  # likely reuses the numbers just freed
    try:
        os.set_blocking(r, False)
        link.send("STATUSTEXT", {"severity": 6, "text": b"late"})
        with pytest.raises(BlockingIOError):
            os.read(r, 10)  # nothing arrived in the new pipe
        assert link.counters["sent_after_stop"] == 1
    finally:
        os.close(r)
        os.close(w)
