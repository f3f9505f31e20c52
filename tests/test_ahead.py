"""Tracking one frame ahead on a helper thread: the same tracks and estimates as tracking in turn."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading

import cv2
import numpy as np
import pytest

from mavvo.geometry.camera_model import CameraModel
from mavvo.odometry.ahead import TrackAhead
from mavvo.odometry.frontend import Frontend, Tracks
from mavvo.service.camera import InjectedSource
from mavvo.service.settings import ServiceConfig
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.paired_frames import PairedSequence
from mavvo.sim.scenarios.service_run import config_for
from mavvo.sim.world.clock import LockstepClock

W, H = 320, 240


def _images(n: int) -> list[np.ndarray]:
    """n (H,W) uint8 views of one smoothed random texture, sliding by a pixel and a half a frame."""
    rng = np.random.default_rng(7)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (2 * H, 2 * W), dtype=np.uint8), (5, 5), 1.5)
    out = []
    for k in range(n):
        M = np.float32([[1, 0, -1.5 * k - 20], [0, 1, -0.7 * k - 20]])
        out.append(cv2.warpAffine(texture, M, (W, H), flags=cv2.INTER_LINEAR))
    return out


def _frontend() -> Frontend:
    return Frontend(CameraModel(W, H, 300.0, 300.0, W / 2, H / 2))


def _same(a: Tracks, b: Tracks) -> bool:
    return (
        a.tracked == b.tracked
        and np.array_equal(a.ids, b.ids)
        and np.array_equal(a.uv_px, b.uv_px)
        and np.array_equal(a.f_cam, b.f_cam)
    )


def test_tracks_made_ahead_on_the_helper_thread_are_those_made_in_turn():
    images = _images(12)
    plain = _frontend()
    expected = [plain.process(im) for im in images]
    assert expected[-1].tracked > 50  # the sequence is trackable, so equal tracks say something

    frontend = _frontend()
    threads: list[str] = []

    def track(image: np.ndarray) -> Tracks:
        threads.append(threading.current_thread().name)
        return frontend.process(image)

    ahead = TrackAhead(track)
    got = []
    try:
        for k, im in enumerate(images):
            got.append(ahead.tracks(im))
            if k + 1 < len(images):
                assert ahead.start(images[k + 1])
                assert not ahead.start(images[k + 1])  # one image ahead at most
    finally:
        ahead.close()
    assert all(_same(a, b) for a, b in zip(got, expected))
    assert ahead.ahead == len(images) - 1
    assert threads[0] == threading.current_thread().name
    assert all(name.startswith("mavvo-track") for name in threads[1:])


def test_without_the_helper_thread_every_image_is_tracked_by_the_caller():
    images = _images(4)
    frontend = _frontend()
    ahead = TrackAhead(frontend.process, thread=False)
    assert not ahead.start(images[0])
    got = [ahead.tracks(im) for im in images]
    ahead.close()
    plain = _frontend()
    assert all(_same(a, plain.process(im)) for a, im in zip(got, images))
    assert ahead.ahead == 0


def test_an_image_started_but_not_asked_for_is_tracked_before_the_next():
    """The tracker sees the started image first (an extra frame in its sequence), then the one asked for."""
    images = _images(4)
    frontend = _frontend()
    ahead = TrackAhead(frontend.process)
    try:
        ahead.tracks(images[0])
        assert ahead.start(images[1])
        got = ahead.tracks(images[2])
    finally:
        ahead.close()
    plain = _frontend()
    for im in images[:2]:
        plain.process(im)
    assert _same(got, plain.process(images[2]))
    assert ahead.ahead == 0


def test_a_malformed_image_tracked_ahead_raises_when_its_tracks_are_asked_for():
    images = _images(2)
    ahead = TrackAhead(_frontend().process)
    try:
        ahead.tracks(images[0])
        bad = np.zeros((H, W), np.float32)
        assert ahead.start(bad)
        with pytest.raises(ValueError, match="uint8"):
            ahead.tracks(bad)
        ahead.tracks(images[1])  # and the tracker goes on
    finally:
        ahead.close()


def test_a_helper_stuck_inside_the_tracker_does_not_keep_the_process_from_exiting():
    """systemd restarts a service that exits; one that hangs on its way out it has to kill. A
    ThreadPoolExecutor's thread (joined at exit) made this process hang; the helper is a daemon thread."""
    code = (
        "import threading, numpy as np\n"
        "from mavvo.odometry.ahead import TrackAhead\n"
        "ahead = TrackAhead(lambda image: threading.Event().wait())\n"
        "assert ahead.start(np.zeros((8, 8), np.uint8))\n"
        "print('started', flush=True)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "started"


def _run_queued(track_ahead: bool, paired) -> tuple[list, dict[str, int]]:
    """The daemon on frames that are all queued before it starts (so each frame's successor waits in
    the queue), the flight controller's attitude fed directly; (estimates, counters)."""
    from mavvo.service.daemon import Daemon

    scenario = load_scenario("hover")
    base = config_for(scenario, ServiceConfig(), "udpout:127.0.0.1:9")
    cfg = dataclasses.replace(
        base, service=dataclasses.replace(base.service, heading_wait_max_s=0.0, track_ahead=track_ahead)
    )
    source = InjectedSource()
    for pf in paired:
        source.push(pf.image, pf.t_exposure_s, pf.seq)
    source.end()
    clock = LockstepClock()
    got: list = []
    d = Daemon(cfg, source=source, clock=clock, on_estimate=got.append)
    times = np.array([pf.t_exposure_s for pf in paired])
    for t_ms in range(0, int(1000 * times[-1]) + 50, 10):  # boot clock = host clock; each frame's roll/pitch around it
        clock.advance_to(t_ms * 1e-3)
        pf = paired[int(np.argmin(np.abs(times - clock.now_s())))]
        d.fc.on_attitude(t_ms, pf.roll_rad, pf.pitch_rad, pf.yaw_rad, body_rates_rad_s=(0.0, 0.0, 0.0))
    summary = d.run()
    return got, summary.counters


def test_the_service_tracking_ahead_sends_the_estimates_it_sends_without_it():
    seq = PairedSequence(load_scenario("hover"), duration_s=2.0)
    paired = list(seq)
    with_helper, counters_on = _run_queued(True, paired)
    alone, counters_off = _run_queued(False, paired)
    assert counters_on["tracked_ahead"] >= len(paired) // 2  # the helper did most of the tracking
    assert counters_off.get("tracked_ahead", 0) == 0
    assert counters_on["paired"] == counters_off["paired"] == len(paired)
    assert len(alone) >= len(paired) - 2
    assert len(with_helper) == len(alone)
    for a, b in zip(with_helper, alone):
        assert a.t_exposure_s == b.t_exposure_s and np.array_equal(a.p_ned_m, b.p_ned_m) and a.quality == b.quality
