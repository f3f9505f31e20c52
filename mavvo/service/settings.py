"""The service's settings: :class:`ServiceConfig`, read from YAML strictly (``mavvo run --config FILE``).

Each section is the options dataclass of the module it configures, so the defaults and help live next
to the code that uses them: ``camera`` (:mod:`mavvo.service.camera`), ``link`` (:mod:`mavvo.service.link`),
``timing`` (:mod:`mavvo.service.timing`), ``odometry`` (:mod:`mavvo.odometry.pipeline`), ``record``
(:mod:`mavvo.service.recorder`); ``mounting``, ``output`` and
``service`` are defined here. ``config/default.yaml`` lists every key with its default and help;
:func:`default_yaml` writes it (a test keeps the file current). Any key left out takes its default.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mavvo.errors import ConfigError
from mavvo.geometry.frames import R_BODY_CAM_NADIR
from mavvo.odometry.options import OdometryOptions
from mavvo.options import bounded
from mavvo.service.camera import CameraOptions
from mavvo.service.link_options import LinkOptions, parse_url
from mavvo.service.messages import Autopilot
from mavvo.service.recorder import RecordOptions
from mavvo.service.timing import TimingOptions
from mavvo.service.yaml_loader import build, load_yaml

__all__ = [
    "MountingOptions",
    "OutputOptions",
    "ServiceOptions",
    "ServiceConfig",
    "load_config",
    "parse_config",
    "config_yaml",
    "default_yaml",
]

Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


def as_matrix3(R: np.ndarray) -> Matrix3:
    """A (3,3) array as the nested tuple a YAML key holds."""
    return tuple(tuple(float(v) for v in row) for row in R)  # type: ignore[return-value]


@dataclass(frozen=True)
class MountingOptions:
    """Where the camera sits on the vehicle."""

    R_body_cam: Matrix3 = bounded(
        as_matrix3(R_BODY_CAM_NADIR),
        "rotation taking camera vectors (x right, y down, z forward) into the body frame (FRD), rows; default: nadir, image top forward",
        ge=-1,
        le=1,
    )
    lever_arm_m: tuple[float, float, float] = bounded(
        (0.0, 0.0, 0.0),
        "camera centre in the body frame (FRD), metres: set VISO_POS_X/Y/Z (ArduPilot) or EKF2_EV_POS_X/Y/Z (PX4) to it",
        ge=-10,
        le=10,
    )

    def __post_init__(self) -> None:
        R = np.asarray(self.R_body_cam, dtype=float)
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0):
            raise ValueError(
                f"R_body_cam: expected a rotation matrix (orthonormal rows, determinant +1), got {self.R_body_cam}"
            )

    def rotation(self) -> np.ndarray:
        """R_body_cam, re-orthonormalised (YAML holds a few decimals)."""
        U, _, Vt = np.linalg.svd(np.asarray(self.R_body_cam, dtype=float))
        return U @ Vt


@dataclass(frozen=True)
class OutputOptions:
    """What goes to the flight controller."""

    max_rate_hz: float = bounded(
        30.0, "most VISION_POSITION_ESTIMATEs per second (ArduPilot ignores faster than 50 Hz)", gt=0, le=50
    )
    speed_estimate: bool = bounded(True, "also send VISION_SPEED_ESTIMATE")
    odometry: bool = bounded(
        False, "also send ODOMETRY (child BODY_FRD, body-frame velocity, quality; -1 once when vision fails)"
    )
    autopilot: Autopilot = bounded(
        "auto", "auto (from the flight controller's HEARTBEAT), ardupilot (ODOMETRY frame LOCAL_FRD) or px4 (LOCAL_NED)"
    )
    estimator_type: Literal["vision", "vio"] = bounded("vision", "ODOMETRY estimator_type: vision (2) or vio (3)")
    statustext_min_interval_s: float = bounded(
        2.0,
        "at most one STATUSTEXT on state changes per this interval (merged: the latest state, and a worse one before it)",
        ge=0,
        le=60,
    )
    max_age_s: float = bounded(
        0.5,
        "an estimate the link could not send within this long of its exposure is dropped, never sent late",
        gt=0,
        le=5,
    )
    health_rate_hz: float = bounded(
        1.0,
        "NAMED_VALUE_FLOAT health values (VO_QUAL, VO_INLIER, VO_LAT_MS, VO_STATE, VO_DRIFT) per second",
        gt=0,
        le=5,
    )


@dataclass(frozen=True)
class ServiceOptions:
    """The daemon itself."""

    health_log_interval_s: float = bounded(5.0, "health counters in the log every this many seconds", gt=0, le=3600)
    shutdown_drain_s: float = bounded(
        2.0, "on stop, wait at most this long for the current frame and the queued messages", gt=0, le=60
    )
    state_file: str = bounded(
        "/var/lib/mavvo/state.json",
        "where the last reset_counter is kept, so a restarted service starts with one the flight controller has not seen (empty: derived from the clock)",
    )
    heading_wait_max_s: float = bounded(
        30.0,
        "wait at most this long for the flight controller's yaw to settle before the first estimate (0: do not wait)",
        ge=0,
        le=600,
    )
    track_ahead: bool = bounded(
        True,
        "track the next frame on a second thread while the current one is estimated, when frames queue up (the same estimates; faster on two or more cores)",
    )


@dataclass(frozen=True)
class ServiceConfig:
    """Everything ``mavvo run`` reads from its configuration file."""

    camera: CameraOptions = field(default_factory=CameraOptions)
    mounting: MountingOptions = field(default_factory=MountingOptions)
    link: LinkOptions = field(default_factory=LinkOptions)
    timing: TimingOptions = field(default_factory=TimingOptions)
    output: OutputOptions = field(default_factory=OutputOptions)
    service: ServiceOptions = field(default_factory=ServiceOptions)
    odometry: OdometryOptions = field(default_factory=OdometryOptions)
    record: RecordOptions = field(default_factory=RecordOptions)


def parse_config(data: Any, source: str) -> ServiceConfig:
    """A ServiceConfig from a parsed YAML mapping; ConfigError naming ``source`` and the key path."""
    cfg = build(ServiceConfig, data, source)
    try:
        parse_url(cfg.link.url)
        check_across_keys(cfg)
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from e
    return cfg


# A pinhole camera's horizontal field of view outside this is a typo in fx_px, not a lens.
_PINHOLE_FOV_DEG = (5.0, 170.0)


def check_across_keys(cfg: ServiceConfig) -> None:
    """Mistakes no single key shows: ConfigError naming the keys and what to set."""
    link, cam, timing = cfg.link, cfg.camera, cfg.timing
    if link.attitude_rate_hz < cam.rate_hz:
        raise ConfigError(
            f"link.attitude_rate_hz ({link.attitude_rate_hz:g}) is below camera.rate_hz ({cam.rate_hz:g}): frames would go "
            f"unpaired; set link.attitude_rate_hz to at least {cam.rate_hz:g} (100 brackets every exposure closely)"
        )
    period_s = 1.0 / link.attitude_rate_hz
    if timing.max_attitude_gap_s < period_s:
        raise ConfigError(
            f"timing.max_attitude_gap_s ({timing.max_attitude_gap_s:g}) is shorter than the ATTITUDE period ({period_s:g} s at "
            f"link.attitude_rate_hz {link.attitude_rate_hz:g}): no frame would pair; set it to at least {period_s:g}"
        )
    if cam.model == "pinhole":
        fov = math.degrees(2.0 * math.atan(cam.width_px / (2.0 * cam.fx_px)))
        lo, hi = _PINHOLE_FOV_DEG
        if not lo <= fov <= hi:
            raise ConfigError(
                f"camera.fx_px ({cam.fx_px:g}) gives a {fov:.1f} deg horizontal field of view on a {cam.width_px} px wide image: "
                f"expected {lo:g} to {hi:g} deg (fx_px is in pixels of this image size)"
            )


def load_config(path: str | Path) -> ServiceConfig:
    """Read and check a configuration file."""
    return parse_config(load_yaml(path), str(path))


def _yaml_value(v: Any) -> str:
    if isinstance(v, tuple):
        return "[" + ", ".join(_yaml_value(x) for x in v) + "]"
    return json.dumps(v)  # JSON scalars are YAML scalars; repr-exact for floats


def config_yaml(config: ServiceConfig | None = None, header: tuple[str, ...] = ()) -> str:
    """Every key of ``config`` (default: the defaults) with its value and help, as a YAML file that
    :func:`load_config` reads back to an equal config."""
    lines = list(header)

    def section(obj: Any, indent: int) -> None:
        pad = "  " * indent
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                doc = (type(value).__doc__ or "").strip().splitlines()[0]
                lines.append(f"{pad}{f.name}:  # {doc}")
                section(value, indent + 1)
            else:
                lines.append(f"{pad}{f.name}: {_yaml_value(value)}  # {f.metadata.get('help', '')}")

    config = config or ServiceConfig()
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        lines += ["", f"{f.name}:  # {(type(value).__doc__ or '').strip().splitlines()[0]}"]
        section(value, 1)
    return "\n".join(lines) + "\n"


def default_yaml() -> str:
    """Every key of :class:`ServiceConfig` with its default and help: ``config/default.yaml``."""
    return config_yaml(
        header=(
            "# mavvo configuration: every key, its default and what it means. Units are in the key names",
            "# (_px pixels, _m metres, _s seconds, _ms milliseconds, _hz per second, _deg degrees).",
            "# Any key may be left out and takes the default shown. Check a file with: mavvo check-config FILE",
            "# (this file is written by mavvo.service.settings.default_yaml; a test keeps it current).",
        )
    )
