"""A EuRoC/ASL dataset folder as a replay input.

Read: ``mav0/cam0`` (data.csv, data/*.png, sensor.yaml with ``T_BS``, intrinsics, radial-tangential
distortion, resolution, rate), ``mav0/imu0/data.csv`` (gyro rad/s, accelerometer m/s^2) and, when there,
``mav0/state_groundtruth_estimate0/data.csv``. The host clock is the dataset's (nanoseconds / 1e9).

Frames (mavvo's conventions, see docs/replay.md):
- the body frame is the IMU's turned so that z points along the mean specific force over the first
  second (down at rest, the thrust's axis in flight) and x along the camera's view (or the image's up
  for a camera looking down); ``mounting.R_body_cam`` and ``lever_arm_m`` follow from ``T_BS``;
- roll/pitch come from the IMU through an attitude filter started with the fitted gyro bias (Mahony
  with integral feedback, :mod:`mavvo.offline.imu_attitude`; what a flight controller computes), or
  from the ground truth plus Gaussian noise; yaw is the filter's (it drifts, as a magnetometer-less
  one does);
- height above the start comes from the ground truth with barometer-like noise (the datasets have no
  barometer or rangefinder), so ``odometry.scale.source`` defaults to ``altitude``; a folder without
  ground truth replays with a warning and the height from the configuration (``fixed``, or ``carried``
  when chosen).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import yaml

from mavvo.errors import ConfigError
from mavvo.evaluation.metrics import PoseSeries
from mavvo.geometry.frames import R_from_quat_wxyz, euler321_from_R, quat_wxyz_from_R
from mavvo.offline.driver import ReplayFrame, ReplayInput, image_loader
from mavvo.offline.fc_logs import FcSeries, series_messages
from mavvo.offline.imu_attitude import ATTITUDE_RATE_HZ, imu_attitude, imu_start, level_from_up, tilt_error_deg
from mavvo.offline.recording import merge
from mavvo.service.settings import parse_config

__all__ = ["load_euroc", "read_euroc_groundtruth"]

HEIGHT_RATE_HZ = 10.0
HEIGHT_NOISE_M = 0.1
_D = np.diag([1.0, -1.0, -1.0])  # the datasets' z-up world to mavvo's level frame (z down)


def _rows(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of a dataset CSV, comments and blank lines skipped."""
    if not path.is_file():
        raise ConfigError(f"{path}: missing (expected a EuRoC/ASL dataset file)")
    with path.open(newline="", encoding="utf-8") as f:
        for n, row in enumerate(csv.reader(f), 1):
            if row and not row[0].startswith("#"):
                yield n, row


def _csv(path: Path, min_columns: int) -> np.ndarray:
    rows = []
    for n, row in _rows(path):
        try:
            values = [float(x) for x in row[:min_columns]]
        except ValueError:
            raise ConfigError(f"{path}:{n}: expected {min_columns} numbers, got {','.join(row)!r}") from None
        if len(values) < min_columns:
            raise ConfigError(f"{path}:{n}: expected {min_columns} columns, got {len(row)}")
        rows.append(values)
    return np.array(rows).reshape(-1, min_columns)


def _frame_rows(path: Path) -> list[tuple[str, str]]:
    out = []
    for n, row in _rows(path):
        if len(row) < 2 or not row[0].strip().isdigit():
            raise ConfigError(f"{path}:{n}: expected 'timestamp_ns,filename', got {','.join(row)!r}")
        out.append((row[0].strip(), row[1].strip()))
    return out


def dataset_times(mav0: Path) -> dict[str, tuple[str, np.ndarray]]:
    """The sample times (seconds, the dataset's clock) of the frames, the IMU and the ground truth (empty
    when the folder has none), each with the file it comes from."""
    gt = mav0 / "state_groundtruth_estimate0" / "data.csv"
    return {
        "frames": ("cam0/data.csv", np.array([int(t) * 1e-9 for t, _ in _frame_rows(mav0 / "cam0" / "data.csv")])),
        "imu": ("imu0/data.csv", _csv(mav0 / "imu0" / "data.csv", 7)[:, 0] * 1e-9),
        "ground_truth": (
            "state_groundtruth_estimate0/data.csv",
            _csv(gt, 8)[:, 0] * 1e-9 if gt.is_file() else np.zeros(0),
        ),
    }


def _sensor_yaml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
        data = yaml.safe_load(
            "\n".join(line for line in text.splitlines() if not line.startswith("%"))
        )  # OpenCV's %YAML:1.0
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"{path}: cannot read: {e}") from e
    if not isinstance(data, dict) or "T_BS" not in data:
        raise ConfigError(f"{path}: expected a EuRoC sensor.yaml with T_BS, got {type(data).__name__}")
    return data


def read_euroc_groundtruth(path: Path) -> PoseSeries:
    """The ground truth of the IMU (``p_RS_R``, ``q_RS`` wxyz) as a series in mavvo's level frame."""
    a = _csv(path, 8)
    R = np.array([_D @ R_from_quat_wxyz(q) for q in a[:, 4:8]])
    return PoseSeries.from_rotations(a[:, 0] * 1e-9, a[:, 1:4] @ _D.T, R)


def _body_from_imu(acc_imu: np.ndarray, R_imu_cam: np.ndarray) -> np.ndarray:
    """R_imu_body: body z down (against the mean specific force), x along the view (see the module docstring)."""
    view = R_imu_cam[:, 2] if abs(R_imu_cam[:, 2] @ acc_imu) < 0.9 * np.linalg.norm(acc_imu) else -R_imu_cam[:, 1]
    return level_from_up(acc_imu, view).T


def _camera(sensor_yaml: Path) -> tuple[np.ndarray, dict[str, Any]]:
    """The camera's pose on the IMU, T_imu_cam (4, 4), and its ``camera:`` settings, from cam0's sensor.yaml."""
    cam = _sensor_yaml(sensor_yaml)
    try:
        T_imu_cam = np.array(cam["T_BS"]["data"], dtype=float).reshape(4, 4)
        fu, fv, cu, cv = (float(x) for x in cam["intrinsics"])
        width, height = (int(x) for x in cam["resolution"])
        dist = [float(x) for x in cam.get("distortion_coefficients", ())]
        rate = float(cam.get("rate_hz", 20.0))
    except (KeyError, TypeError, ValueError) as e:
        raise ConfigError(
            f"{sensor_yaml}: expected T_BS (4x4), intrinsics [fu, fv, cu, cv], resolution [w, h]: {e}"
        ) from e
    if cam.get("distortion_model", "radial-tangential") != "radial-tangential":
        raise ConfigError(
            f"{sensor_yaml}: distortion_model: expected radial-tangential, got {cam.get('distortion_model')!r}"
        )
    settings = {"source": "euroc", "width_px": width, "height_px": height, "rate_hz": rate}
    settings.update({"fx_px": fu, "fy_px": fv, "cx_px": cu, "cy_px": cv, "model": "pinhole", "distortion": dist})
    return T_imu_cam, settings


def _truth_attitude(gt: np.ndarray, R_imu_body: np.ndarray, noise_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Rows (t_s, roll, pitch, yaw) at ATTITUDE_RATE_HZ from the ground truth's orientation, roll and pitch
    with ``noise_deg`` of Gaussian noise."""
    att = []
    for row in gt[:: max(int(round(len(gt) / ((gt[-1, 0] - gt[0, 0]) * 1e-9 * ATTITUDE_RATE_HZ))), 1)]:
        r, p, y = euler321_from_R(_D @ R_from_quat_wxyz(row[4:8]) @ R_imu_body)
        n = np.radians(noise_deg) * rng.standard_normal(2)
        att.append((row[0] * 1e-9, r + n[0], p + n[1], y))
    return np.array(att)


def _frames(cam0: Path, gap_s: float, problems: list[str]) -> list[ReplayFrame]:
    """cam0's frames as data.csv lists them, up to the first missing image (named in ``problems``)."""
    frames = []
    for k, (t_ns, name) in enumerate(_frame_rows(cam0 / "data.csv")):
        path = cam0 / "data" / name
        if not path.is_file():
            problems.append(f"{path}: missing; the frames after it are not replayed")
            break
        t = int(t_ns) * 1e-9
        frames.append(ReplayFrame(k, t, t + gap_s, None, image_loader(path)))
    return frames


def _imu_at_rest(imu_path: Path, gt: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray, float]:
    """The IMU's samples (None where not needed), its mean specific force over the first second (which
    way the body's z is: "up" at rest, the thrust's axis in flight) and the first time, s. With ``gt``
    (the truth's attitude is used) and no IMU folder, the truth's first orientation says where up is."""
    if imu_path.is_file() or gt is None:
        imu = _csv(imu_path, 7)
        if len(imu) < 10:
            raise ConfigError(f"{imu_path}: expected IMU samples, found {len(imu)}")
        first_s = imu[:, 0] * 1e-9 <= imu[0, 0] * 1e-9 + 1.0
        return imu, imu[first_s, 4:7].mean(axis=0), imu[0, 0] * 1e-9
    R_lvl_imu = _D @ R_from_quat_wxyz(gt[0, 4:8])
    return None, R_lvl_imu.T @ np.array([0.0, 0.0, -9.81]), gt[0, 0] * 1e-9


def _from_truth(
    gt: np.ndarray,
    R_imu_body: np.ndarray,
    t_imu_cam: np.ndarray,
    attitude_rows: np.ndarray,
    rng: np.random.Generator,
    notes: dict[str, Any],
) -> tuple[np.ndarray, PoseSeries]:
    """From the ground truth: the heights (t_s, m) the flight controller is given, and the camera's
    reference trajectory; what they are goes into ``notes``."""
    t_gt = gt[:, 0] * 1e-9
    step = max(int(round(len(gt) / ((t_gt[-1] - t_gt[0]) * HEIGHT_RATE_HZ))), 1)
    z = gt[::step, 3]
    heights = np.column_stack([t_gt[::step], z - z[0] + HEIGHT_NOISE_M * rng.standard_normal(len(z))])
    notes["height"] = (
        f"the ground truth's height over its start with {HEIGHT_NOISE_M:g} m of noise, as the flight "
        "controller's altitude (odometry.scale.source: altitude); EuRoC has no rangefinder"
    )
    R_lvl_imu = np.array([_D @ R_from_quat_wxyz(q) for q in gt[:, 4:8]])
    p_cam = gt[:, 1:4] @ _D.T + R_lvl_imu @ t_imu_cam  # the camera centre: what mavvo estimates
    reference = PoseSeries(t_gt, p_cam, np.array([quat_wxyz_from_R(R @ R_imu_body) for R in R_lvl_imu]))
    notes["attitude_tilt_error_deg"] = tilt_error_deg(attitude_rows, t_gt, R_lvl_imu @ R_imu_body)
    return heights, reference


def load_euroc(
    root: Path, overrides: dict[str, Any], *, attitude: str = "imu", attitude_noise_deg: float = 0.1, seed: int = 0
) -> ReplayInput:
    """The dataset at ``root`` (the folder holding mav0, or mav0 itself); ``overrides``: settings that
    replace the ones derived from the dataset."""
    mav0 = root if root.name == "mav0" else root / "mav0"
    T_imu_cam, camera = _camera(mav0 / "cam0" / "sensor.yaml")
    gt_path = mav0 / "state_groundtruth_estimate0" / "data.csv"
    gt = _csv(gt_path, 8) if gt_path.is_file() else None
    if attitude == "truth" and gt is None:
        raise ConfigError(f"{gt_path}: missing; --attitude truth needs the ground truth")
    imu, specific_force, t0_s = _imu_at_rest(mav0 / "imu0" / "data.csv", gt if attitude == "truth" else None)
    R_imu_cam, t_imu_cam = T_imu_cam[:3, :3], T_imu_cam[:3, 3]
    R_imu_body = _body_from_imu(specific_force, R_imu_cam)
    R_body_cam = R_imu_body.T @ R_imu_cam
    lever = R_imu_body.T @ t_imu_cam
    data = merge(
        {
            "camera": camera,
            "mounting": {"R_body_cam": R_body_cam.round(9).tolist(), "lever_arm_m": lever.round(6).tolist()},
            "odometry": {"scale": {"source": "altitude"}},
            # The attitude comes from the IMU (or the truth), not from an EKF converging after boot:
            # there is no yaw to wait for, and a short set would lose its first second of frames.
            "service": {"heading_wait_max_s": 0.0},
        },
        overrides,
    )
    warnings: list[str] = []
    if gt is None:
        # The height for scale comes from the ground truth: without it, a height from the configuration.
        odometry = overrides.get("odometry")
        scale = odometry.get("scale") if isinstance(odometry, dict) else None
        chosen = scale.get("source") if isinstance(scale, dict) else None  # a malformed one is parse_config's to name
        if chosen not in ("fixed", "carried"):
            data = merge(data, {"odometry": {"scale": {"source": "fixed"}}})
    config = parse_config(data, f"{mav0} (with --config)")
    if gt is None:
        sc = config.odometry.scale
        how = (
            f"a fixed height of {sc.fixed_height_m:g} m above flat ground (odometry.scale.fixed_height_m)"
            if sc.source == "fixed"
            else "depths carried between keyframes, from an assumed first depth (odometry.scale.initial_depth_m)"
        )
        warnings.append(
            f"{gt_path}: missing: no reference (unless --ground-truth gives one), no attitude error to report, and no height: metric scale from {how}; "
            "give the flight's height with --config (odometry: {scale: {source: fixed, fixed_height_m: H}})"
        )
    rng = np.random.default_rng(seed)
    notes: dict[str, Any] = {"attitude": attitude}
    if gt is not None and attitude == "truth":
        attitude_rows = _truth_attitude(gt, R_imu_body, attitude_noise_deg, rng)
        notes["attitude_noise_deg"] = attitude_noise_deg
    else:
        assert imu is not None  # read above: the attitude is the IMU's
        start = imu_start(imu)
        attitude_rows = imu_attitude(imu, R_imu_body, start)
        notes["gyro_bias_rad_s"] = [round(float(x), 5) for x in start.gyro_bias_rad_s]
    heights, reference = np.zeros((0, 2)), None
    if gt is not None:
        heights, reference = _from_truth(gt, R_imu_body, t_imu_cam, attitude_rows, rng, notes)
    series = FcSeries(str(root), "euroc", attitude_rows, np.zeros((0, 2)), heights)
    problems: list[str] = []
    frames = _frames(mav0 / "cam0", config.timing.max_attitude_gap_s, problems)
    return ReplayInput(
        "euroc",
        str(root),
        config,
        series_messages(series, boot_epoch_s=float(np.floor(t0_s))),
        frames,
        reference,
        "ground truth" if reference is not None else "",
        notes=notes,
        problems=problems,
        warnings=warnings,
    )
