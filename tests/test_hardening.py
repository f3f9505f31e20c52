"""Hostile and broken input against the service's parts, over real sockets on 127.0.0.1 and real files:
a flood, a configured flight controller, a connected udpout socket, stale estimates, oversized images,
a camera that keeps failing, a second stop signal, and threads that stop or die. The whole service
against each input is the fault suite (tools/faults/suite.py, tests/test_fault_suite.py)."""

from __future__ import annotations

import dataclasses
import json
import resource
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from mavvo.errors import CameraError, FrameRefused
from mavvo.service.camera import ImageFolderSource, InjectedSource, image_size_px
from mavvo.service.link import Link, SystemStatus
from mavvo.service.link_options import LinkOptions
from mavvo.service.mavlink import mavutil
from mavvo.service.settings import ServiceConfig
from mavvo.service.timing import MonotonicClock
from mavvo.sim.flight_controller.autopilot import SimFlightController
from mavvo.sim.flight_controller.spec import FlightControllerSpec
from mavvo.sim.world.clock import RealClock
from mavvo.sim.world.faults import FaultSchedule
from mavvo.sim.world.trajectories import HoverSpec, make_trajectory
from tests.conftest import free_port, wait_for
from tests.test_link import Recorder


def run_bounded(daemon, timeout_s: float = 60.0):
    """``daemon.run()`` on a thread; its summary, or a failed test if it has not returned in time."""
    out = []
    t = threading.Thread(target=lambda: out.append(daemon.run()), daemon=True)
    t.start()
    t.join(timeout_s)
    if not out:
        daemon.request_stop()
        pytest.fail(f"run() did not end within {timeout_s} s")
    return out[0]


class LinkThread:
    """A Link in its own thread, stopped by ``close``."""

    def __init__(self, **options) -> None:
        self.listener = Recorder()
        self.link = Link(LinkOptions(**options), MonotonicClock(), self.listener, lambda: SystemStatus.ACTIVE)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.link.run, args=(self.stop,), daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(10)


class FcThread:
    """The simulated flight controller in real time, in its own thread."""

    def __init__(self, url: str) -> None:
        self.clock = RealClock()
        self.fc = SimFlightController(
            url, make_trajectory(HoverSpec()), self.clock, FlightControllerSpec(), FaultSchedule(())
        )
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            self.fc.advance_to(self.clock.now_s())
            time.sleep(0.002)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(10)
        self.fc.close()


def _heartbeat(mav, sys_id: int) -> bytes:
    m = mavutil().mavlink
    mav.srcSystem = sys_id
    return bytes(
        m.MAVLink_heartbeat_message(
            m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, m.MAV_STATE_ACTIVE, 3
        ).pack(mav)
    )


# ---------------------------------------------------------------------------------------------- the link


def test_a_flood_of_garbage_datagrams_does_not_silence_the_heartbeat():
    """Before the fix the link never left its read loop under a flood: nothing was sent, not even
    HEARTBEAT. The flood's own socket is a client of ``udpin`` and hears the link's HEARTBEATs."""
    port = free_port()
    lt = LinkThread(url=f"udpin:127.0.0.1:{port}")
    flood = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    flood.setblocking(False)
    rng = np.random.default_rng(7)
    garbage = [bytes(rng.integers(0, 256, 200, dtype=np.uint8)) for _ in range(64)]
    parser = mavutil().mavlink.MAVLink(None)
    parser.robust_parsing = True
    heartbeats = 0
    try:
        assert wait_for(lambda: lt.link.connected.is_set())
        deadline = time.monotonic() + 60.0
        sent = 0
        while heartbeats < 3 and time.monotonic() < deadline:
            for g in garbage:  # as fast as the socket takes them
                try:
                    flood.sendto(g, ("127.0.0.1", port))
                    sent += 1
                except BlockingIOError:
                    pass
            try:
                while True:
                    data = flood.recv(65535)
                    heartbeats += sum(1 for m in (parser.parse_buffer(data) or []) if m.get_type() == "HEARTBEAT")
            except BlockingIOError:
                pass
        assert heartbeats >= 3, f"{heartbeats} HEARTBEATs during a flood of {sent} datagrams"
        assert lt.link.counters["bad_data"] > 100  # the garbage was read (and skipped), not ignored
        assert lt.thread.is_alive()
    finally:
        flood.close()
        lt.close()


def test_configured_fc_system_id_ignores_every_other_autopilot():
    port = free_port()
    lt = LinkThread(url=f"udpin:127.0.0.1:{port}", fc_system_id=7)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavutil().mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        assert wait_for(lambda: lt.link.connected.is_set())
        for _ in range(3):
            s.sendto(_heartbeat(mav, 1), ("127.0.0.1", port))
        assert wait_for(lambda: lt.link.counters["other_autopilots"] == 3)
        assert lt.link.fc_system_id == 7 and lt.link.fc_component_id is None
        s.sendto(_heartbeat(mav, 7), ("127.0.0.1", port))
        assert wait_for(lambda: lt.link.fc_component_id == 1)  # the configured one: chosen at its first HEARTBEAT
    finally:
        s.close()
        lt.close()


def test_udpout_is_connected_to_the_flight_controller_only():
    fc = FcThread("udpin:127.0.0.1:0")
    host, port = fc.fc.address
    lt = LinkThread(url=f"udpout:{host}:{port}")
    try:
        assert wait_for(lambda: lt.link.connected.is_set() and lt.link._conn is not None)
        sock = lt.link._conn.port
        assert sock.getpeername() == (host, port)  # the kernel drops datagrams from anyone else
        assert sock.getsockname()[0] == "127.0.0.1"  # not 0.0.0.0: nothing from outside the host reaches it
    finally:
        lt.close()
        fc.close()


def test_an_estimate_past_its_send_by_time_is_dropped_not_sent_late():
    fc = FcThread("udpin:127.0.0.1:0")
    host, port = fc.fc.address
    lt = LinkThread(url=f"udpout:{host}:{port}")
    texts = lambda: [m.msg.text for m in fc.fc.received if m.type == "STATUSTEXT"]  # noqa: E731
    try:
        assert wait_for(lambda: lt.link.connected.is_set())
        from mavvo.service.messages import statustext_line

        lt.link.send("STATUSTEXT", statustext_line("late"), send_by_s=time.monotonic() - 1.0)
        lt.link.send("STATUSTEXT", statustext_line("on time"), send_by_s=time.monotonic() + 60.0)
        assert wait_for(lambda: "on time" in texts())
        assert "late" not in texts() and lt.link.counters["stale_dropped"] == 1
    finally:
        lt.close()
        fc.close()


# ---------------------------------------------------------------------------------------------- the camera


def _write_png(path: Path, w: int, h: int) -> None:
    cv2.imwrite(str(path), np.full((h, w), 128, np.uint8))


def test_image_sizes_are_read_from_headers_without_decoding(tmp_path):
    _write_png(tmp_path / "a.png", 64, 48)
    cv2.imwrite(str(tmp_path / "b.jpg"), np.zeros((30, 70, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "c.bmp"), np.zeros((20, 50), np.uint8))
    cv2.imwrite(str(tmp_path / "d.pgm"), np.zeros((11, 13), np.uint8))
    assert [image_size_px(tmp_path / n) for n in ("a.png", "b.jpg", "c.bmp", "d.pgm")] == [
        (64, 48),
        (70, 30),
        (50, 20),
        (13, 11),
    ]
    (tmp_path / "e.txt").write_bytes(b"not an image")
    assert image_size_px(tmp_path / "e.txt") is None


def test_an_oversized_image_is_refused_before_it_is_decoded(tmp_path):
    """A 20000 x 20000 PNG of one colour is a few hundred kB on disk and 400 MB decoded."""
    _write_png(tmp_path / "0.png", 64, 48)
    big = np.zeros((20000, 20000), np.uint8)
    cv2.imwrite(str(tmp_path / "1.png"), big, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    del big
    _write_png(tmp_path / "2.png", 64, 48)
    (tmp_path / "timestamps.txt").write_text("0.0 0.png\n0.05 1.png\n0.1 2.png\n")

    class Still:
        realtime = False

        def now_s(self) -> float:
            return 0.0

    src = ImageFolderSource(tmp_path, Still(), (640, 480))
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    assert src.read(0.1).image.shape == (48, 64)
    with pytest.raises(
        FrameRefused, match=r"1.png is 20000x20000 px, larger than camera.width_px x height_px = 640x480"
    ):
        src.read(0.1)
    assert src.read(0.1).image.shape == (48, 64)  # the source goes on after the refused one
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 100_000  # kB: never decoded


def test_a_camera_that_keeps_failing_ends_run_with_a_failure():
    """A source that fails for longer than camera.lost_after_s: run() ends with ``failure`` (the CLI
    exits 1 for systemd to restart the service), instead of retrying silently for ever."""
    from mavvo.service.daemon import Daemon

    class Broken:
        def read(self, timeout_s):
            raise CameraError("camera.source /dev/video0: no frame (device lost?)")

        def close(self):
            pass

    base = ServiceConfig()
    cfg = dataclasses.replace(
        base,
        link=dataclasses.replace(base.link, url="udpout:127.0.0.1:9"),
        service=dataclasses.replace(base.service, state_file=""),
        camera=dataclasses.replace(base.camera, lost_after_s=0.3, reconnect_max_s=0.1),
    )
    d = Daemon(cfg, source=Broken())
    summary = run_bounded(d)
    assert "camera thread stopped" in summary.failure and "camera.lost_after_s" in summary.failure
    assert summary.counters["camera_errors"] >= 2


def test_stuck_threads_are_named_and_a_thread_that_waits_on_purpose_is_not():
    """The watchdog is fed only while every loop turns; injected real times, no waiting."""
    from mavvo.service.daemon import Daemon

    base = ServiceConfig()
    cfg = dataclasses.replace(
        base,
        link=dataclasses.replace(base.link, url="udpout:127.0.0.1:9"),
        service=dataclasses.replace(base.service, state_file=""),
    )
    d = Daemon(cfg, source=InjectedSource())
    assert d.stuck_threads(100.0, 2.0) == []  # first look: nothing to compare with
    assert d.stuck_threads(101.0, 2.0) == []
    d.turns["worker"] += 1
    d.link.turns += 1
    assert d.stuck_threads(103.0, 2.0) == ["camera"]  # only the camera's loop has not turned for 3 s
    d.turns["camera"] += 1
    assert d.stuck_threads(104.0, 2.0) == []
    assert d.stuck_threads(106.5, 2.0) == ["link", "camera", "worker"]


# ---------------------------------------------------------------------------------------------- stopping


def test_a_second_stop_signal_skips_the_drain():
    """The first SIGTERM waits up to service.shutdown_drain_s for the worker; a second one does not wait.
    The worker here is stuck for good inside the odometry; the handler is called as the signal would."""
    from mavvo.service.daemon import Daemon

    release = threading.Event()

    class Stuck:
        def track(self, image):
            release.wait()

        def step(self, frame, tracks=None):
            release.wait()

        def restart(self) -> None:
            pass

    base = ServiceConfig()
    cfg = dataclasses.replace(
        base,
        link=dataclasses.replace(base.link, url="udpout:127.0.0.1:9"),
        service=dataclasses.replace(base.service, state_file="", shutdown_drain_s=60.0),
    )
    source = InjectedSource()
    d = Daemon(cfg, source=source)
    d.odometry = Stuck()
    done = threading.Event()
    runner = threading.Thread(target=lambda: (d.run(), done.set()), daemon=True)
    runner.start()
    try:
        source.push(np.zeros((480, 640), np.uint8), time.monotonic())
        assert wait_for(lambda: d.counters["frames"] == 1)  # the worker is inside the stuck odometry
        d.on_signal(signal.SIGTERM, None)
        assert d.stop_event.is_set() and not done.is_set()  # draining: waiting for the worker (up to 60 s)
        d.on_signal(signal.SIGTERM, None)
        assert done.wait(30.0)  # the second signal: no more waiting
    finally:
        release.set()
        runner.join(10)


def test_the_link_thread_dying_ends_run_with_a_failure():
    """A link whose thread dies (here: its listener raises something no message handler expects) no
    longer leaves a worker feeding systemd's watchdog: run() ends with the failure."""
    from mavvo.service.daemon import Daemon

    base = ServiceConfig()
    cfg = dataclasses.replace(
        base,
        link=dataclasses.replace(base.link, url="udpout:127.0.0.1:9"),
        service=dataclasses.replace(base.service, state_file=""),
    )
    d = Daemon(cfg, source=InjectedSource())

    def dies(stop):
        raise MemoryError("the link thread ran out of memory")

    d.link.run = dies
    summary = run_bounded(d)
    assert summary.failure == "the link thread stopped: MemoryError: the link thread ran out of memory"


def test_a_full_disk_stops_recording_keeps_what_was_written_and_sighup_reopens(tmp_path):
    """A recorder in a process whose files may not grow past 40 kB (writes then fail with EFBIG, as
    with ENOSPC on a full disk): the first segment fills, the reopen (SIGHUP's action) starts a second,
    that fills too; recording stops with its reason, close() does not raise, and every file written is
    readable and private. (The whole service against a full disk is the fault suite's full_disk case.)"""
    script = f"""
import json, resource, signal, sys, time
import numpy as np
from mavvo.service.recorder import Recorder, RecordOptions
from mavvo.service.timing import MonotonicClock, Pairing
from mavvo.types import Frame
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (40_000, 40_000))
told = []
rec = Recorder(RecordOptions(dir={str(tmp_path)!r}, min_free_mb=0), "camera: {{}}\\n", MonotonicClock(), on_stop=told.append)
rng = np.random.default_rng(0)
for k in range(400):
    if k == 20:
        rec.reopen()
    rec.frame(Frame(rng.integers(0, 255, (48, 64), dtype=np.uint8), k * 0.05, k), Pairing("paired", k, 0.0, 0.0, 0.0), k * 0.05)
    for _ in range(20):
        rec.mavlink(k * 1000, bytes(40))
    time.sleep(0.002)
    if rec.stopped_reason:
        break
rec.close()
print(json.dumps({{"told": told, "segments": rec.counters["segments"], "frames": rec.counters["frames"]}}))
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["told"] and r["told"][0].startswith("a write failed") and r["segments"] == 2 and r["frames"] > 0
    (folder,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    files = [p for p in folder.rglob("*") if p.is_file()]
    assert {"mavlink-000.tlog", "mavlink-001.tlog", "frames-000.csv", "meta.json"} <= {p.name for p in files}
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in files)
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["stopped_reason"].startswith("a write failed")
    pngs = sorted((folder / "frames").glob("*.png"))
    assert pngs and all(cv2.imread(str(p), cv2.IMREAD_UNCHANGED) is not None for p in pngs)
