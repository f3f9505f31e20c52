"""A libcamera camera through Picamera2 as a frame source (``camera.source: picamera2:INDEX``).

Raspberry Pi CSI cameras (Camera Module 2/3, the Global Shutter Camera, OV9281 boards) run on the
libcamera stack, which OpenCV's V4L2 backend cannot open. Picamera2 can; it needs the system's
``python3-libcamera``, so the venv is made with ``--system-site-packages`` (``make install
CAMERA=picamera2``).

Time: a request's metadata has ``SensorTimestamp`` (nanoseconds, CLOCK_MONOTONIC as ``time.monotonic``,
the end of the first row's exposure, when its readout starts) and ``ExposureTime`` (microseconds). The
middle of the exposure of the image's middle row, which is what a frame's ``t_exposure_s`` means, is

    t = SensorTimestamp - ExposureTime / 2 + readout / 2

with ``readout`` the rolling shutter's top-to-bottom readout time (``camera.readout_ms``; 0 for a global
shutter). A stamp that is not plausible against the grab time (more than a second apart) falls back to
the grab time minus ``camera.latency_ms`` under ``camera.timestamps: auto``.

Only Picamera2's documented API is used (``Picamera2(index)``, ``create_video_configuration``,
``configure``, ``set_controls``, ``start``, ``capture_request``, ``request.make_array``,
``request.get_metadata``, ``request.release``, ``stop``, ``close``, ``global_camera_info``), so the tests
run it against an object that follows that API where libcamera cannot run.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from mavvo.errors import CameraError
from mavvo.service.camera_options import CameraOptions
from mavvo.service.timing import Clock
from mavvo.types import Frame

__all__ = ["Picamera2Source", "exposure_mid_time_s", "import_picamera2", "picamera2_controls", "sensor_modes"]

log = logging.getLogger(__name__)

INSTALL_HINT = (
    "picamera2 needs python3-libcamera: install it with apt (python3-picamera2 brings both), and make the venv "
    "with --system-site-packages (make install CAMERA=picamera2 does)"
)
_PLAUSIBLE_S = 1.0


def import_picamera2() -> Any:
    """The ``Picamera2`` class; CameraError saying what to install when it cannot be imported."""
    try:
        from picamera2 import Picamera2
    except ImportError as e:
        raise CameraError(f"{INSTALL_HINT} ({e})") from None
    return Picamera2


def exposure_mid_time_s(sensor_timestamp_ns: int, exposure_time_us: float, readout_ms: float) -> float:
    """The middle of the middle row's exposure, seconds on the sensor timestamp's clock (see the module)."""
    return sensor_timestamp_ns * 1e-9 - exposure_time_us * 0.5e-6 + readout_ms * 0.5e-3


def _number(value: Any) -> float | None:
    """A metadata value as a float, None where it is missing or not a number."""
    try:
        return float(value) if value is not None else None
    except (TypeError, ValueError):
        return None


def sensor_modes(cam: Any) -> list[str]:
    """An opened Picamera2's ``sensor_modes`` (dicts with size, fps, bit_depth, format), one line each:
    what ``camera.width_px``/``height_px``/``rate_hz`` can ask for without the ISP scaling a crop."""
    out = []
    for mode in cam.sensor_modes:
        w, h = mode.get("size", ("?", "?"))
        fps = _number(mode.get("fps"))
        rate = f" up to {fps:.1f} fps" if fps is not None else ""
        out.append(f"{w}x{h} {mode.get('format', '?')} {mode.get('bit_depth', '?')}-bit{rate}")
    return out


def picamera2_controls(options: CameraOptions) -> dict[str, Any]:
    """libcamera controls for ``options``: the frame rate, and a fixed exposure and gain where set."""
    period_us = int(round(1e6 / options.rate_hz))
    controls: dict[str, Any] = {"FrameDurationLimits": (period_us, period_us)}
    if options.exposure_us > 0 or options.gain > 0:
        controls["AeEnable"] = False
    if options.exposure_us > 0:
        controls["ExposureTime"] = int(options.exposure_us)
    if options.gain > 0:
        controls["AnalogueGain"] = float(options.gain)
    return controls


class Picamera2Source:
    """``picamera2:INDEX``: grey frames (the luma plane of YUV420) stamped at mid-exposure."""

    def __init__(self, index: str, options: CameraOptions, clock: Clock, picamera2_cls: Any = None) -> None:
        self.options, self.clock = options, clock
        self.name = f"picamera2:{index}"
        try:
            num = int(index or "0")
        except ValueError:
            raise CameraError(
                f"camera.source {self.name}: expected picamera2:INDEX with a camera number, got {index!r}"
            ) from None
        cls = picamera2_cls or import_picamera2()
        try:
            self._cam = cls(num)
        except (IndexError, RuntimeError, OSError) as e:
            raise CameraError(f"camera.source {self.name}: cannot open libcamera camera {num}: {e}") from None
        try:
            config = self._cam.create_video_configuration(
                main={"size": (options.width_px, options.height_px), "format": "YUV420"},
                controls=picamera2_controls(options),
                buffer_count=max(2, options.queue_size + 1),
            )
            self._cam.configure(config)
            self._cam.start()
        except (RuntimeError, ValueError, OSError) as e:
            self._cam.close()
            raise CameraError(
                f"camera.source {self.name}: the camera refused {options.width_px}x{options.height_px} at {options.rate_hz} Hz: {e}"
            ) from None
        self._seq = 0
        self._closed = False

    def read(self, timeout_s: float) -> Frame | None:
        """The next frame. Picamera2's capture blocks until the camera delivers one (a frame period);
        ``timeout_s`` is not used. CameraError when the camera fails."""
        if self._closed:
            raise CameraError(f"camera.source {self.name}: read after close")
        try:
            request = self._cam.capture_request()
        except (RuntimeError, OSError) as e:  # a timeout is an OSError
            raise CameraError(f"camera.source {self.name}: no frame: {e}") from None
        t_grab = self.clock.now_s()
        try:
            yuv = np.asarray(request.make_array("main"))
            metadata = request.get_metadata()
        finally:
            request.release()
        image = np.ascontiguousarray(yuv[: self.options.height_px, : self.options.width_px])
        frame = Frame(
            image,
            self._exposure_time_s(metadata, t_grab),
            self._seq,
            exposure_us=_number(metadata.get("ExposureTime")),
            gain=_number(metadata.get("AnalogueGain")),
        )
        self._seq += 1
        return frame

    def _exposure_time_s(self, metadata: dict[str, Any], t_grab_s: float) -> float:
        fallback = t_grab_s - self.options.latency_ms * 1e-3
        stamp, exposure = metadata.get("SensorTimestamp"), metadata.get("ExposureTime")
        if self.options.timestamps == "grab" or stamp is None or exposure is None:
            return fallback
        t = exposure_mid_time_s(int(stamp), float(exposure), self.options.readout_ms)
        if self.options.timestamps == "auto" and abs(t - t_grab_s) >= _PLAUSIBLE_S:
            return fallback
        return t

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._cam.stop()
            finally:
                self._cam.close()
