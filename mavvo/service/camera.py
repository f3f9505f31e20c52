"""Frame sources and the newest-frame queue.

The daemon reads frames through :class:`FrameSource` only, so a V4L2 device, a video file, an image
folder, an injected source and the simulator's rendered camera are interchangeable. Every frame carries
its exposure time on the host clock: the driver's timestamp when it has one (V4L2 buffers are stamped
on the monotonic clock), else the grab time minus ``camera.latency_ms``. File and folder sources replay
their own timestamps from the moment they are opened, paced in real time.

``camera.source`` forms: ``/dev/videoN`` (V4L2), ``gst:PIPELINE`` (a GStreamer pipeline,
:mod:`mavvo.service.camera_gst`), ``picamera2:INDEX`` (a libcamera camera through Picamera2,
:mod:`mavvo.service.camera_picamera2`), a video file, a folder of images with a ``timestamps.txt``
(``TIMESTAMP_S FILENAME`` per line), or ``SCHEME:ARGUMENT`` for a source the caller registers (the CLI
registers ``sim:SCENARIO``, the simulator's rendered camera). Devices are reopened when they fail.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import queue
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, Protocol, runtime_checkable

import cv2
import numpy as np

from mavvo.errors import CameraEnded, CameraError, CameraLost, FrameRefused
from mavvo.service.camera_options import CameraOptions
from mavvo.service.timing import Clock, FlightControllerState
from mavvo.types import Frame

__all__ = [
    "CameraOptions",
    "FrameSource",
    "FrameQueue",
    "InjectedSource",
    "V4L2Source",
    "VideoFileSource",
    "ImageFolderSource",
    "ReconnectingSource",
    "open_source",
]

log = logging.getLogger(__name__)

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".tif", ".tiff")
_DRIVER_STAMP_PLAUSIBLE_S = 1.0
_V4L2_READ_TIMEOUT_MS = 1000.0


@runtime_checkable
class FrameSource(Protocol):
    """A camera as the daemon sees it."""

    def read(self, timeout_s: float) -> Frame | None:
        """The next frame, waiting at most ``timeout_s`` (where the source can: see
        :meth:`V4L2Source.read`); None if none came in time.

        Raises :class:`CameraEnded` when a finite source is done, :class:`CameraError` when it failed.
        """

    def close(self) -> None:
        """Release the device or file; idempotent."""


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    return image


class FrameQueue:
    """Frames between the camera thread and the worker.

    ``drop_oldest`` (real time): ``put`` never blocks; a full queue drops its oldest frame (counted in
    ``dropped``), so the worker always gets the newest. Otherwise (lockstep simulation) ``put`` waits
    for room, so no frame is lost and runs repeat.
    """

    def __init__(self, capacity: int, *, drop_oldest: bool = True) -> None:
        self._q: queue.Queue[Frame] = queue.Queue(capacity)
        self.drop_oldest = drop_oldest
        self.dropped = 0

    def put(self, frame: Frame, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                if self.drop_oldest:
                    self._q.put_nowait(frame)
                else:
                    self._q.put(frame, timeout=0.05)
                return
            except queue.Full:
                if self.drop_oldest:
                    try:
                        self._q.get_nowait()
                        self.dropped += 1
                    except queue.Empty:
                        pass

    def get(self, timeout_s: float) -> Frame | None:
        try:
            return self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def empty(self) -> bool:
        return self._q.empty()


class InjectedSource:
    """Frames pushed by the embedding program (or a test): ``push`` queues one, ``end`` finishes."""

    def __init__(self) -> None:
        self._q: queue.Queue[Frame | None] = queue.Queue()
        self._seq = 0
        self._ended = False

    def push(self, image: np.ndarray, t_exposure_s: float, seq: int | None = None) -> None:
        """Queue one frame; ``seq`` defaults to one more than the last."""
        self._seq = self._seq if seq is None else seq
        self._q.put(Frame(image, float(t_exposure_s), self._seq))
        self._seq += 1

    def end(self) -> None:
        self._q.put(None)

    def read(self, timeout_s: float) -> Frame | None:
        if self._ended:
            raise CameraEnded("injected source: ended")
        try:
            f = self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if f is None:
            self._ended = True
            raise CameraEnded("injected source: ended")
        return f

    def close(self) -> None:
        self._ended = True


@contextlib.contextmanager
def _opencv_quiet() -> Iterator[None]:
    """OpenCV's log at errors only, for a call whose failure mavvo reports in its own words."""
    previous = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(previous)


class V4L2Source:
    """A V4L2 camera through OpenCV, grey frames, stamped as ``options.timestamps`` says."""

    def __init__(self, device: str, options: CameraOptions, clock: Clock) -> None:
        self.device, self.options, self.clock = device, options, clock
        if not os.path.exists(device):
            raise CameraError(
                f"camera.source {device}: no such device (is the camera plugged in? mavvo camera lists the ones here)"
            )
        with _opencv_quiet():  # OpenCV's own [ WARN ] lines would stand beside mavvo's error
            cap = cv2.VideoCapture(device, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise CameraError(
                f"camera.source {device}: cannot open the V4L2 device (busy, no permission: the video group, or no capture device)"
            )
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, options.width_px)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, options.height_px)
        cap.set(cv2.CAP_PROP_FPS, options.rate_hz)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not a backlog
        _set_v4l2_controls(cap, device, options)
        # OpenCV's V4L2 read waits up to 10 s for a frame unless told otherwise (where the build honours it).
        self._timeout_honoured = bool(cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, _V4L2_READ_TIMEOUT_MS))
        self._cap = cap
        self._seq = 0

    def read(self, timeout_s: float) -> Frame | None:
        """The next frame. OpenCV's read blocks until the driver delivers a frame or its own timeout
        expires (1 s where the build honours ``CAP_PROP_READ_TIMEOUT_MSEC``, else 10 s), which raises
        CameraError; ``timeout_s`` is not used."""
        if self._cap is None:
            raise CameraError(f"camera.source {self.device}: read after close")
        ok, img = self._cap.read()
        t_grab = self.clock.now_s()
        if not ok or img is None:
            raise CameraError(f"camera.source {self.device}: no frame (device lost?)")
        t_exp = t_grab - self.options.latency_ms * 1e-3
        if self.options.timestamps != "grab":
            t_driver = self._cap.get(cv2.CAP_PROP_POS_MSEC) * 1e-3
            plausible = t_driver > 0 and abs(t_driver - t_grab) < _DRIVER_STAMP_PLAUSIBLE_S
            if plausible or self.options.timestamps == "driver":
                t_exp = t_driver
        frame = Frame(_grey(img), t_exp, self._seq)
        self._seq += 1
        return frame

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def _set_v4l2_controls(cap: cv2.VideoCapture, device: str, options: CameraOptions) -> None:
    """A fixed exposure (V4L2 counts it in units of 100 us) and gain where set; CameraError naming the
    key when the driver has no such control."""
    wanted = []
    if options.exposure_us > 0:
        wanted += [
            ("exposure_us", cv2.CAP_PROP_AUTO_EXPOSURE, 1.0),
            ("exposure_us", cv2.CAP_PROP_EXPOSURE, options.exposure_us / 100.0),
        ]
    if options.gain > 0:
        wanted.append(("gain", cv2.CAP_PROP_GAIN, options.gain))
    for key, prop, value in wanted:
        if not cap.set(prop, value):
            cap.release()
            raise CameraError(
                f"camera.{key}: camera.source {device} has no such V4L2 control (or refused {value}); set it to 0 for the driver's automatic one"
            )


class _PacedSource:
    """Frames with recorded timestamps, replayed from the moment of opening, paced in real time."""

    def __init__(self, name: str, clock: Clock) -> None:
        self.name, self.clock = name, clock
        self._t0_host: float | None = None
        self._t0_rec = 0.0
        self._seq = 0
        self._closed = False
        self._pending: tuple[np.ndarray, float] | None = None

    def _next(self) -> tuple[np.ndarray, float] | None:
        raise NotImplementedError

    def read(self, timeout_s: float) -> Frame | None:
        if self._closed:
            raise CameraError(f"camera.source {self.name}: read after close")
        if self._pending is None:
            self._pending = self._next()
            if self._pending is None:
                raise CameraEnded(f"camera.source {self.name}: end after {self._seq} frames")
        img, t_rec = self._pending
        now = self.clock.now_s()
        if self._t0_host is None:
            self._t0_host, self._t0_rec = now, t_rec
        t_host = self._t0_host + (t_rec - self._t0_rec)
        if self.clock.realtime and t_host > now:
            if t_host - now > timeout_s:  # not due yet: the caller gets control back in time
                time.sleep(timeout_s)
                return None
            time.sleep(t_host - now)
        self._pending = None
        frame = Frame(_grey(img), t_host, self._seq)
        self._seq += 1
        return frame

    def close(self) -> None:
        self._closed = True


class VideoFileSource(_PacedSource):
    """A video file; timestamps from the container (frame index / fps when it has none)."""

    def __init__(self, path: Path, clock: Clock) -> None:
        super().__init__(str(path), clock)
        self._cap = cv2.VideoCapture(str(path))
        if not self._cap.isOpened():
            raise CameraError(f"camera.source {path}: cannot open as a video file")
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self._period_s = 1.0 / fps if fps and math.isfinite(fps) and fps > 0 else 0.05

    def _next(self) -> tuple[np.ndarray, float] | None:
        if self._cap is None:
            return None
        ok, img = self._cap.read()
        if not ok:
            return None
        t = self._cap.get(cv2.CAP_PROP_POS_MSEC) * 1e-3
        return img, (t if t > 0 or self._seq == 0 else self._seq * self._period_s)

    def close(self) -> None:
        super().close()
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def image_size_px(path: Path) -> tuple[int, int] | None:
    """(width, height) of a PNG, JPEG, BMP or PGM/PPM file from its header, without decoding it; None
    for other formats or a header that does not parse. OSError if the file cannot be read."""
    with path.open("rb") as f:
        head = f.read(1 << 16)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head[:2] == b"BM" and len(head) >= 26:
        return int.from_bytes(head[18:22], "little", signed=True), abs(
            int.from_bytes(head[22:26], "little", signed=True)
        )
    if head[:2] in (b"P2", b"P5", b"P3", b"P6"):
        tokens = [t for line in head[2:].split(b"\n") for t in line.split(b"#", 1)[0].split()]
        return (
            (int(tokens[0]), int(tokens[1]))
            if len(tokens) >= 2 and tokens[0].isdigit() and tokens[1].isdigit()
            else None
        )
    if head[:2] == b"\xff\xd8":  # JPEG: walk the segments to the first start-of-frame
        i = 2
        while i + 9 <= len(head) and head[i] == 0xFF:
            marker, length = head[i + 1], int.from_bytes(head[i + 2 : i + 4], "big")
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                return int.from_bytes(head[i + 7 : i + 9], "big"), int.from_bytes(head[i + 5 : i + 7], "big")
            i += 2 + length
    return None


def read_frame_index(folder: Path) -> list[tuple[int, float, Path]]:
    """The frames listed in ``folder/timestamps.txt``: (line number, time in seconds, image path), one
    ``TIMESTAMP_S FILENAME`` per line, ``#`` comments, increasing times; CameraError naming the file and
    line otherwise."""
    index = folder / "timestamps.txt"
    try:
        lines = index.read_text(encoding="utf-8").splitlines()
    except OSError as e:
        raise CameraError(f"camera.source {index}: cannot read: {e.strerror or e}") from e
    items: list[tuple[int, float, Path]] = []
    for n, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(maxsplit=1)
        try:
            t = float(parts[0])
        except ValueError:
            t = math.nan
        if len(parts) != 2 or not math.isfinite(t) or (items and t <= items[-1][1]):
            raise CameraError(f"{index}:{n}: expected 'TIMESTAMP_S FILENAME' with increasing times, got {line!r}")
        items.append((n, t, folder / parts[1]))
    if not items:
        raise CameraError(f"{index}: no frames listed")
    return items


class ImageFolderSource(_PacedSource):
    """A folder of images listed in its ``timestamps.txt``: ``TIMESTAMP_S FILENAME`` per line, ``#``
    comments; timestamps must increase.

    An image larger than ``max_size_px`` (width, height) is refused from its header, before it is
    decoded (:class:`FrameRefused`); one that does not decode is skipped with a warning; a file that has
    vanished (the folder was unmounted) raises CameraError and is tried again on the next read.
    """

    def __init__(self, folder: Path, clock: Clock, max_size_px: tuple[int, int] | None = None) -> None:
        super().__init__(str(folder), clock)
        self._items = [(t, path) for _, t, path in read_frame_index(folder)]
        self._i = 0
        self.max_size_px = max_size_px

    def _next(self) -> tuple[np.ndarray, float] | None:
        while self._i < len(self._items):
            t, path = self._items[self._i]
            try:
                size = image_size_px(path)
            except OSError as e:  # not advanced: the next read tries this file again
                raise CameraError(f"camera.source {self.name}: cannot read {path.name}: {e.strerror or e}") from e
            self._i += 1
            if (
                size is not None
                and self.max_size_px is not None
                and (size[0] > self.max_size_px[0] or size[1] > self.max_size_px[1])
            ):
                raise FrameRefused(
                    f"camera.source {self.name}: {path.name} is {size[0]}x{size[1]} px, larger than camera.width_px x height_px "
                    f"= {self.max_size_px[0]}x{self.max_size_px[1]}; refused"
                )
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is not None:
                return img, t
            log.warning("camera.source %s: cannot read %s; skipped", self.name, path)
        return None


class ReconnectingSource:
    """Reopens a source that failed (not one that ended), with back-off; ``read`` returns None while
    the camera is away, and raises :class:`CameraLost` once it has been away for ``lost_after_s``.
    Counts ``reconnects``."""

    def __init__(
        self,
        open_source: Callable[[], FrameSource],
        clock: Clock,
        *,
        reconnect_max_s: float = 5.0,
        lost_after_s: float = math.inf,
        name: str = "camera",
    ) -> None:
        self._open = open_source
        self.clock = clock
        self.name = name
        self.reconnect_max_s = reconnect_max_s
        self.lost_after_s = lost_after_s
        self.reconnects = 0
        self._source: FrameSource | None = open_source()
        self._backoff_s = 0.25
        self._retry_at_s = -math.inf
        self._away_since_s = math.nan

    def read(self, timeout_s: float) -> Frame | None:
        if self._source is None:
            if self.clock.now_s() - self._away_since_s > self.lost_after_s:
                raise CameraLost(
                    f"camera.source {self.name}: away for {self.clock.now_s() - self._away_since_s:.0f} s (camera.lost_after_s)"
                )
            if self.clock.now_s() < self._retry_at_s:
                time.sleep(min(timeout_s, 0.05))
                return None
            try:
                self._source = self._open()
                self.reconnects += 1
                self._backoff_s = 0.25
                log.info("%s: reopened", self.name)
            except CameraEnded:
                raise
            except CameraError as e:
                self._retry_at_s = self.clock.now_s() + self._backoff_s
                self._backoff_s = min(2 * self._backoff_s, self.reconnect_max_s)
                log.debug("%s: still unavailable: %s", self.name, e)
                return None
        try:
            return self._source.read(timeout_s)
        except CameraEnded:
            raise
        except FrameRefused:
            raise
        except CameraError as e:
            log.warning("%s: %s; reopening", self.name, e)
            self._source.close()
            self._source = None
            self._away_since_s = self.clock.now_s()
            self._retry_at_s = self._away_since_s + self._backoff_s
            return None

    def close(self) -> None:
        if self._source is not None:
            self._source.close()
            self._source = None


SourceFactory = Callable[[str, CameraOptions, Clock, "FlightControllerState | None"], FrameSource]
"""Makes the source of a ``SCHEME:ARGUMENT``: (argument, camera options, host clock, the flight
controller's state as the link fills it, or None), e.g. a simulated camera that follows the flight
controller's clock."""


def open_source(
    options: CameraOptions,
    clock: Clock,
    schemes: dict[str, SourceFactory] | None = None,
    fc: FlightControllerState | None = None,
) -> FrameSource:
    """The source ``options.source`` names (see the module docstring); devices are wrapped to reconnect.
    CameraError naming the source when it is none of the known forms or cannot be opened."""
    spec = options.source
    scheme, sep, arg = spec.partition(":")
    if sep and schemes and scheme in schemes:
        return schemes[scheme](arg, options, clock, fc)
    device: Callable[[], FrameSource] | None = None
    if sep and scheme == "gst":
        from mavvo.service.camera_gst import GstSource

        _refuse_controls(
            options,
            ("exposure_us", "gain"),
            "a gst: source takes its controls in the pipeline description (e.g. v4l2src extra-controls=...)",
        )
        device = functools.partial(GstSource, arg, options, clock)
    elif sep and scheme == "picamera2":
        from mavvo.service.camera_picamera2 import Picamera2Source

        device = functools.partial(Picamera2Source, arg, options, clock)
    elif spec.startswith("/dev/video"):
        device = functools.partial(V4L2Source, spec, options, clock)
    if device is not None:
        return ReconnectingSource(
            device, clock, reconnect_max_s=options.reconnect_max_s, lost_after_s=options.lost_after_s, name=spec
        )
    p = Path(spec)
    if p.is_dir():
        return ImageFolderSource(p, clock, (options.width_px, options.height_px))
    if p.is_file():
        return VideoFileSource(p, clock)
    known = ", ".join(f"{s}:" for s in ("gst", "picamera2", *(schemes or {})))
    raise CameraError(
        f"camera.source {spec!r}: expected /dev/videoN, a video file, an image folder or {known}ARGUMENT; nothing there"
    )


def _refuse_controls(options: CameraOptions, keys: tuple[str, ...], why: str) -> None:
    """CameraError naming the first of ``keys`` set away from its default (0) for a source that cannot apply it."""
    for key in keys:
        if getattr(options, key):
            raise CameraError(
                f"camera.{key}: {getattr(options, key)} is not supported by camera.source {options.source!r}: {why}; set it to 0"
            )
