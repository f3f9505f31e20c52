"""What ``mavvo replay`` would use from a source, without replaying it (``mavvo inspect PATH``).

For a flight-controller log (.tlog, dataflash .bin/.log, PX4 .ulg), a mavvo recording, a video file or
image folder, or a EuRoC/ASL folder: each time series replay would read (where from, how many, rate,
time range, longest gap), how the attitude would pair with frames, the overlap of frames and attitude
when both are known, and what is missing for a replay with the option that supplies it.

Times are each source's own clock in seconds (a log's boot clock, a video's time from its first frame,
a dataset's Unix time); rates are samples per second over the series' span.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mavvo.errors import ConfigError
from mavvo.offline.sources import log_pairing_gap_s
from mavvo.service.timing import TimingOptions

__all__ = ["SeriesInfo", "Missing", "Inspection", "inspect_source", "series_info"]

_LOG_SUFFIXES = (".tlog", ".bin", ".log", ".ulg")
_SLOW_ATTITUDE_HZ = 10.0  # below this, interpolated roll/pitch degrade the estimates (timing.attitude_accel_rad_s2)


@dataclass(frozen=True)
class SeriesInfo:
    """One time series: ``source`` names the message or file it comes from."""

    name: str
    source: str
    count: int
    rate_hz: float | None = None
    start_s: float | None = None
    end_s: float | None = None
    longest_gap_s: float | None = None


@dataclass(frozen=True)
class Missing:
    """Something a replay lacks; ``fix``: the option or file that supplies it; ``blocking``: replay
    refuses without it (otherwise it runs, with less)."""

    what: str
    fix: str
    blocking: bool


@dataclass(frozen=True)
class Inspection:
    path: str
    kind: str  # tlog, dataflash, ulog, recording, video, images, euroc
    series: tuple[SeriesInfo, ...]
    facts: dict[str, Any] = field(default_factory=dict)  # how replay would use it (pairing limit, overlap, ...)
    missing: tuple[Missing, ...] = ()
    problems: tuple[str, ...] = ()  # damage the readers found

    @property
    def replayable(self) -> bool:
        return not any(m.blocking for m in self.missing)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["replayable"] = self.replayable
        return d


def series_info(name: str, source: str, t_s: np.ndarray) -> SeriesInfo:
    """Count, rate, range and longest gap of the sample times ``t_s`` (seconds, any order)."""
    t = np.sort(np.asarray(t_s, dtype=float))
    if len(t) == 0:
        return SeriesInfo(name, source, 0)
    span = float(t[-1] - t[0])
    rate = (len(t) - 1) / span if len(t) > 1 and span > 0 else None
    gap = float(np.diff(t).max()) if len(t) > 1 else None
    return SeriesInfo(
        name,
        source,
        len(t),
        None if rate is None else round(rate, 3),
        round(float(t[0]), 6),
        round(float(t[-1]), 6),
        None if gap is None else round(gap, 4),
    )


def _interpolation_sigma_deg(gap_s: float) -> float:
    """The roll/pitch uncertainty interpolation adds in the middle of a gap (see
    :meth:`mavvo.service.timing.FlightControllerState.pair`)."""
    return float(np.degrees(0.5 * TimingOptions().attitude_accel_rad_s2 * (gap_s / 2) ** 2))


def _overlap(facts: dict[str, Any], a: SeriesInfo, b: SeriesInfo, offset_s: float = 0.0) -> None:
    if a.count and b.count and a.start_s is not None and b.start_s is not None:
        lo, hi = max(a.start_s + offset_s, b.start_s), min(a.end_s + offset_s, b.end_s)  # type: ignore[operator]
        facts[f"{a.name}_{b.name}_overlap_s"] = round(max(hi - lo, 0.0), 3)


def _inspect_log(
    p: Path, video: Path | None, fps: float | None, offset_s: float | None, config: Path | None
) -> Inspection:
    from mavvo.offline.fc_logs import read_fc_log

    s = read_fc_log(p)
    src = s.sources
    att = series_info("attitude", src["attitude"], s.attitude[:, 0])
    series = [att]
    rng_ok = s.range_m[np.isfinite(s.range_m[:, 1])] if len(s.range_m) else s.range_m
    series.append(series_info("range", src["range"], rng_ok[:, 0]))
    series.append(series_info("height", src["height"] or "-", s.height_m[:, 0]))
    series.append(series_info("position", src["position"], s.local_ned_m[:, 0]))
    series.append(series_info("camera_triggers", src["triggers"], s.triggers_s))
    facts: dict[str, Any] = {"duration_s": round(float(s.attitude[-1, 0] - s.attitude[0, 0]), 3)}
    gap = log_pairing_gap_s(s.attitude[:, 0], TimingOptions().max_attitude_gap_s)
    facts["attitude_pairing_max_gap_s"] = gap
    facts["attitude_pairing"] = (
        "exact enough (at the flight controller's rate)"
        if not att.rate_hz or att.rate_hz >= _SLOW_ATTITUDE_HZ
        else (
            f"slow stream: every frame pairs, degraded; roll/pitch sigma up to {_interpolation_sigma_deg(1.0 / att.rate_hz):.1f} deg "  # type: ignore[operator]
            f"between samples {1.0 / att.rate_hz:.2f} s apart"  # type: ignore[operator]
        )
    )
    if len(s.range_m):
        facts["range_valid_fraction"] = round(len(rng_ok) / len(s.range_m), 3)
    missing: list[Missing] = []
    if video is None:
        missing.append(Missing("the flight's video", "--video FILE_OR_FOLDER", True))
    else:
        frames = _frames_series(video, fps)
        series.insert(0, frames)
        if offset_s is not None:
            _overlap(facts, frames, att, offset_s)
            facts["time_offset_s"] = offset_s
        else:
            facts["time_offset_s"] = "estimated by replay from the rotation the camera sees (or give --offset-s)"
    if config is None:
        missing.append(
            Missing(
                "the camera (intrinsics, rate) and its mounting",
                "--config FILE (mavvo calibrate writes the camera part)",
                True,
            )
        )
    if not len(rng_ok) and not len(s.height_m):
        missing.append(
            Missing(
                "a rangefinder or height for metric scale",
                "--config with odometry.scale.source: fixed and fixed_height_m, or carried",
                False,
            )
        )
    if not len(s.local_ned_m):
        missing.append(
            Missing("a reference trajectory to evaluate against", "--ground-truth FILE (TUM or EuRoC CSV)", False)
        )
    return Inspection(str(p), s.kind, tuple(series), facts, tuple(missing), tuple(s.problems))


def _frames_series(path: Path, fps: float | None) -> SeriesInfo:
    from mavvo.offline.sources import VideoFrames

    v = VideoFrames(path, fps)
    return series_info("frames", "image folder" if path.is_dir() else "video file", v.times_s)


def _inspect_video(p: Path, fps: float | None) -> Inspection:
    from mavvo.offline.sources import VideoFrames

    v = VideoFrames(p, fps)
    frames = series_info("frames", "image folder" if p.is_dir() else "video file", v.times_s)
    missing = (Missing("the flight-controller log with the attitude", "mavvo replay LOG --video " + str(p), True),)
    return Inspection(
        str(p), "images" if p.is_dir() else "video", (frames,), {"duration_s": frames.end_s}, missing, tuple(v.problems)
    )


_MSG_IDS = {30: "ATTITUDE", 132: "DISTANCE_SENSOR", 33: "GLOBAL_POSITION_INT", 32: "LOCAL_POSITION_NED"}


def _inspect_recording(p: Path) -> Inspection:
    from mavvo.offline.recording import load_recording

    inp = load_recording(p)
    by_id: dict[int, list[float]] = {k: [] for k in _MSG_IDS}
    for t_us, frame in inp.messages:
        if len(frame) >= 10 and frame[0] == 0xFD:  # MAVLink 2: the message id is bytes 7..9
            msg_id = int.from_bytes(frame[7:10], "little")
            if msg_id in by_id:
                by_id[msg_id].append(t_us * 1e-6)
    frames = series_info("frames", "frames/ (recorded exposures)", np.array([f.t_exposure_s for f in inp.frames]))
    series = [frames] + [series_info(name.lower(), name, np.array(by_id[i])) for i, name in _MSG_IDS.items()]
    facts: dict[str, Any] = {
        "duration_s": None if frames.start_s is None else round(frames.end_s - frames.start_s, 3),  # type: ignore[operator]
        "recorded_estimates": len(inp.expected_vpe or []),
        "reference": inp.reference_label or None,
    }
    _overlap(facts, frames, series[1])
    return Inspection(str(p), "recording", tuple(series), facts, (), tuple(inp.problems))


def _inspect_euroc(p: Path) -> Inspection:
    from mavvo.offline.euroc import dataset_times

    mav0 = p if p.name == "mav0" else p / "mav0"
    times = dataset_times(mav0)
    series = [series_info(name, source, t) for name, (source, t) in times.items()]
    facts: dict[str, Any] = {}
    by = {s.name: s for s in series}
    _overlap(facts, by["frames"], by["imu"])
    missing: list[Missing] = []
    if by["ground_truth"].count == 0:
        missing.append(
            Missing(
                "ground truth (state_groundtruth_estimate0): no reference, no height for scale",
                "--ground-truth FILE; --config with odometry.scale.fixed_height_m (the flight's height)",
                False,
            )
        )
    else:
        _overlap(facts, by["frames"], by["ground_truth"])
    facts["attitude"] = "from the IMU through an attitude filter that estimates the gyro bias (--attitude imu)"
    return Inspection(str(p), "euroc", tuple(series), facts, tuple(missing), ())


def inspect_source(
    path: Path,
    *,
    video: Path | None = None,
    fps: float | None = None,
    offset_s: float | None = None,
    config: Path | None = None,
) -> Inspection:
    """What replay would use from ``path`` (see the module docstring); ConfigError naming what is
    wrong when it cannot be read at all."""
    from mavvo.offline.recording import is_recording

    if not path.exists():
        raise ConfigError(f"{path}: no such file or folder")
    if path.is_dir() and is_recording(path):
        return _inspect_recording(path)
    if path.is_dir() and ((path / "mav0").is_dir() or path.name == "mav0"):
        return _inspect_euroc(path)
    if path.is_file() and path.suffix.lower() in _LOG_SUFFIXES:
        return _inspect_log(path, video, fps, offset_s, config)
    if path.is_dir() or path.is_file():
        try:
            return _inspect_video(path, fps)
        except ConfigError as e:
            raise ConfigError(
                f"{path}: not a source mavvo can replay (expected a flight-controller log .tlog/.bin/.log/.ulg, a mavvo recording, "
                f"a video file or image folder, or a EuRoC/ASL folder): {e}"
            ) from e
    raise ConfigError(f"{path}: not a file or folder")
