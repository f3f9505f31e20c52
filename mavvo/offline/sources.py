"""What ``mavvo replay SOURCE`` can read, turned into a :class:`mavvo.offline.driver.ReplayInput`:

- a mavvo recording (:mod:`mavvo.offline.recording`);
- a flight-controller log (.tlog or dataflash .bin, :mod:`mavvo.offline.fc_logs`) with a video file or an image
  folder, the time offset between them given or estimated (:mod:`mavvo.offline.time_offset`);
- a EuRoC/ASL dataset folder (:mod:`mavvo.offline.euroc`).

For a log, the host clock of the replay is the flight controller's boot clock: every message arrives
at its own time stamp and a frame exposed at video time ``t`` is at ``t + offset_s``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from mavvo.errors import CameraError, ConfigError
from mavvo.evaluation.metrics import PoseSeries
from mavvo.evaluation.report import read_tum
from mavvo.geometry.frames import R_from_euler321
from mavvo.offline.driver import ReplayFrame, ReplayInput
from mavvo.offline.fc_logs import FcSeries, read_fc_log, series_messages
from mavvo.offline.recording import is_recording, load_recording
from mavvo.offline.time_offset import attitude_rotation_rates, camera_rotation_rates, estimate_offset
from mavvo.service.camera import read_frame_index
from mavvo.service.settings import ServiceConfig, parse_config
from mavvo.service.yaml_loader import load_yaml

__all__ = ["open_replay_source", "VideoFrames", "read_reference"]

_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


def _grey(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


class VideoFrames:
    """The frames of a video file or an image folder with their times on the video's own clock: seconds
    from the first frame for a video file or a folder taken at ``fps``, the listed times for a folder with
    a ``timestamps.txt`` (``TIME_S FILENAME`` lines, as ``camera.source`` reads), so that frames stamped on
    the flight controller's clock replay with an offset of 0. ``problems``: a video that ends before the frame count
    its header gives, listed images that are missing.
    """

    def __init__(self, path: Path, fps: float | None = None) -> None:
        self.path = path
        self.problems: list[str] = []
        self._files: list[Path] | None = None
        if path.is_dir():
            self.times_s, self._files = self._scan_folder(path, fps)
        elif path.is_file():
            self.times_s = self._scan_video(path)
        else:
            raise ConfigError(f"--video {path}: no such file or folder")
        if len(self.times_s) < 2:
            raise ConfigError(f"--video {path}: expected frames, found {len(self.times_s)}")
        self._cap: Any = None
        self._next_index = 0

    def _scan_folder(self, folder: Path, fps: float | None) -> tuple[np.ndarray, list[Path]]:
        index = folder / "timestamps.txt"
        if index.is_file():
            try:
                listed = read_frame_index(folder)
            except CameraError as e:
                raise ConfigError(str(e)) from e
            times, files = [], []
            for n, t, path in listed:
                if not path.is_file():
                    self.problems.append(f"{index}:{n}: {path.name} is missing; the frames after it are not replayed")
                    break
                times.append(t)
                files.append(path)
            return np.array(times), files  # as listed: 0 offset when they are on the log's clock already
        if fps is None or not fps > 0:
            raise ConfigError(f"--video {folder}: an image folder without timestamps.txt needs --fps")
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_EXTENSIONS)
        return np.arange(len(files)) / fps, files

    def _scan_video(self, path: Path) -> np.ndarray:
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise ConfigError(f"--video {path}: cannot open as a video file")
        declared = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
        times = []
        while cap.grab():
            t = cap.get(cv2.CAP_PROP_POS_MSEC) * 1e-3
            if times and not t > times[-1]:  # a container without frame times: index / rate
                t = len(times) / (fps or 20.0)
            times.append(t)
        cap.release()
        if declared > 0 and len(times) < declared:
            self.problems.append(
                f"--video {path}: the video ends after {len(times)} of the {declared} frames its header declares (cut off?)"
            )
        return np.array(times) - (times[0] if times else 0.0)

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:
        """(t_s, grey image) in order, from the start."""
        if self._files is not None:
            for t, f in zip(self.times_s, self._files):
                img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
                if img is not None:
                    yield float(t), _grey(img)
            return
        cap = cv2.VideoCapture(str(self.path))
        try:
            for t in self.times_s:
                ok, img = cap.read()
                if not ok:
                    return
                yield float(t), _grey(img)
        finally:
            cap.release()

    def load(self, k: int) -> np.ndarray:
        """Frame ``k``; a video is read forward, so frames must be asked for in increasing order."""
        if self._files is not None:
            img = cv2.imread(str(self._files[k]), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ConfigError(f"{self._files[k]}: cannot read the image")
            return _grey(img)
        if self._cap is None or k < self._next_index:
            self._cap = cv2.VideoCapture(str(self.path))
            self._next_index = 0
        while self._next_index < k:
            self._cap.grab()
            self._next_index += 1
        ok, img = self._cap.read()
        self._next_index += 1
        if not ok:
            raise ConfigError(f"--video {self.path}: cannot read frame {k}")
        return _grey(img)


def read_reference(path: Path) -> tuple[PoseSeries, str]:
    """A reference trajectory: a TUM file, or a EuRoC ground-truth CSV (nanoseconds, position, wxyz)."""
    if path.suffix.lower() == ".csv":
        from mavvo.offline.euroc import read_euroc_groundtruth

        return read_euroc_groundtruth(path), "ground truth"
    return read_tum(path), "ground truth"


def _load_config(path: Path | None) -> dict[str, Any]:
    return load_yaml(path) if path is not None else {}


def log_pairing_gap_s(t_attitude_s: np.ndarray, configured_s: float) -> float:
    """The gap allowed between the two attitude samples around a frame when replaying a log with
    attitude at these times: 1.5 times the median interval or the 99th percentile, whichever is longer,
    never below the configured limit, at most 1 s, to the boot clock's millisecond."""
    dt = np.diff(np.asarray(t_attitude_s, dtype=float))
    dt = dt[dt > 0]
    if not len(dt):
        return configured_s
    gap = min(max(configured_s, 1.5 * float(np.median(dt)), float(np.percentile(dt, 99))), 1.0)
    return float(np.ceil(gap * 1000.0 - 1e-9) / 1000.0)


def paired_at_log_rate(config: ServiceConfig, t_attitude_s: np.ndarray) -> tuple[ServiceConfig, dict[str, Any]]:
    """``config`` with ``timing.max_attitude_gap_s`` set from the log's own attitude rate
    (:func:`log_pairing_gap_s`), so that every frame pairs: a live link's 50 ms limit would skip every
    frame of a ground station's 2 Hz telemetry log. The interpolation's uncertainty grows with the gap
    and degrades the estimates that need it (``timing.attitude_accel_rad_s2``)."""
    dt = np.diff(t_attitude_s)
    dt = dt[dt > 0]
    configured = config.timing.max_attitude_gap_s
    if not len(dt):
        return config, {"rate_hz": None, "max_gap_s": configured}
    gap = log_pairing_gap_s(t_attitude_s, configured)
    timing = dataclasses.replace(
        config.timing, max_attitude_gap_s=gap, history_s=max(config.timing.history_s, 4.0 * gap)
    )
    # A frame is handed over once the sample after it has come, up to the gap after its exposure: its
    # estimate must not be dropped as too old to send for that wait.
    output = dataclasses.replace(config.output, max_age_s=max(config.output.max_age_s, gap + 0.5))
    note = {
        "rate_hz": round(1.0 / float(np.median(dt)), 2),
        "max_gap_s": gap,
        "configured_max_gap_s": configured,
        "longest_interval_s": round(float(dt.max()), 3),
    }
    return dataclasses.replace(config, timing=timing, output=output), note


def _fc_reference(s: FcSeries) -> PoseSeries | None:
    """The flight controller's own position (LOCAL_POSITION_NED, XKF1) with its attitude."""
    if len(s.local_ned_m) < 3:
        return None
    t = s.local_ned_m[:, 0]
    att = s.attitude
    yaw = np.interp(t, att[:, 0], np.unwrap(att[:, 3]))
    R = np.array(
        [
            R_from_euler321(np.interp(ti, att[:, 0], att[:, 1]), np.interp(ti, att[:, 0], att[:, 2]), y)
            for ti, y in zip(t, yaw)
        ]
    )
    return PoseSeries.from_rotations(t, s.local_ned_m[:, 1:4], R)


def _from_log(
    log_path: Path, config_path: Path | None, video: Path | None, fps: float | None, offset_s: float | None
) -> ReplayInput:
    if video is None:
        raise ConfigError(f"{log_path}: a flight-controller log needs the flight's video: --video FILE_OR_FOLDER")
    if config_path is None:
        raise ConfigError(
            f"{log_path}: a flight-controller log needs --config with the camera (intrinsics, rate) and its mounting"
        )
    config = parse_config(_load_config(config_path), str(config_path))
    s = read_fc_log(log_path)
    frames_src = VideoFrames(video, fps)
    problems = s.problems + frames_src.problems
    notes: dict[str, Any] = {
        "log": f"{s.kind}, {len(s.attitude)} attitude samples over {s.attitude[-1, 0] - s.attitude[0, 0]:.1f} s"
    }
    if offset_s is None:
        step = 2
        cam_t, cam_w = camera_rotation_rates(frames_src, config.camera.camera_model(), step=step)
        interval = step * float(np.median(np.diff(frames_src.times_s)))
        fc_t, fc_w = attitude_rotation_rates(s.attitude, config.mounting.rotation()[:, 2], interval)
        est = estimate_offset(cam_t, cam_w, fc_t, fc_w, source=f"--video {video}")
        offset_s = est.offset_s
        notes["time_offset"] = {"estimated": True, **est.as_dict()}
    else:
        notes["time_offset"] = {"estimated": False, "offset_s": offset_s}
    t_exp = frames_src.times_s + offset_s
    inside = (t_exp >= s.attitude[0, 0]) & (t_exp <= s.attitude[-1, 0])
    if not inside.any():
        raise ConfigError(
            f"--video {video}: with the offset {offset_s:.3f} s no frame falls inside the log's attitude ({s.attitude[0, 0]:.1f} to {s.attitude[-1, 0]:.1f} s)"
        )
    if not inside.all():
        notes["frames_outside_log"] = int((~inside).sum())
    config, notes["attitude_pairing"] = paired_at_log_rate(config, s.attitude[:, 0])
    gap = config.timing.max_attitude_gap_s
    frames = [
        ReplayFrame(k, float(t), float(t) + gap, None, (lambda k=k: frames_src.load(k)))
        for k, t in enumerate(t_exp)
        if inside[k]
    ]
    ref = _fc_reference(s)
    return ReplayInput(
        s.kind,
        str(log_path),
        config,
        series_messages(s),
        frames,
        ref,
        "flight controller's local position" if ref is not None else "",
        notes=notes,
        problems=problems,
    )


def open_replay_source(
    source: Path,
    *,
    config: Path | None = None,
    video: Path | None = None,
    fps: float | None = None,
    offset_s: float | None = None,
    ground_truth: Path | None = None,
    attitude: str = "imu",
    attitude_noise_deg: float = 0.1,
) -> ReplayInput:
    """The replay input for ``source`` (see the module docstring); ConfigError naming what is wrong."""
    if not source.exists():
        raise ConfigError(f"{source}: no such file or folder")
    if source.is_dir() and is_recording(source):
        inp = load_recording(source, _load_config(config))
    elif source.is_dir() and ((source / "mav0").is_dir() or source.name == "mav0"):
        from mavvo.offline.euroc import load_euroc

        inp = load_euroc(source, _load_config(config), attitude=attitude, attitude_noise_deg=attitude_noise_deg)
    elif source.is_file():
        inp = _from_log(source, config, video, fps, offset_s)
    else:
        inp = load_recording(source)  # raises with what the folder holds
    if ground_truth is not None:
        inp.reference, inp.reference_label = read_reference(ground_truth)
    return inp
