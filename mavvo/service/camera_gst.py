"""A GStreamer pipeline as a frame source (``camera.source: gst:PIPELINE``).

This is how Jetson CSI cameras (``nvarguscamerasrc``), ``libcamerasrc`` on a Raspberry Pi, RTSP and UDP
video from another board and most USB cameras (``v4l2src``) reach mavvo: the pip wheels of OpenCV have
no GStreamer, so mavvo drives the pipeline itself through PyGObject (the distribution's ``python3-gi``
and ``python3-gst-1.0``).

The pipeline ends in an ``appsink``: the one named ``mavvo`` or the only one the description has; a
description without one gets ``! videoconvert ! video/x-raw,format=GRAY8 ! appsink name=mavvo``
appended. The sink keeps the newest frames only (``max-buffers`` = ``camera.queue_size``, ``drop``).

Time: a buffer's PTS plus the pipeline's base time is its capture time on the pipeline clock
(CLOCK_MONOTONIC by default, the sources' own driver stamps where they have them: ``v4l2src`` takes the
V4L2 buffer's, ``nvarguscamerasrc`` the sensor's). It is carried onto the host clock by its age on the
pipeline clock when the sample is pulled, which is exact for the monotonic clock and right for any
other. ``camera.timestamps: grab``, or a buffer with no PTS, stamps the grab time minus
``camera.latency_ms``. Errors on the pipeline's bus become :class:`CameraError` (the daemon reopens the
source), end of stream :class:`CameraEnded`.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from mavvo.errors import CameraEnded, CameraError
from mavvo.service.camera_options import CameraOptions
from mavvo.service.timing import Clock
from mavvo.types import Frame

__all__ = ["GstSource", "gst_available", "import_gst", "sink_description"]

log = logging.getLogger(__name__)

SINK_NAME = "mavvo"
_GREY_TAIL = f"videoconvert ! video/x-raw,format=GRAY8 ! appsink name={SINK_NAME}"
INSTALL_HINT = (
    "the gst: camera needs GStreamer's Python bindings: install them with apt "
    "(python3-gi python3-gst-1.0 gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base gstreamer1.0-plugins-good), "
    "and make the venv see them (make setup links them; make install CAMERA=gst makes it with --system-site-packages)"
)
# A driver stamp older than this when its sample is pulled is not believed (a stalled or buffered pipeline).
_MAX_AGE_S = 1.0
_NS = 1e-9


def import_gst() -> tuple[Any, Any, Any]:
    """The ``Gst`` module, initialised, ``GLib`` (for its error type) and ``GstVideo`` (plane layouts);
    CameraError saying what to install when they cannot be imported."""
    try:
        import gi

        gi.require_version("Gst", "1.0")
        gi.require_version("GstApp", "1.0")
        gi.require_version("GstVideo", "1.0")
        from gi.repository import GLib, Gst, GstApp, GstVideo  # noqa: F401  (GstApp registers the appsink's methods)
    except (ImportError, ValueError) as e:
        raise CameraError(f"{INSTALL_HINT} ({type(e).__name__}: {e})") from None
    if not Gst.is_initialized():
        Gst.init(None)
    return Gst, GLib, GstVideo


def gst_available() -> bool:
    """Whether the gst: camera can be used here."""
    try:
        import_gst()
    except CameraError:
        return False
    return True


def sink_description(pipeline: str) -> str:
    """The pipeline description with mavvo's grey appsink appended when it has no appsink of its own."""
    text = pipeline.strip()
    if not text:
        raise CameraError("camera.source gst:: expected a GStreamer pipeline after 'gst:', got nothing")
    return text if "appsink" in text else f"{text} ! {_GREY_TAIL}"


def _grey_from_sample(Gst: Any, GstVideo: Any, sample: Any, name: str) -> np.ndarray:
    """(H, W) uint8 from a GRAY8 sample, or the luma plane of an I420/NV12 one. The plane's offset and
    row stride come from the buffer's video meta where the element set one (hardware buffers), else
    from the caps' default layout (rows padded to 4 bytes)."""
    caps = sample.get_caps()
    info = GstVideo.VideoInfo.new_from_caps(caps)
    fmt = info.finfo.format if info is not None else None
    grey_first = (
        GstVideo.VideoFormat.GRAY8,
        GstVideo.VideoFormat.I420,
        GstVideo.VideoFormat.YV12,
        GstVideo.VideoFormat.NV12,
        GstVideo.VideoFormat.NV21,
    )
    if fmt not in grey_first:
        raise CameraError(
            f"camera.source {name}: the appsink gets {caps.to_string()}; expected video/x-raw with format GRAY8 (or I420/NV12)"
        )
    buf = sample.get_buffer()
    meta = GstVideo.buffer_get_video_meta(buf)
    offset, stride = (meta.offset[0], meta.stride[0]) if meta is not None else (info.offset[0], info.stride[0])
    width, height = info.width, info.height
    ok, mapped = buf.map(Gst.MapFlags.READ)
    if not ok:
        raise CameraError(f"camera.source {name}: cannot map a buffer")
    try:
        data = np.frombuffer(mapped.data, dtype=np.uint8)
        if data.size < offset + stride * (height - 1) + width:
            raise CameraError(f"camera.source {name}: a {width}x{height} buffer of {data.size} bytes is too short")
        return np.lib.stride_tricks.as_strided(data[offset:], (height, width), (stride, 1)).copy()
    finally:
        buf.unmap(mapped)


class GstSource:
    """``gst:PIPELINE``: grey frames from a GStreamer pipeline's appsink, stamped as the module says."""

    def __init__(self, pipeline: str, options: CameraOptions, clock: Clock) -> None:
        self.options, self.clock = options, clock
        self.name = f"gst:{pipeline}"
        Gst, GLib, self._GstVideo = import_gst()
        self._Gst = Gst
        description = sink_description(pipeline)
        try:
            self._pipeline = Gst.parse_launch(description)
        except GLib.Error as e:  # the description does not parse or names a missing element
            raise CameraError(f"camera.source {self.name}: not a pipeline GStreamer can build: {e.message}") from None
        self._sink = self._find_sink()
        self._sink.set_property("max-buffers", options.queue_size)
        self._sink.set_property("drop", True)
        self._sink.set_property("emit-signals", False)
        self._bus = self._pipeline.get_bus()
        self._seq = 0
        self._closed = False
        if self._pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
            reason = self._bus_error() or "the pipeline refused to start"
            self._pipeline.set_state(Gst.State.NULL)
            raise CameraError(f"camera.source {self.name}: {reason}")

    def _find_sink(self) -> Any:
        named = self._pipeline.get_by_name(SINK_NAME) if hasattr(self._pipeline, "get_by_name") else None
        if named is not None:
            return named
        sinks = []
        if hasattr(self._pipeline, "iterate_sinks"):
            it = self._pipeline.iterate_sinks()
            while True:
                res, elem = it.next()
                if res != self._Gst.IteratorResult.OK:
                    break
                if elem.get_factory() is not None and elem.get_factory().get_name() == "appsink":
                    sinks.append(elem)
        if len(sinks) != 1:
            raise CameraError(
                f"camera.source {self.name}: expected one appsink (or one named {SINK_NAME!r}), found {len(sinks)}"
            )
        return sinks[0]

    def _bus_error(self) -> str | None:
        """The first error posted on the bus, as one line, or None."""
        Gst = self._Gst
        while True:
            msg = self._bus.pop_filtered(Gst.MessageType.ERROR | Gst.MessageType.WARNING)
            if msg is None:
                return None
            if msg.type == Gst.MessageType.ERROR:
                err, _debug = msg.parse_error()
                src = msg.src.get_name() if msg.src is not None else "pipeline"
                return f"{src}: {err.message}"
            warn, _ = msg.parse_warning()
            log.warning("camera.source %s: %s", self.name, warn.message)

    def read(self, timeout_s: float) -> Frame | None:
        """The newest frame, waiting at most ``timeout_s``; None if none came in time. CameraEnded at
        the end of the stream, CameraError when the pipeline failed."""
        if self._closed:
            raise CameraError(f"camera.source {self.name}: read after close")
        sample = self._sink.try_pull_sample(int(max(timeout_s, 0.0) / _NS))
        if sample is None:
            reason = self._bus_error()
            if reason is not None:
                raise CameraError(f"camera.source {self.name}: {reason}")
            if self._sink.is_eos():
                raise CameraEnded(f"camera.source {self.name}: end of stream after {self._seq} frames")
            return None
        image = _grey_from_sample(self._Gst, self._GstVideo, sample, self.name)
        frame = Frame(image, self._exposure_time_s(sample.get_buffer().pts), self._seq)
        self._seq += 1
        return frame

    def _exposure_time_s(self, pts: int) -> float:
        """The capture time on the host clock: PTS + base time, carried over by its age on the pipeline
        clock; grab time minus latency where there is no usable PTS (or the config says grab)."""
        clock = self._pipeline.get_clock()
        # Both clocks read back to back: the age carried over is off by no more than the gap between them.
        t_grab_s = self.clock.now_s()
        t_pipeline_ns = clock.get_time() if clock is not None else None
        fallback = t_grab_s - self.options.latency_ms * 1e-3
        if self.options.timestamps == "grab" or pts == self._Gst.CLOCK_TIME_NONE or t_pipeline_ns is None:
            return fallback
        age_s = (t_pipeline_ns - (self._pipeline.get_base_time() + pts)) * _NS
        if self.options.timestamps == "auto" and not 0.0 <= age_s < _MAX_AGE_S:
            return fallback
        return t_grab_s - age_s

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._pipeline.set_state(self._Gst.State.NULL)
