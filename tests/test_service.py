"""The service end to end: the daemon, the simulated flight controller over UDP on 127.0.0.1 and the
rendered camera in lockstep; faults it must live through; a clean stop on SIGTERM; systemd's
notifications."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from mavvo.errors import CameraEnded, CameraError
from mavvo.service.camera import InjectedSource, ReconnectingSource
from mavvo.service.settings import OutputOptions, ServiceConfig
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.service_run import run_daemon_in_sim
from mavvo.sim.world.faults import FaultSpec


@pytest.fixture(scope="module")
def figure_eight():
    """The default scenario with ODOMETRY on: one run shared by the end-to-end checks (its first 30 s:
    about 76 m, most of the figure)."""
    cfg = dataclasses.replace(ServiceConfig(), output=OutputOptions(odometry=True))
    return run_daemon_in_sim(load_scenario("figure_eight"), cfg, duration_s=30.0)


def test_vision_estimates_reach_the_flight_controller_as_mavlink2_from_component_197(figure_eight):
    run = figure_eight
    vpe = run.vision_messages
    assert len(vpe) > 0.95 * run.daemon.counters["paired"]
    for m in vpe[:: max(len(vpe) // 50, 1)]:
        assert m.get_srcComponent() == 197 and m.get_msgbuf()[0] == 0xFD
        cov = np.array(m.covariance)
        assert np.all(np.isfinite(cov)) and all(cov[i] > 0 for i in (0, 6, 11, 15, 18, 20))
    assert {m.reset_counter for m in vpe} == {0} and run.resets == 0
    # At the camera's 20 frames/s (under the 30 Hz cap): usec steps of 50 ms, none shorter.
    dt = np.diff([m.usec for m in vpe]) * 1e-6
    assert np.min(dt) >= 0.05 - 1e-6 and np.median(dt) == pytest.approx(0.05, abs=1e-6)
    assert run.received["VISION_SPEED_ESTIMATE"] == len(vpe) and run.received["ODOMETRY"] == len(vpe)
    assert run.received["HEARTBEAT"] >= run.duration_s - 2 and run.received["STATUSTEXT"] >= 1
    assert run.received["NAMED_VALUE_FLOAT"] >= 4 * (run.duration_s - 2) * 0.9  # four values at 1 Hz


def test_trajectory_error_is_within_the_odometry_bar(figure_eight):
    ev = figure_eight.evaluation
    assert ev is not None and ev.path_length_m > 70
    assert ev.ate_se3_rmse_percent_of_path < 1.0  # the bar of the odometry on nadir flights with a rangefinder
    assert abs(ev.sim3_scale - 1.0) < 0.02


def test_summary_has_what_mavvo_sim_json_promises(figure_eight):
    s = figure_eight.summary()
    for key in ("ate_rmse_m", "path_length_m", "frames", "estimates_received", "resets"):
        assert s[key] is not None, key
    json.dumps(s)  # serialisable as it stands


def test_rate_cap(tmp_path):
    cfg = dataclasses.replace(ServiceConfig(), output=OutputOptions(max_rate_hz=8.0, speed_estimate=False))
    run = run_daemon_in_sim(
        load_scenario("hover"), cfg, duration_s=6.0
    )  # estimates start after ~3.5 s (FC chosen, yaw settled)
    dt = np.diff([m.usec for m in run.vision_messages]) * 1e-6
    assert len(dt) > 10 and np.min(dt) >= 1 / 8.0 - 1e-6 and np.max(dt) <= 0.15 + 1e-6  # every third frame of 20
    assert "VISION_SPEED_ESTIMATE" not in run.received and run.daemon.counters["not_sent_rate"] > 0


def test_faults_are_survived_and_recovered_from():
    t0 = 5.0  # estimates flow by then (the flight controller chosen, its yaw settled)
    faults = (
        FaultSpec("link_silence", t0, 4.0),  # longer than link.silence_timeout_s: a reconnect
        FaultSpec("reboot", t0 + 6.0, 1.5),
        FaultSpec("nan_attitude", t0 + 10.0, 0.5),
        FaultSpec("stale_attitude", t0 + 12.0, 0.5),
        FaultSpec("corrupt_bytes", t0 + 14.0, 1.0),
        FaultSpec("frames_missing", t0 + 16.0, 1.0),
    )
    scenario = dataclasses.replace(load_scenario("hover"), faults=faults, duration_s=t0 + 21.0)
    run = run_daemon_in_sim(scenario)
    c = run.daemon.counters
    assert c["link_reconnects"] >= 1 and c["link_reboots"] == 1 and c["fc_reboots"] == 1
    assert c["fc_attitude_rejected"] > 0  # NaN and repeated samples refused
    assert c["skipped_attitude_stale"] > 0 and c["link_bad_data"] > 0
    assert c.get("errors", 0) == 0
    t = np.array([m.usec for m in run.vision_messages]) * 1e-6
    # Estimates resume after each fault, and never during the silence or the reboot (no attitude then).
    for f in faults:
        assert np.any((t > f.end_s) & (t < f.end_s + 3.0)), f"no estimate within 3 s after {f.kind}"
    assert not np.any((t > t0 + 0.3) & (t < t0 + 4.0)) and not np.any((t > t0 + 6.05) & (t < t0 + 7.5))
    # No frozen pose around the faults: consecutive estimates never repeat a position exactly. (At the very
    # start the hover shows no parallax yet, and the filter rightly holds the origin.)
    p = np.array([[m.x, m.y, m.z] for m in run.vision_messages])[t > t[0] + 2.0]
    assert len(p) > 200 and not np.any(np.all(np.diff(p, axis=0) == 0, axis=1))
    assert run.evaluation is not None and run.evaluation.ate_se3_m["rmse"] < 0.5
    assert run.daemon.state == "tracking"
    # The operator is told: vision failed for want of attitude during the silence, and tracking came back.
    texts = run.statustexts
    assert any(t0 < t < t0 + 4.5 and text == "mavvo: failed (no_attitude)" for t, text in texts), texts
    # (state changes within statustext_min_interval_s are merged: "failed (no_attitude) then tracking")
    assert any(t > t0 + 4.0 and (text == "mavvo: tracking" or text.endswith(" then tracking")) for t, text in texts), (
        texts
    )
    # During the silence and the reboot the stream stalled; the operator is not told to raise a rate that is fine.
    assert not any("link.attitude_rate_hz" in text for _, text in texts), texts
    # HEARTBEAT: CRITICAL (5) while vision had failed, ACTIVE (4) again afterwards, never
    # FLIGHT_TERMINATION (7), which would tell the ground station the vehicle is terminating itself.
    status = run.heartbeat_status
    assert 7 not in {s for _, s in status}
    assert any(t0 < t < t0 + 4.5 and s == 5 for t, s in status), status
    assert status[-1][1] == 4


def _offline_config() -> ServiceConfig:
    """Settings for a daemon with no flight controller (the link sends into the void) and no state file."""
    base = ServiceConfig()
    return dataclasses.replace(
        base,
        link=dataclasses.replace(base.link, url="udpout:127.0.0.1:9"),
        service=dataclasses.replace(base.service, state_file=""),
    )


class FixedClock:
    """A lockstep host clock that the test sets."""

    realtime = False
    t = 0.0

    def now_s(self) -> float:
        return self.t


def test_bad_frames_are_counted_not_fatal():
    """Frames of the wrong size or type from the camera: counted and skipped, the service goes on."""
    from mavvo.service.daemon import Daemon

    source = InjectedSource()
    source.push(np.zeros((10, 10), np.uint8), 0.0)
    source.push(np.zeros((480, 640), np.float32), 0.05)
    source.end()
    cfg = _offline_config()
    clock = FixedClock()
    d = Daemon(cfg, source=source, clock=clock)
    for t_ms in (0, 40, 80):  # an attitude stream around the exposures, arriving at once: boot clock = host clock
        clock.t = t_ms * 1e-3
        d.fc.on_attitude(t_ms, 0.0, 0.0, 0.0)
    summary = d.run()
    assert summary.counters["bad_frames"] == 2 and summary.counters["frames"] == 2


def test_messages_held_by_a_disconnected_link_do_not_hold_a_lockstep_driver():
    """What the worker queues while the link is down (a reconnect's back-off) is written after the
    reconnect, which only a later tick brings: a driver that waited for it held the clock for its whole
    timeout on every frame of the back-off (the faults flight's lockstep twin, now and then)."""
    from mavvo.service.daemon import Daemon

    d = Daemon(_offline_config(), source=InjectedSource(), clock=FixedClock())
    assert not d.link.connected.is_set()
    d.link.send("NAMED_VALUE_FLOAT", {"time_boot_ms": 0, "name": b"VO_DRIFT", "value": 0.1})
    assert d.link.sends_pending() == 1
    p = d.progress()
    assert p.sends_pending == 0 and p.idle_after(0)


def test_lockstep_hook_reports_progress_a_driver_can_wait_for():
    """The documented hook a simulation or replay drives the daemon with: hand over a frame, wait until
    the daemon can do nothing more with it (finished, or waiting for an ATTITUDE), move the clock on;
    the counts only grow. A frame with its ATTITUDE pairs at once; one without waits, on a stopped
    clock, until the driver moves the clock past the exposure plus timing.attitude_wait_s."""
    from mavvo.service.daemon import Daemon

    source = InjectedSource()
    cfg = _offline_config()
    clock = FixedClock()
    d = Daemon(cfg, source=source, clock=clock)
    assert d.progress().frames_done == 0 and d.progress().fc_state_version == 0
    d.fc.on_attitude(0, 0.0, 0.0, 0.0)
    assert d.progress().fc_state_version == 1
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    try:
        source.push(np.zeros((480, 640), np.uint8), 0.0)  # exposed at the ATTITUDE's time: paired at once
        assert d.wait_progress(lambda p: p.idle_after(1), timeout_s=60.0)
        assert d.progress().frames_done == 1
        for k in (1, 2):
            source.push(np.zeros((480, 640), np.uint8), 0.01 * k)  # no ATTITUDE after it yet
            assert d.wait_progress(lambda p, k=k: p.idle_after(k + 1), timeout_s=60.0)
            p = d.progress()
            assert p.frames_done == k and p.waiting_for_attitude
            clock.t = 0.01 * k + cfg.timing.attitude_wait_s + 1e-3  # the driver moves the clock on
            assert d.wait_progress(lambda p, k=k: p.frames_done >= k + 1, timeout_s=60.0)
        p = d.progress()
        assert p.frames_done == 3 and not p.waiting_for_attitude and d.counters["skipped_attitude_stale"] == 2
        assert not d.wait_progress(lambda p: p.frames_done >= 4, timeout_s=0.2)  # nothing more was handed over
    finally:
        source.end()
        d.request_stop()
        runner.join(30)
    assert not runner.is_alive()


def test_reconnecting_source_reopens_a_lost_camera():
    class Clock:
        realtime = True
        t = 0.0

        def now_s(self):
            return self.t

    clock = Clock()
    opens = {"n": 0}

    class Flaky:
        def __init__(self):
            opens["n"] += 1
            self.reads = 0

        def read(self, timeout_s):
            self.reads += 1
            if self.reads > 2:
                raise CameraError("device lost")
            return "frame"

        def close(self):
            pass

    def opener():
        if opens["n"] == 1 and clock.t < 1.0:
            raise CameraError("not back yet")
        return Flaky()

    src = ReconnectingSource(opener, clock, reconnect_max_s=1.0)
    assert [src.read(0.01) for _ in range(3)] == ["frame", "frame", None]  # lost on the third read
    clock.t = 0.5
    assert src.read(0.01) is None  # reopening fails: still away
    clock.t = 2.0
    assert src.read(0.01) == "frame" and src.reconnects == 1

    class Ended:
        def read(self, timeout_s):
            raise CameraEnded("done")

        def close(self):
            pass

    with pytest.raises(CameraEnded):
        ReconnectingSource(Ended, clock).read(0.01)


def _notify_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    s.settimeout(60)
    return s, path


def test_sigterm_during_work_stops_cleanly_with_systemd_notifications(tmp_path):
    sock, path = _notify_socket(tmp_path)
    env = dict(os.environ, NOTIFY_SOCKET=path, WATCHDOG_USEC="400000")
    proc = subprocess.Popen(
        [sys.executable, "-m", "mavvo", "sim", "--scenario", "hover", "--json", "--out", str(tmp_path / "out")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    lines: list[str] = []
    try:
        states = []
        while "WATCHDOG=1" not in states:
            states.append(sock.recv(100).decode())
        # Status lines may come first (loading the compiled kernels); READY=1 before any watchdog ping.
        events = [x for x in states if not x.startswith("STATUS=")]
        assert events[0] == "READY=1" and any(
            x.startswith("STATUS=") and "kernels" in x for x in states[: states.index("READY=1")]
        )
        # Wait (generously) until the daemon is at work, tracking and sending: its log says so.
        reader = threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")), daemon=True)
        reader.start()
        deadline = time.monotonic() + 60.0
        while not any("-> tracking" in line for line in lines) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        out = proc.stdout.read()
        proc.wait(timeout=30)
        reader.join(10)
        while "STOPPING=1" not in states:
            states.append(sock.recv(100).decode())
    finally:
        if proc.poll() is None:
            proc.kill()
        sock.close()
    err = "".join(lines)
    assert proc.returncode == 0, err
    summary = json.loads(out)
    assert summary["estimates_received"] > 0 and summary["duration_s"] < 29.0  # stopped before the 30 s hover ended
    assert "Traceback" not in err


def test_mavvo_run_reads_an_image_folder_and_stops_on_sigterm(tmp_path):
    """``mavvo run`` with a real YAML file, an image folder as the camera (paced at its timestamps, one
    frame a second) and no flight controller: it keeps going (no attitude: every frame skipped and
    counted) until SIGTERM, then exits 0 before the folder's last frame is due."""
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    lines = []
    for i in range(30):
        cv2.imwrite(str(folder / f"{i:04d}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))
        lines.append(f"{i * 1.0:.3f} {i:04d}.png")
    (folder / "timestamps.txt").write_text("\n".join(lines) + "\n")
    cfg = tmp_path / "mavvo.yaml"
    cfg.write_text(
        f"camera: {{source: '{folder}'}}\nlink: {{url: 'udpout:127.0.0.1:9'}}\nservice: {{health_log_interval_s: 0.5, state_file: ''}}\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "mavvo", "run", "--config", str(cfg)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines: list[str] = []
    try:
        # Wait (generously) for the event, not for a time: the health line that counts the third
        # frame skipped for want of attitude.
        reader = threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")), daemon=True)
        reader.start()
        deadline = time.monotonic() + 60.0
        while (
            not any("skipped_attitude_missing 3" in line for line in lines)
            and proc.poll() is None
            and time.monotonic() < deadline
        ):
            time.sleep(0.05)
        assert proc.poll() is None, "the service stopped by itself: " + "".join(lines)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        reader.join(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = "".join(lines)
    assert proc.returncode == 0, err
    final = [line for line in lines if "final:" in line]
    assert len(final) == 1 and "frames_dropped" not in final[0]
    n = int(final[0].split("frames ")[1].split(",")[0])
    # Every frame was skipped and counted, and SIGTERM stopped the service before the folder's end.
    assert 3 <= n < 29 and f"skipped_attitude_missing {n}" in final[0]


class StoppedWallClock:
    """Real time that does not move: processing takes no time (the test injects it, not measures it)."""

    realtime = True

    def now_s(self) -> float:
        return 0.0


def test_latency_advice_follows_the_cameras_latency():
    """In lockstep the capture-to-send latency is the simulated camera's readout latency plus the
    processing time (injected here as zero), not the frame period: 40 ms more readout, 40 ms more advice."""

    def advice(readout_ms: float):
        sc = load_scenario("hover")
        sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, readout_latency_ms=readout_ms))
        return run_daemon_in_sim(sc, duration_s=6.0, wall_clock=StoppedWallClock()).daemon.latency

    fast, slow = advice(20.0), advice(60.0)
    assert fast is not None and slow is not None and fast.samples > 20
    assert fast.min_ms == pytest.approx(20.0) and fast.p95_ms == pytest.approx(20.0)  # not the 50 ms frame period
    assert (fast.ardupilot_delay_ms, fast.px4_delay_ms) == (20, 20)
    assert (slow.ardupilot_delay_ms, slow.px4_delay_ms) == (60, 60)
    assert fast.transfer_ms == 0.0  # a socket: nothing on the wire to add


def test_serial_transfer_time_is_bytes_over_baud():
    from mavvo.service.latency import VPE_FRAME_BYTES, LatencyTracker

    t = LatencyTracker(baud=57600)
    for ms in (30, 32, 35, 60):
        t.add(ms * 1e-3)
    s = t.stats()
    assert s.transfer_ms == pytest.approx(VPE_FRAME_BYTES * 10 / 57600 * 1e3)  # 22 ms at 57600 baud
    assert s.min_ms == pytest.approx(30.0) and s.p50_ms == pytest.approx(33.5)
    assert s.ardupilot_delay_ms == round(30.0 + s.transfer_ms) and s.px4_delay_ms == round(33.5 + s.transfer_ms)


def test_the_operator_is_told_why_frames_do_not_pair():
    """ATTITUDE at 10 Hz for a 20 fps camera (a flight controller that sends less than asked, or a
    configuration check-config would refuse): every frame goes unpaired, and after 2 s the operator
    reads the cause and the key to change."""
    base = ServiceConfig()
    cfg = dataclasses.replace(base, link=dataclasses.replace(base.link, attitude_rate_hz=10.0))
    run = run_daemon_in_sim(load_scenario("hover"), cfg, duration_s=6.0)
    assert run.daemon.counters.get("paired", 0) == 0 and run.daemon.counters["skipped_attitude_stale"] > 40
    told = [text for _, text in run.statustexts if "link.attitude_rate_hz" in text]
    assert told == ["mavvo: ATTITUDE 10 Hz; link.attitude_rate_hz 20"], run.statustexts


def test_a_bug_inside_the_odometry_restarts_tracking_not_the_service():
    from mavvo.service.daemon import Daemon

    class Flaky:
        """An odometry that fails once, unexpectedly, then works (it records what it was asked)."""

        def __init__(self) -> None:
            self.steps, self.restarts = 0, 0

        def step(self, frame, tracks=None):
            self.steps += 1
            if self.steps == 2:
                raise RuntimeError("index out of range somewhere deep")
            return None

        def track(self, image):
            pass

        def restart(self) -> None:
            self.restarts += 1

    source = InjectedSource()
    for k in range(4):
        source.push(np.zeros((480, 640), np.uint8), 0.05 * k)
    source.end()
    clock = FixedClock()
    cfg = _offline_config()
    cfg = dataclasses.replace(
        cfg, service=dataclasses.replace(cfg.service, heading_wait_max_s=0.0)
    )  # no yaw to wait for here
    d = Daemon(cfg, source=source, clock=clock)
    d.odometry = flaky = Flaky()
    for t_ms in range(0, 250, 10):  # attitude around every exposure, boot clock = host clock
        clock.t = t_ms * 1e-3
        d.fc.on_attitude(t_ms, 0.0, 0.0, 0.0, body_rates_rad_s=(0.0, 0.0, 0.0))
    summary = d.run()
    assert flaky.steps == 4 and flaky.restarts == 1  # every frame reached it; the failure restarted tracking
    assert summary.counters["odometry_errors"] == 1 and summary.counters.get("errors", 0) == 0


def test_the_last_state_change_reaches_the_ground_station_when_the_service_stops():
    """State changes are told at most once per ``output.statustext_min_interval_s``; those held back when
    the service stopped used to be lost, so the operator's last word could be 'initialising' while the
    vehicle had been tracking (seen in a real-time run: tracking came 55 ms after it). At shutdown what
    is pending goes out, merged. Here the interval outlasts the flight: the first change is told at
    once, and what the faults scenario's first 20 s do after it (a failure or a degraded stretch, then
    tracking again) only at the stop."""
    cfg = dataclasses.replace(ServiceConfig(), output=OutputOptions(statustext_min_interval_s=600.0))
    run = run_daemon_in_sim(load_scenario("faults"), cfg, duration_s=20.0)
    texts = [text for _, text in run.statustexts]
    assert run.daemon.state == "tracking" and len(texts) == 2, texts
    # What came after the first (a failure or a degraded stretch, then tracking), merged, at the stop.
    assert texts[-1].startswith("mavvo: ") and texts[-1].endswith(" then tracking"), texts
