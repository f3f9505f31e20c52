"""What cameras this machine has, and how one behaves: the measurements behind ``mavvo camera``.

A camera is judged by what visual odometry needs of it: the frame rate it really delivers, frames lost
before mavvo (gaps in the source's sequence numbers), how far each frame's stamp lies before the moment
mavvo got it (the spread of that age says how much the stamps can be trusted: a driver stamp ages by a
steady transfer time, a grab-time stamp by exactly ``camera.latency_ms``), and whether the exposure moves
(the exposure time and gain the frames report, Picamera2's; the mean brightness for every source).
The listing names each camera's modes (V4L2's enumerated formats, sizes and rates; libcamera's sensor
modes), so ``camera.width_px``, ``height_px`` and ``rate_hz`` can be set to one the camera has.
"""

from __future__ import annotations

import glob
import statistics
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from mavvo.errors import CameraEnded, CameraError
from mavvo.service.camera import FrameSource
from mavvo.service.camera_options import CameraOptions
from mavvo.service.camera_picamera2 import sensor_modes
from mavvo.service.timing import Clock
from mavvo.service.v4l2_modes import v4l2_modes

__all__ = ["CameraListing", "CameraMeasurement", "advice", "list_cameras", "measure"]


@dataclass(frozen=True)
class CameraListing:
    """One camera mavvo could open: the ``camera.source`` to write, and what it is."""

    source: str
    kind: str  # "v4l2", "libcamera", "gstreamer"
    description: str
    modes: tuple[str, ...] = ()  # what the sensor or driver offers: format, size, rates; or why it cannot say


@dataclass(frozen=True)
class CameraMeasurement:
    """A source read for a while. Times in seconds, ages in milliseconds."""

    source: str
    seconds: float
    frames: int
    width_px: int
    height_px: int
    rate_hz: float  # frames over the span of their stamps
    dropped: int  # frames lost before mavvo: gaps in the sequence numbers or in the stamps
    age_median_ms: float  # grab time minus the frame's stamp
    age_spread_ms: float  # 5th to 95th percentile of that age
    brightness_min: float  # mean grey level of the darkest and brightest frame, 0-255
    brightness_max: float
    exposure_us_min: float  # the exposure time and analogue gain the frames report (NaN where the
    exposure_us_max: float  # source does not say: V4L2, GStreamer, files)
    gain_min: float
    gain_max: float
    ended: str | None  # why the source stopped early, or None

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def list_cameras() -> list[CameraListing]:
    """V4L2 capture devices, libcamera cameras (through Picamera2, where installed), and whether
    GStreamer pipelines can be opened."""
    from mavvo.service.camera_gst import INSTALL_HINT as GST_HINT
    from mavvo.service.camera_gst import import_gst
    from mavvo.service.camera_picamera2 import INSTALL_HINT as PICAMERA2_HINT
    from mavvo.service.camera_picamera2 import import_picamera2

    out = []
    for dev in sorted(glob.glob("/dev/video*"), key=lambda d: (len(d), d)):
        name_file = Path("/sys/class/video4linux") / Path(dev).name / "name"
        try:
            name = name_file.read_text(encoding="utf-8").strip()
        except OSError:
            name = "V4L2 device"
        out.append(CameraListing(dev, "v4l2", name, tuple(v4l2_modes(dev))))
    try:
        Picamera2 = import_picamera2()
        for i, info in enumerate(Picamera2.global_camera_info()):
            num = info.get("Num", i)
            out.append(
                CameraListing(
                    f"picamera2:{num}",
                    "libcamera",
                    f"{info.get('Model', '?')} at {info.get('Location', '?')}",
                    _libcamera_modes(Picamera2, num),
                )
            )
    except CameraError:
        out.append(CameraListing("picamera2:INDEX", "libcamera", f"not available: {PICAMERA2_HINT}"))
    try:
        Gst, _, _ = import_gst()
        out.append(
            CameraListing(
                "gst:PIPELINE", "gstreamer", f"{Gst.version_string()}: any pipeline, e.g. gst:videotestsrc is-live=true"
            )
        )
    except CameraError:
        out.append(CameraListing("gst:PIPELINE", "gstreamer", f"not available: {GST_HINT}"))
    return out


def _libcamera_modes(picamera2_cls: Any, num: int) -> tuple[str, ...]:
    """The sensor modes of libcamera camera ``num`` (opened and closed again), or why they cannot be read."""
    try:
        cam = picamera2_cls(num)
    except (IndexError, RuntimeError, OSError) as e:
        return (f"cannot open: {e}",)
    try:
        return tuple(sensor_modes(cam))
    except (RuntimeError, OSError) as e:
        return (f"cannot list modes: {e}",)
    finally:
        cam.close()


def _span(values: list[float]) -> tuple[float, float]:
    nan = float("nan")
    return (min(values), max(values)) if values else (nan, nan)


def _percentile(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, round(q * (len(s) - 1))))]


def _seq_gaps(seqs: list[int]) -> int:
    """Frames missing from the source's sequence numbers."""
    return sum(max(0, b - a - 1) for a, b in zip(seqs, seqs[1:]))


def _stamp_gaps(stamps: list[float]) -> int:
    """Frames missing from the stamps: a gap of k median periods (k >= 2, rounded) lost k - 1 frames.
    Sources that number their own deliveries (GStreamer's appsink dropping the oldest, a V4L2 read
    that skips) show their losses here only."""
    if len(stamps) < 3:
        return 0
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    period = statistics.median(gaps)
    return sum(round(g / period) - 1 for g in gaps if g > 1.5 * period) if period > 0 else 0


def measure(source: FrameSource, clock: Clock, seconds: float, name: str) -> CameraMeasurement:
    """Reads ``source`` for ``seconds`` of ``clock`` and sums up what it delivered."""
    stamps: list[float] = []
    ages_ms: list[float] = []
    seqs: list[int] = []
    brightness: list[float] = []
    exposures_us: list[float] = []
    gains: list[float] = []
    shape = (0, 0)
    ended = None
    t_end = clock.now_s() + seconds
    while clock.now_s() < t_end:
        try:
            frame = source.read(min(1.0, max(0.05, t_end - clock.now_s())))
        except CameraEnded as e:
            ended = str(e)
            break
        t_grab = clock.now_s()
        if frame is None:
            continue
        stamps.append(frame.t_exposure_s)
        ages_ms.append((t_grab - frame.t_exposure_s) * 1e3)
        seqs.append(frame.seq)
        brightness.append(float(frame.image.mean()))
        if frame.exposure_us is not None:
            exposures_us.append(frame.exposure_us)
        if frame.gain is not None:
            gains.append(frame.gain)
        shape = frame.image.shape[:2]
    n = len(stamps)
    span = stamps[-1] - stamps[0] if n >= 2 else 0.0
    dropped = max(_seq_gaps(seqs), _stamp_gaps(stamps))
    nan = float("nan")
    exposure_us_min, exposure_us_max = _span(exposures_us)
    gain_min, gain_max = _span(gains)
    return CameraMeasurement(
        source=name,
        seconds=seconds,
        frames=n,
        width_px=int(shape[1]),
        height_px=int(shape[0]),
        rate_hz=(n - 1) / span if span > 0 else nan,
        dropped=dropped,
        age_median_ms=statistics.median(ages_ms) if ages_ms else nan,
        age_spread_ms=_percentile(ages_ms, 0.95) - _percentile(ages_ms, 0.05) if ages_ms else nan,
        brightness_min=min(brightness, default=nan),
        brightness_max=max(brightness, default=nan),
        exposure_us_min=exposure_us_min,
        exposure_us_max=exposure_us_max,
        gain_min=gain_min,
        gain_max=gain_max,
        ended=ended,
    )


def advice(m: CameraMeasurement, options: CameraOptions) -> list[str]:
    """What to change, in words an operator can act on; empty when nothing looks wrong."""
    out = []
    if m.frames == 0:
        return [f"no frame in {m.seconds:g} s: check camera.source and that nothing else holds the camera"]
    if not m.rate_hz >= 0.9 * options.rate_hz:
        out.append(
            f"frame rate {m.rate_hz:.1f} Hz is below camera.rate_hz {options.rate_hz:g}: lower camera.rate_hz, or the exposure time or resolution"
        )
    if m.dropped:
        out.append(
            f"{m.dropped} frames lost before mavvo (gaps in the sequence or the stamps): a slow consumer or a busy bus"
        )
    if (m.width_px, m.height_px) != (options.width_px, options.height_px):
        out.append(
            f"frames are {m.width_px}x{m.height_px} px but camera.width_px x height_px is {options.width_px}x{options.height_px}: the intrinsics must be of the delivered size"
        )
    if options.timestamps == "grab" or (m.age_spread_ms < 0.05 and abs(m.age_median_ms - options.latency_ms) < 0.05):
        out.append(
            f"stamps come from the grab time minus camera.latency_ms ({options.latency_ms:g} ms): pairing with attitude is only as good as that guess; a source with driver stamps (V4L2, gst:, picamera2:) is better"
        )
    elif m.age_spread_ms > 10.0:
        out.append(
            f"frame stamps age by {m.age_median_ms:.1f} ms with a {m.age_spread_ms:.1f} ms spread: the delivery jitters (load, USB); the stamps themselves may still be right"
        )
    if options.exposure_us == 0:
        out.append(
            "auto-exposure is on: set camera.exposure_us (e.g. 2000-5000) to bound motion blur and stop brightness jumps between frames"
        )
    if m.exposure_us_max > 1.1 * m.exposure_us_min or m.gain_max > 1.1 * m.gain_min:
        out.append(
            f"the camera changed its exposure ({m.exposure_us_min:.0f}-{m.exposure_us_max:.0f} us) or gain "
            f"({m.gain_min:.2f}-{m.gain_max:.2f}) while measuring: features change brightness between frames; fix camera.exposure_us and camera.gain"
        )
    if m.exposure_us_max * (1.0 / 1e6) * m.rate_hz > 0.5:
        out.append(
            f"exposures up to {m.exposure_us_max:.0f} us are over half the frame period: motion blur at speed; bound camera.exposure_us"
        )
    if m.brightness_max - m.brightness_min > 0.2 * max(m.brightness_max, 1.0):
        out.append(
            f"brightness moved {m.brightness_min:.0f}-{m.brightness_max:.0f} of 255 while measuring: the exposure or gain is changing"
        )
    return out
