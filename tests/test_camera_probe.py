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


def test_reported_exposure_and_gain_are_measured_and_advised_on() -> None:
    clock = SteppedClock()

    class AutoExposing(ScriptedSource):
        exposures = [2000.0] * 5 + [12000.0] * 5  # the camera lengthens its exposure in a darker room

        def read(self, timeout_s: float) -> Frame | None:
            f = super().read(timeout_s)
            return Frame(f.image, f.t_exposure_s, f.seq, exposure_us=self.exposures[f.seq], gain=1.0 + f.seq)

    m = measure(AutoExposing(clock, [(i, 100.0 + 0.02 * i) for i in range(10)], age_s=0.01), clock, 10.0, "scripted")
    assert (m.exposure_us_min, m.exposure_us_max, m.gain_min, m.gain_max) == (2000.0, 12000.0, 1.0, 10.0)
    text = "\n".join(advice(m, CameraOptions(rate_hz=50.0)))
    assert "changed its exposure (2000-12000 us) or gain (1.00-10.00)" in text
    assert "exposures up to 12000 us are over half the frame period" in text  # 20 ms at 50 Hz
    quiet = measure(ScriptedSource(clock, [(i, 200.0 + 0.02 * i) for i in range(10)], age_s=0.01), clock, 10.0, "s")
    assert np.isnan(quiet.exposure_us_max) and not any("exposure (" in t for t in advice(quiet, CameraOptions()))
