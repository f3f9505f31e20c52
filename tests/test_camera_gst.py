"""The gst: camera with real GStreamer pipelines: frames arrive stamped on the host's monotonic clock,
the end of a file is CameraEnded, a failing pipeline a CameraError naming it, a camera that comes back
is reopened, and ``mavvo run`` flies on one against the simulated flight controller.

GStreamer comes from the distribution (``.ci/run`` installs it; ``make setup`` links its PyGObject into
the venv); where it is missing the tests say so and skip."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import free_port, wait_for

from mavvo.errors import CameraEnded, CameraError
from mavvo.service.camera import open_source
from mavvo.service.camera_gst import gst_available, sink_description
from mavvo.service.camera_options import CameraOptions
from mavvo.service.timing import MonotonicClock

pytestmark = pytest.mark.skipif(
    not gst_available(),
    reason="GStreamer's Python bindings are not importable: sudo apt-get install python3-gi python3-gst-1.0 "
    "gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base gstreamer1.0-plugins-good; then .venv/bin/python tools/link_system_gi.py",
)

CAPS = "video/x-raw,width=160,height=120,framerate=30/1"
LIVE = f"videotestsrc is-live=true pattern=ball ! {CAPS}"


def live(frames: int) -> str:
    return f"videotestsrc is-live=true pattern=ball num-buffers={frames} ! {CAPS}"


def _read_all(src, limit: int = 500, timeout_s: float = 2.0) -> tuple[list, str | None]:
    frames, ended = [], None
    while len(frames) < limit:
        try:
            f = src.read(timeout_s)
        except CameraEnded as e:
            ended = str(e)
            break
        assert f is not None, "no frame within 2 s from a running pipeline"
        frames.append(f)
    return frames, ended


def test_a_live_pipeline_gives_grey_frames_stamped_on_the_monotonic_clock() -> None:
    t_before = time.monotonic()
    # Room for every frame (no drops however slowly this test reads), and a backlog made on purpose:
    # after the first frame the reader pauses for 9 frame periods, so grab times would bunch up while
    # the capture times must not.
    src = open_source(CameraOptions(source=f"gst:{live(15)}", rate_hz=30.0, queue_size=64), MonotonicClock())
    try:
        first = src.read(2.0)
        time.sleep(0.3)
        frames, ended = _read_all(src)
    finally:
        src.close()
    t_after = time.monotonic()
    frames = [first, *frames]
    assert len(frames) == 15 and ended is not None and "end of stream after 15 frames" in ended
    assert all(f.image.shape == (120, 160) and f.image.dtype == np.uint8 for f in frames)
    assert [f.seq for f in frames] == list(range(15))
    stamps = np.array([f.t_exposure_s for f in frames])
    # On the host's monotonic clock: inside the run, never in the future of the moment it was read.
    assert t_before <= stamps[0] and stamps[-1] <= t_after
    # From the buffers' PTS, not the grab time: 1/30 s apart as produced, also across the backlog. Each
    # stamp is off by the gap between two back-to-back clock reads; 5 ms allows for a preempted one.
    np.testing.assert_allclose(np.diff(stamps), 1 / 30, atol=5e-3)


def test_a_grab_stamp_is_the_grab_time_minus_the_latency() -> None:
    clock = MonotonicClock()
    src = open_source(CameraOptions(source=f"gst:{live(5)}", timestamps="grab", latency_ms=40.0), clock)
    try:
        assert src.read(2.0) is not None  # the pipeline runs
        t_before = clock.now_s()
        f = src.read(2.0)
        t_after = clock.now_s()
    finally:
        src.close()
    assert f is not None and t_before - 0.040 <= f.t_exposure_s <= t_after - 0.040


def test_a_video_file_through_decodebin_plays_to_its_end(tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (96, 64))
    rng = np.random.default_rng(3)
    for _ in range(12):
        writer.write(cv2.cvtColor(rng.integers(0, 255, (64, 96), dtype=np.uint8), cv2.COLOR_GRAY2BGR))
    writer.release()
    src = open_source(CameraOptions(source=f"gst:filesrc location={video} ! decodebin"), MonotonicClock())
    try:
        frames, ended = _read_all(src)
    finally:
        src.close()
    assert len(frames) == 12 and ended is not None and all(f.image.shape == (64, 96) for f in frames)
    assert all(b.t_exposure_s > a.t_exposure_s for a, b in zip(frames, frames[1:]))


@pytest.mark.parametrize(
    "pipeline, message",
    [
        ("gst:nosuchelement ! appsink", "not a pipeline GStreamer can build"),
        ("gst:filesrc location=/nonexistent/clip.avi ! decodebin", "clip.avi"),
        ("gst:", "expected a GStreamer pipeline after 'gst:'"),
        ("gst:videotestsrc ! appsink name=a videotestsrc ! appsink name=b", "expected one appsink"),
    ],
)
def test_a_pipeline_that_cannot_run_is_a_camera_error_naming_it(pipeline: str, message: str) -> None:
    with pytest.raises(CameraError, match=re.escape(message)):
        open_source(CameraOptions(source=pipeline), MonotonicClock())


def test_controls_a_pipeline_cannot_take_are_refused_with_the_key_named() -> None:
    with pytest.raises(CameraError, match=r"camera\.exposure_us: 2000 is not supported .* in the pipeline description"):
        open_source(CameraOptions(source=f"gst:{LIVE}", exposure_us=2000), MonotonicClock())


def test_a_camera_that_fails_is_reopened_when_it_comes_back(tmp_path: Path) -> None:
    """The first open fails (no file yet); the reconnecting wrapper tries again with back-off and
    reads once the camera is there."""
    video = tmp_path / "late.avi"
    options = CameraOptions(source=f"gst:filesrc location={video} ! decodebin", reconnect_max_s=0.2)
    with pytest.raises(CameraError):  # at start, a missing camera is the operator's to know at once
        open_source(options, MonotonicClock())
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (64, 48))
    for i in range(4):
        writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
    writer.release()
    src = open_source(options, MonotonicClock())
    video.unlink()  # the next open fails: the source is away until the file is back
    try:
        frames, ended = _read_all(src)
    finally:
        src.close()
    assert len(frames) == 4 and ended is not None


def test_the_appended_sink_converts_to_grey() -> None:
    assert (
        sink_description("v4l2src device=/dev/video1")
        == "v4l2src device=/dev/video1 ! videoconvert ! video/x-raw,format=GRAY8 ! appsink name=mavvo"
    )
    assert sink_description("videotestsrc ! appsink name=mine") == "videotestsrc ! appsink name=mine"


def test_mavvo_camera_lists_and_measures_a_gstreamer_test_source() -> None:
    listed = subprocess.run([sys.executable, "-m", "mavvo", "camera"], capture_output=True, text=True, timeout=60)
    assert listed.returncode == 0 and re.search(r"gst:PIPELINE\s+gstreamer\s+GStreamer 1\.", listed.stdout), (
        listed.stdout + listed.stderr
    )
    out = subprocess.run(
        [sys.executable, "-m", "mavvo", "camera", "--source", f"gst:{LIVE}", "--seconds", "2", "--json"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    m = json.loads(out.stdout)
    assert m["width_px"] == 160 and m["height_px"] == 120 and m["age_median_ms"] > 0
    # The source makes 30 frames a second; a loaded machine may take fewer (the appsink keeps the newest
    # two), and what it misses is counted as lost: delivered and lost together cover most of the 2 s.
    assert m["frames"] >= 10 and m["frames"] + m["dropped"] >= 40 and m["rate_hz"] <= 31.0
    assert any("auto-exposure" in a for a in m["advice"])


def test_mavvo_run_flies_on_a_gstreamer_camera_against_the_simulated_flight_controller(tmp_path: Path) -> None:
    """Runs until the service's own health line reports paired frames (an event, not a time window),
    then stops it as systemd would and reads its final line."""
    port = free_port()
    cfg = tmp_path / "run.yaml"
    cfg.write_text(
        "camera: {source: 'gst:videotestsrc is-live=true pattern=ball ! video/x-raw,width=640,height=480,framerate=20/1', rate_hz: 20.0}\n"
        f"link: {{url: 'udpout:127.0.0.1:{port}'}}\nservice: {{state_file: ''}}\n"
    )
    fc_cmd = ["--fc-only", "--scenario", "hover", "--mavlink", f"udpin:127.0.0.1:{port}", "--out", str(tmp_path / "fc")]
    fc = subprocess.Popen(
        [sys.executable, "-m", "mavvo", "sim", *fc_cmd], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    run = None
    lines: list[str] = []
    try:
        run = subprocess.Popen(
            [sys.executable, "-m", "mavvo", "run", "--config", str(cfg)], stderr=subprocess.PIPE, text=True
        )
        reader = threading.Thread(target=lambda: lines.extend(run.stderr), daemon=True)
        reader.start()

        def paired_in_health() -> bool:
            return any(
                int(m.group(1)) >= 20
                for m in map(re.compile(r"health: state \w+;.* paired (\d+)").search, list(lines))
                if m
            )

        assert wait_for(paired_in_health, timeout_s=120.0), "".join(lines)
        run.send_signal(signal.SIGTERM)
        assert run.wait(timeout=60) == 0, "".join(lines)
        reader.join(timeout=10)
    finally:
        for p in (run, fc):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    p.kill()
    log = "".join(lines)
    final = re.search(r"final: state \w+.*?frames (\d+), paired (\d+)", log)
    assert final is not None, log
    # Frames came from the pipeline and were paired with the flight controller's attitude at their stamps.
    assert int(final.group(1)) >= int(final.group(2)) >= 20, final.group(0)
    assert "camera gst:videotestsrc" in log and "Traceback" not in log
