"""The picamera2: camera, against an object that follows Picamera2's documented API (libcamera cannot
run here): the configuration and controls asked of it, the luma plane handed over, and the exposure
time arithmetic with a rolling shutter."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from mavvo.errors import CameraError
from mavvo.service.camera import open_source
from mavvo.service.camera_options import CameraOptions
from mavvo.service.camera_picamera2 import Picamera2Source, exposure_mid_time_s, picamera2_controls


class StillClock:
    realtime = False

    def __init__(self, t: float) -> None:
        self.t = t

    def now_s(self) -> float:
        return self.t


class FakeRequestFollowingPicamera2API:
    """A CompletedRequest as Picamera2 documents it: make_array(name), get_metadata(), release()."""

    def __init__(self, array: np.ndarray, metadata: dict) -> None:
        self.array, self.metadata, self.released = array, metadata, False

    def make_array(self, name: str) -> np.ndarray:
        assert name == "main"
        return self.array

    def get_metadata(self) -> dict:
        return dict(self.metadata)

    def release(self) -> None:
        self.released = True


class FakePicamera2FollowingDocumentedAPI:
    """Picamera2(camera_num) with create_video_configuration, configure, start, capture_request, stop, close."""

    instances: list["FakePicamera2FollowingDocumentedAPI"] = []

    def __init__(self, camera_num: int = 0) -> None:
        if camera_num > 0:
            raise IndexError("list index out of range")  # what Picamera2 raises for a camera it does not have
        self.camera_num = camera_num
        self.config = None
        self.started = self.closed = False
        self.requests: list[FakeRequestFollowingPicamera2API] = []
        self.sensor_ns = 1_000_000_000_000
        FakePicamera2FollowingDocumentedAPI.instances.append(self)

    def create_video_configuration(self, main: dict, controls: dict, buffer_count: int) -> dict:
        return {"main": main, "controls": controls, "buffer_count": buffer_count}

    def configure(self, config: dict) -> None:
        self.config = config

    def start(self) -> None:
        self.started = True

    def capture_request(self) -> FakeRequestFollowingPicamera2API:
        w, h = self.config["main"]["size"]
        yuv = np.zeros((h * 3 // 2, w), np.uint8)
        yuv[:h] = 100  # luma
        yuv[h:] = 200  # chroma planes below it, as YUV420 arrives
        self.sensor_ns += 20_000_000
        req = FakeRequestFollowingPicamera2API(
            yuv, {"SensorTimestamp": self.sensor_ns, "ExposureTime": 4000, "AnalogueGain": 2.0}
        )
        self.requests.append(req)
        return req

    # Two of an IMX219's sensor modes, as Picamera2 lists them.
    sensor_modes = [
        {"format": "SRGGB10_CSI2P", "unpacked": "SRGGB10", "bit_depth": 10, "size": (640, 480), "fps": 206.65},
        {"format": "SRGGB10_CSI2P", "unpacked": "SRGGB10", "bit_depth": 10, "size": (1640, 1232), "fps": 41.85},
    ]

    def stop(self) -> None:
        self.started = False

    def close(self) -> None:
        self.closed = True


def test_the_middle_rows_mid_exposure_from_the_sensor_timestamp() -> None:
    # End of the first row's exposure at 10 s; 4 ms exposure; 20 ms readout top to bottom:
    # the middle row's exposure is centred 2 ms before that plus 10 ms of readout.
    assert exposure_mid_time_s(10_000_000_000, 4000.0, 20.0) == pytest.approx(10.0 - 0.002 + 0.010, abs=1e-12)
    assert exposure_mid_time_s(10_000_000_000, 4000.0, 0.0) == pytest.approx(9.998, abs=1e-12)  # global shutter


def test_frames_carry_the_luma_plane_and_the_mid_exposure_stamp() -> None:
    opts = CameraOptions(
        source="picamera2:0", width_px=320, height_px=240, rate_hz=50.0, readout_ms=12.0, exposure_us=3000, gain=1.5
    )
    clock = StillClock(1000.05)
    src = Picamera2Source("0", opts, clock, picamera2_cls=FakePicamera2FollowingDocumentedAPI)
    cam = FakePicamera2FollowingDocumentedAPI.instances[-1]
    assert cam.started and cam.config["main"] == {"size": (320, 240), "format": "YUV420"}
    assert cam.config["controls"] == {
        "FrameDurationLimits": (20000, 20000),
        "AeEnable": False,
        "ExposureTime": 3000,
        "AnalogueGain": 1.5,
    }
    f = src.read(1.0)
    assert f is not None and f.image.shape == (240, 320) and np.all(f.image == 100) and f.seq == 0
    assert (f.exposure_us, f.gain) == (4000.0, 2.0)  # the request's metadata, for mavvo camera
    assert f.t_exposure_s == pytest.approx(1000.02 - 0.002 + 0.006, abs=1e-9)
    assert cam.requests[-1].released  # every request goes back to the camera
    src.close()
    assert cam.closed and not cam.started


def test_an_implausible_sensor_stamp_falls_back_to_the_grab_time() -> None:
    opts = CameraOptions(source="picamera2:0", latency_ms=25.0)
    clock = StillClock(5000.0)  # a sensor clock 4000 s away from the host's
    src = Picamera2Source("0", opts, clock, picamera2_cls=FakePicamera2FollowingDocumentedAPI)
    f = src.read(1.0)
    assert f is not None and f.t_exposure_s == pytest.approx(5000.0 - 0.025)


def test_a_missing_camera_or_library_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(CameraError, match="cannot open libcamera camera 3"):
        Picamera2Source("3", CameraOptions(), StillClock(0.0), picamera2_cls=FakePicamera2FollowingDocumentedAPI)
    with pytest.raises(CameraError, match="expected picamera2:INDEX with a camera number, got 'front'"):
        Picamera2Source("front", CameraOptions(), StillClock(0.0), picamera2_cls=FakePicamera2FollowingDocumentedAPI)
    monkeypatch.setitem(sys.modules, "picamera2", None)  # as on a machine without it: the import fails
    with pytest.raises(
        CameraError, match=r"picamera2 needs python3-libcamera: install it with apt .* --system-site-packages"
    ):
        open_source(CameraOptions(source="picamera2:0"), StillClock(0.0))


def test_auto_exposure_asks_only_for_the_frame_rate() -> None:
    assert picamera2_controls(CameraOptions(rate_hz=30.0)) == {"FrameDurationLimits": (33333, 33333)}


def test_the_listing_names_each_sensor_mode_and_closes_the_camera() -> None:
    from mavvo.service.camera_probe import _libcamera_modes

    assert _libcamera_modes(FakePicamera2FollowingDocumentedAPI, 0) == (
        "640x480 SRGGB10_CSI2P 10-bit up to 206.7 fps",
        "1640x1232 SRGGB10_CSI2P 10-bit up to 41.9 fps",
    )
    assert FakePicamera2FollowingDocumentedAPI.instances[-1].closed
    assert _libcamera_modes(FakePicamera2FollowingDocumentedAPI, 1) == ("cannot open: list index out of range",)
