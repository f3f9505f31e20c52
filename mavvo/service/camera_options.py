"""The ``camera:`` settings: intrinsics, where frames come from, how they are stamped, and the controls
asked of the camera (exposure, gain, frame rate, image size, rolling-shutter readout)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from mavvo.geometry.camera_model import CameraIntrinsics
from mavvo.options import bounded

__all__ = ["CameraOptions"]


@dataclass(frozen=True)
class CameraOptions(CameraIntrinsics):
    """The camera: its intrinsics (:class:`CameraIntrinsics`, whose ``width_px`` x ``height_px`` is also
    the image size asked of the sensor), where frames come from, how they are stamped, its controls."""

    source: str = bounded(
        "/dev/video0",
        "/dev/videoN (V4L2), gst:PIPELINE (GStreamer), picamera2:INDEX (libcamera), a video file, an image folder with timestamps.txt, or sim:SCENARIO",
    )
    rate_hz: float = bounded(20.0, "frame rate requested from a device", gt=0, le=240)
    timestamps: Literal["auto", "driver", "grab"] = bounded(
        "auto", "exposure time from the driver's timestamp (auto: when plausible) or the grab time minus latency_ms"
    )
    latency_ms: float = bounded(
        30.0, "grab time minus this is the exposure time, when the driver gives none", ge=0, le=1000
    )
    exposure_us: int = bounded(
        0,
        "fixed exposure time in microseconds (short: less motion blur); 0: the camera's auto-exposure",
        ge=0,
        le=1_000_000,
    )
    gain: float = bounded(0.0, "fixed analogue gain; 0: automatic", ge=0, le=64)
    readout_ms: float = bounded(
        0.0,
        "rolling shutter: top-to-bottom readout time; the odometry moves each track to the frame's time by it, and picamera2 stamps the middle row with it; 0 for a global shutter",
        ge=0,
        le=100,
    )
    queue_size: int = bounded(2, "frames waiting for the worker; the oldest is dropped when full", ge=1, le=64)
    reconnect_max_s: float = bounded(5.0, "longest back-off between attempts to reopen a lost camera", gt=0, le=600)
    lost_after_s: float = bounded(
        30.0,
        "a camera that fails and cannot be reopened for this long ends the service non-zero, for systemd to restart it",
        gt=0,
        le=3600,
    )
