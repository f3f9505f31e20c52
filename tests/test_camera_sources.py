"""Frame sources: the newest-frame queue, a video file, and the ``sim:`` scheme the CLI registers."""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest

from mavvo.errors import CameraEnded, CameraError
from mavvo.service.camera import CameraOptions, FrameQueue, VideoFileSource, open_source
from mavvo.service.timing import MonotonicClock
from mavvo.types import Frame


class StillClock:
    realtime = False

    def now_s(self) -> float:
        return 100.0


def test_queue_keeps_the_newest_frames_and_counts_drops():
    q = FrameQueue(2, drop_oldest=True)
    stop = threading.Event()
    for i in range(5):
        q.put(Frame(np.zeros((2, 2), np.uint8), i * 0.05, i), stop)
    assert q.dropped == 3 and [q.get(0.01).seq for _ in range(2)] == [3, 4] and q.get(0.01) is None


def test_lockstep_queue_waits_instead_of_dropping():
    q = FrameQueue(1, drop_oldest=False)
    stop = threading.Event()
    q.put(Frame(np.zeros((2, 2), np.uint8), 0.0, 0), stop)
    t = threading.Thread(target=q.put, args=(Frame(np.zeros((2, 2), np.uint8), 0.05, 1), stop))
    t.start()
    t.join(0.2)
    assert t.is_alive(), "put waits while the queue is full"
    assert q.get(1.0).seq == 0
    t.join(5)
    assert q.get(1.0).seq == 1 and q.dropped == 0


def test_video_file_frames_are_grey_and_stamped_from_the_container(tmp_path):
    path = tmp_path / "flight.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (64, 48))
    rng = np.random.default_rng(3)
    for _ in range(6):
        writer.write(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    writer.release()
    src = open_source(CameraOptions(source=str(path), width_px=64, height_px=48, cx_px=31.5, cy_px=23.5), StillClock())
    assert isinstance(src, VideoFileSource)
    frames = [src.read(1.0) for _ in range(6)]
    assert all(f.image.shape == (48, 64) and f.image.dtype == np.uint8 for f in frames)
    assert np.allclose(np.diff([f.t_exposure_s for f in frames]), 0.05, atol=1e-3)
    assert frames[0].t_exposure_s == 100.0  # the first frame at the moment the file was opened
    with pytest.raises(CameraEnded):
        src.read(1.0)


def test_unknown_source_names_itself():
    with pytest.raises(
        CameraError,
        match=r"camera.source 'nowhere/video.mp4': expected /dev/videoN, a video file, an image folder or gst:, picamera2:, sim:ARGUMENT",
    ):
        open_source(CameraOptions(source="nowhere/video.mp4"), StillClock(), {"sim": lambda *a: None})


def test_sim_scheme_renders_the_scenario_on_the_host_clock():
    from mavvo.commands.run import sim_camera

    clock = MonotonicClock()
    t_open_s = clock.now_s()
    src = open_source(CameraOptions(source="sim:hover"), clock, {"sim": sim_camera})
    try:
        f = None
        while f is None:
            f = src.read(0.5)
        assert f.image.shape == (480, 640) and f.image.std() > 10  # a textured ground
        # On the host's monotonic clock: exposed after the camera opened, before it was read (a bound by
        # two clock reads, not a tolerance a loaded machine could overrun).
        assert t_open_s <= f.t_exposure_s <= clock.now_s()
    finally:
        src.close()


def test_a_camera_that_is_not_there_is_named_in_mavvos_words_only(tmp_path, capfd):
    """Before: OpenCV's own '[ WARN ] ... can't be used to capture by name' line stood beside mavvo's error."""
    from mavvo.service.camera import V4L2Source

    with pytest.raises(CameraError, match=r"video7: no such device \(is the camera plugged in\?"):
        V4L2Source(str(tmp_path / "video7"), CameraOptions(), StillClock())
    not_a_camera = tmp_path / "video8"
    not_a_camera.write_bytes(b"")
    with pytest.raises(CameraError, match=r"video8: cannot open the V4L2 device \(busy, no permission"):
        V4L2Source(str(not_a_camera), CameraOptions(), StillClock())
    assert "WARN" not in capfd.readouterr().err
