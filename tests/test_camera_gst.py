"""The gst: camera with real GStreamer pipelines: frames arrive stamped on the host's monotonic clock,
the end of a file is CameraEnded, a failing pipeline a CameraError naming it, a camera that comes back
is reopened, and ``mavvo run`` flies on one against the simulated flight controller.

GStreamer comes from the distribution (``.ci/run`` installs it; ``make setup`` links its PyGObject into
the venv); where it is missing the tests say so and skip."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from mavvo.errors import CameraEnded, CameraError
from mavvo.service.camera import open_source
from mavvo.service.camera_gst import gst_available, sink_description
from mavvo.service.camera_options import CameraOptions
from mavvo.service.timing import MonotonicClock

pytestmark = pytest.mark.skipif(
    not gst_available(),
    reason="GStreamer's Python bindings are not importable: sudo apt-get install python3-gi python3-gst-1.0 "
    "gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base gstreamer1.0-plugins-good; then make setup",
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
    src = open_source(CameraOptions(source=f"gst:{live(15)}", rate_hz=30.0), MonotonicClock())
    try:
        frames, ended = _read_all(src)
    finally:
        src.close()
    t_after = time.monotonic()
    assert len(frames) == 15 and ended is not None and "end of stream after 15 frames" in ended
    assert all(f.image.shape == (120, 160) and f.image.dtype == np.uint8 for f in frames)
    assert [f.seq for f in frames] == list(range(15))
    stamps = np.array([f.t_exposure_s for f in frames])
    # On the host's monotonic clock: inside the run, never in the future of the moment it was read.
    assert t_before <= stamps[0] and stamps[-1] <= t_after
    # From the buffers' PTS, not the grab time: a live source's frames stand 1/30 s apart, as produced.
    np.testing.assert_allclose(np.diff(stamps), 1 / 30, atol=2e-3)


def test_a_grab_stamp_is_the_grab_time_minus_the_latency() -> None:
    clock = MonotonicClock()
    src = open_source(CameraOptions(source=f"gst:{live(5)}", timestamps="grab", latency_ms=40.0), clock)
    try:
        f = src.read(2.0)
        t_after = clock.now_s()
    finally:
        src.close()
    assert f is not None and 0.0 <= t_after - (f.t_exposure_s + 0.040) < 0.05


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
    import json

    m = json.loads(out.stdout)
    assert m["frames"] >= 30 and m["width_px"] == 160 and m["height_px"] == 120 and m["dropped"] == 0
    assert 25.0 < m["rate_hz"] < 35.0 and m["age_median_ms"] > 0
    assert any("auto-exposure" in a for a in m["advice"])


def test_mavvo_run_flies_on_a_gstreamer_camera_against_the_simulated_flight_controller(tmp_path: Path) -> None:
    from conftest import free_port

    port = free_port()
    cfg = tmp_path / "run.yaml"
    cfg.write_text(
        "camera: {source: 'gst:videotestsrc is-live=true pattern=ball ! video/x-raw,width=640,height=480,framerate=20/1', rate_hz: 20.0}\n"
        f"link: {{url: 'udpout:127.0.0.1:{port}'}}\nservice: {{state_file: ''}}\n"
    )
    fc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mavvo",
            "sim",
            "--fc-only",
            "--scenario",
            "hover",
            "--mavlink",
            f"udpin:127.0.0.1:{port}",
            "--out",
            str(tmp_path / "fc"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        time.sleep(1.0)
        run = subprocess.Popen(
            [sys.executable, "-m", "mavvo", "run", "--config", str(cfg)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            time.sleep(8.0)
        finally:
            run.send_signal(signal.SIGTERM)
            _, run_err = run.communicate(timeout=60)
        fc.send_signal(signal.SIGTERM)
        fc.communicate(timeout=120)
    finally:
        if fc.poll() is None:
            fc.kill()
    assert run.returncode == 0, run_err
    final = re.search(r"final: state \w+.*?frames (\d+), paired (\d+)", run_err)
    assert final is not None, run_err
    # Frames came from the pipeline and were paired with the flight controller's attitude at their stamps.
    assert int(final.group(1)) > 40 and int(final.group(2)) > 20, final.group(0)
    assert "camera gst:videotestsrc" in run_err and "Traceback" not in run_err
