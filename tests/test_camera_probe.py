"""What ``mavvo camera`` measures and advises, on a source and clock the test controls: lost frames from
sequence gaps and from stamp gaps, the stamp age, and advice that names the keys to change."""

from __future__ import annotations

import numpy as np
import pytest

from mavvo.errors import CameraEnded
from mavvo.service.camera_options import CameraOptions
from mavvo.service.camera_probe import advice, measure
from mavvo.types import Frame


class SteppedClock:
    realtime = False

    def __init__(self) -> None:
        self.t = 100.0

    def now_s(self) -> float:
        return self.t


class ScriptedSource:
    """Frames at the given (seq, stamp) pairs; each read moves the clock to the stamp plus ``age_s``."""

    def __init__(
        self, clock: SteppedClock, frames: list[tuple[int, float]], age_s: float, brightness: list[int] | None = None
    ) -> None:
        self.clock, self.frames, self.age_s = clock, list(frames), age_s
        self.brightness = brightness or [100] * len(frames)

    def read(self, timeout_s: float) -> Frame | None:
        if not self.frames:
            raise CameraEnded("scripted: done")
        seq, t = self.frames.pop(0)
        self.clock.t = t + self.age_s
        return Frame(np.full((48, 64), self.brightness.pop(0), np.uint8), t, seq)

    def close(self) -> None:
        pass


def test_stamp_gaps_count_as_lost_frames_where_the_sequence_has_none() -> None:
    clock = SteppedClock()
    stamps = [100.0 + 0.05 * k for k in range(20) if k not in (7, 12, 13)]  # 20 Hz, three frames missing
    src = ScriptedSource(clock, [(i, t) for i, t in enumerate(stamps)], age_s=0.012)
    m = measure(src, clock, 10.0, "scripted")
    assert m.frames == 17 and m.dropped == 3 and m.ended == "scripted: done"
    assert m.age_median_ms == pytest.approx(12.0) and m.age_spread_ms == pytest.approx(0.0, abs=1e-9)
    assert (m.width_px, m.height_px) == (64, 48)
    assert m.rate_hz == pytest.approx(16 / 0.95)


def test_sequence_gaps_count_as_lost_frames() -> None:
    clock = SteppedClock()
    src = ScriptedSource(clock, [(0, 100.0), (1, 100.05), (5, 100.1), (6, 100.15)], age_s=0.01)
    assert measure(src, clock, 10.0, "scripted").dropped == 3


def test_advice_names_what_to_change() -> None:
    clock = SteppedClock()
    src = ScriptedSource(clock, [(i, 100.0 + 0.1 * i) for i in range(10)], age_s=0.030, brightness=[60] * 5 + [140] * 5)
    m = measure(src, clock, 10.0, "scripted")
    tips = advice(m, CameraOptions(rate_hz=20.0, width_px=640, height_px=480, latency_ms=30.0))
    text = "\n".join(tips)
    assert "frame rate 10.0 Hz is below camera.rate_hz 20" in text
    assert "frames are 64x48 px but camera.width_px x height_px is 640x480" in text
    assert "stamps come from the grab time minus camera.latency_ms (30 ms)" in text
    assert "auto-exposure is on: set camera.exposure_us" in text
    assert "brightness moved 60-140 of 255" in text
    fine = advice(
        m,
        CameraOptions(
            rate_hz=10.0, width_px=64, height_px=48, cx_px=31.5, cy_px=23.5, latency_ms=5.0, exposure_us=3000
        ),
    )
    assert [t for t in fine if "brightness" not in t] == []
    assert advice(measure(ScriptedSource(clock, [], 0.0), clock, 1.0, "empty"), CameraOptions())[0].startswith(
        "no frame in 1 s"
    )
