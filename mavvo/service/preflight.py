"""Whether the flight controller will use mavvo's output: its parameters, its EKF origin and the
service's latency against what it is set to (pure; ``mavvo preflight`` reads them over MAVLink).

Each :class:`Check` says the value, what is expected, a :class:`Verdict` (``block``: vision will not be
used or will be used wrongly; ``warn``: it will work worse; ``ok``), what to set, and the value
``--fix`` may write (None: the operator decides). The expectations are those of docs/service.md's
ArduPilot and PX4 sections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

from mavvo.service.settings import ServiceConfig
from mavvo.types import StrEnum

__all__ = ["Verdict", "Check", "params_to_read", "checks", "blocks_flight", "table"]

_DELAY_TOLERANCE_MS = 20.0
_LEVER_TOLERANCE_M = 0.02
_PX4_EV_HPOS = 1  # EKF2_EV_CTRL bit 0: horizontal position


class Verdict(StrEnum):
    OK = "ok"
    WARN = "warn"
    BLOCK = "block"


@dataclass(frozen=True)
class Check:
    """One line of the preflight table."""

    name: str
    value: str
    expected: str
    verdict: Verdict
    advice: str = ""
    set_to: float | None = None  # what --fix writes to parameter ``name``; None: not fixed automatically


def params_to_read(autopilot: str) -> tuple[str, ...]:
    """The parameters the checks of ``autopilot`` (``ardupilot`` or ``px4``) read."""
    if autopilot == "px4":
        return ("EKF2_EV_CTRL", "EKF2_EV_DELAY", "EKF2_HGT_REF", "EKF2_EV_POS_X", "EKF2_EV_POS_Y", "EKF2_EV_POS_Z")
    return (
        "AHRS_EKF_TYPE",
        "VISO_TYPE",
        "VISO_DELAY_MS",
        "VISO_POS_X",
        "VISO_POS_Y",
        "VISO_POS_Z",
        "EK3_SRC1_POSXY",
        "EK3_SRC1_VELXY",
        "EK3_SRC1_POSZ",
        "EK3_SRC1_YAW",
        "GPS1_TYPE",  # ArduPilot 4.6 on; GPS_TYPE before
        "GPS_TYPE",
    )


def _fmt(v: float | None) -> str:
    return "(missing)" if v is None else (f"{v:g}" if math.isfinite(v) else str(v))


def _equal(
    name: str, params: Mapping[str, float], want: float, advice: str, block: bool = True, fix: bool = True
) -> Check:
    v = params.get(name)
    ok = v is not None and abs(v - want) < 1e-6
    verdict = Verdict.OK if ok else (Verdict.BLOCK if block else Verdict.WARN)
    return Check(
        name, _fmt(v), f"{want:g}", verdict, "" if ok else advice, None if ok or not fix or v is None else want
    )


def _one_of(name: str, params: Mapping[str, float], allowed: Sequence[float], advice: str) -> Check:
    v = params.get(name)
    ok = v is not None and any(abs(v - a) < 1e-6 for a in allowed)
    return Check(
        name, _fmt(v), " or ".join(f"{a:g}" for a in allowed), Verdict.OK if ok else Verdict.WARN, "" if ok else advice
    )


def _lever(names: Sequence[str], params: Mapping[str, float], lever_m: Sequence[float]) -> list[Check]:
    out = []
    for name, want in zip(names, lever_m):
        v = params.get(name)
        ok = v is not None and abs(v - want) <= _LEVER_TOLERANCE_M
        out.append(
            Check(
                name,
                _fmt(v),
                f"{want:g} (mounting.lever_arm_m)",
                Verdict.OK if ok else Verdict.WARN,
                "" if ok else "the camera's lever arm: every yaw otherwise becomes a position error",
                None if ok or v is None else float(want),
            )
        )
    return out


_MIN_PLAUSIBLE_DELAY_MS = 5.0  # below this no camera pipeline delivers: the parameter was never set


def _delay(name: str, params: Mapping[str, float], advised_ms: float | None) -> Check:
    v = params.get(name)
    if advised_ms is None:
        # Nothing measured yet: a value can only be judged plausible. A camera's capture-to-send is
        # tens of milliseconds; 0 (the default) has the EKF fuse each estimate as if taken on arrival.
        plausible = v is not None and v >= _MIN_PLAUSIBLE_DELAY_MS
        return Check(
            name,
            _fmt(v),
            "the latency mavvo measures",
            Verdict.OK if plausible else Verdict.WARN,
            "run the service and preflight again to compare with its measured latency"
            if plausible
            else "missing"
            if v is None
            else f"{_fmt(v)} ms has the EKF fuse each estimate as if taken when it arrives; run mavvo and set "
            "what its health line prints (capture-to-send is tens of ms)",
        )
    ok = v is not None and abs(v - advised_ms) <= _DELAY_TOLERANCE_MS
    return Check(
        name,
        _fmt(v),
        f"{advised_ms:.0f} +- {_DELAY_TOLERANCE_MS:.0f} (measured)",
        Verdict.OK if ok else Verdict.WARN,
        "" if ok else "the EKF fuses each sample at the wrong moment",
        None if ok or v is None else float(round(advised_ms)),
    )


_EK3_SRC_GPS = 3  # EK3_SRC1_VELXY: GPS
_EK3_YAW_GPS = (2, 3)  # EK3_SRC1_YAW: GPS, GPS with compass fallback
_EK3_YAW_COMPASS, _EK3_SRC_EXTNAV = 1, 6


def _has_gps(params: Mapping[str, float]) -> bool | None:
    """Whether a GPS is configured (GPS1_TYPE, or GPS_TYPE before ArduPilot 4.6, not 0); None: not read."""
    v = params.get("GPS1_TYPE", params.get("GPS_TYPE"))
    return None if v is None else v != 0


def _yaw_source(params: Mapping[str, float], config: ServiceConfig, has_gps: bool | None) -> Check:
    """EK3_SRC1_YAW against mavvo's heading policy: with ``odometry.heading_source`` vision mavvo never
    follows the flight controller's yaw, so the EKF takes mavvo's (6); otherwise the compass (1) or 6.
    A GPS yaw on a vehicle with no GPS leaves the EKF without a heading: BLOCK."""
    v = params.get("EK3_SRC1_YAW")
    vision = config.odometry.heading_source == "vision"
    allowed = (_EK3_SRC_EXTNAV,) if vision else (_EK3_YAW_COMPASS, _EK3_SRC_EXTNAV)
    want = _EK3_SRC_EXTNAV if vision else _EK3_YAW_COMPASS
    ok = v is not None and any(abs(v - a) < 1e-6 for a in allowed)
    gps_without_gps = v is not None and has_gps is False and int(v) in _EK3_YAW_GPS
    expected = " or ".join(f"{a:g}" for a in allowed) + f" (odometry.heading_source {config.odometry.heading_source})"
    if ok:
        return Check("EK3_SRC1_YAW", _fmt(v), expected, Verdict.OK)
    advice = (
        "a GPS yaw on a vehicle with no GPS: the EKF has no heading"
        if gps_without_gps
        else "1 (compass; mavvo takes north from it on the ground) or 6 (ExternalNav: mavvo's heading)"
    )
    return Check(
        "EK3_SRC1_YAW",
        _fmt(v),
        expected,
        Verdict.BLOCK if gps_without_gps else Verdict.WARN,
        advice,
        None if v is None else float(want),
    )


def _velocity_source(params: Mapping[str, float], has_gps: bool | None) -> Check:
    """EK3_SRC1_VELXY: 6 (ExternalNav) or 0; GPS (3) on a vehicle with no GPS is a BLOCK (fixed to 6)."""
    v = params.get("EK3_SRC1_VELXY")
    if v is not None and has_gps is False and int(v) == _EK3_SRC_GPS:
        return Check(
            "EK3_SRC1_VELXY",
            _fmt(v),
            "6 or 0",
            Verdict.BLOCK,
            "a GPS velocity on a vehicle with no GPS: the EKF waits for it",
            float(_EK3_SRC_EXTNAV),
        )
    return _one_of("EK3_SRC1_VELXY", params, (6, 0), "6 (ExternalNav) or 0")


_EKF_POS_HORIZ_REL = 0x8  # EKF_STATUS_REPORT flags (ArduPilot)
_EKF_CONST_POS_MODE = 0x80


def checks(
    autopilot: str,
    params: Mapping[str, float],
    config: ServiceConfig,
    *,
    advised_delay_ms: float | None = None,
    has_origin: bool | None = None,
    ekf_flags: int | None = None,
) -> list[Check]:
    """The checks for ``autopilot`` (``ardupilot`` or ``px4``) on the ``params`` read (a missing one is
    absent), the service's ``config``, the delay its latency advises (None: not running), whether the
    EKF has an origin (None: not asked) and its EKF_STATUS_REPORT flags (None: not heard)."""
    lever = config.mounting.lever_arm_m
    out: list[Check] = []
    if autopilot == "px4":
        v = params.get("EKF2_EV_CTRL")
        hpos = v is not None and int(v) & _PX4_EV_HPOS
        out.append(
            Check(
                "EKF2_EV_CTRL",
                _fmt(v),
                "bit 0 set (horizontal position; 1 vertical, 2 velocity, 3 yaw as wanted)",
                Verdict.OK if hpos else Verdict.BLOCK,
                "" if hpos else "EKF2 ignores vision positions",
                None if hpos or v is None else float(int(v) | _PX4_EV_HPOS),
            )
        )
        out.append(_delay("EKF2_EV_DELAY", params, advised_delay_ms))
        out.append(
            _one_of(
                "EKF2_HGT_REF",
                params,
                (1, 2, 3),
                "the height source: 1 baro, 2 GNSS, 3 range; 4 vision only with vision Z",
            )
        )
        out += _lever(("EKF2_EV_POS_X", "EKF2_EV_POS_Y", "EKF2_EV_POS_Z"), params, lever)
        return out
    out.append(_equal("AHRS_EKF_TYPE", params, 3, "EKF3 fuses external navigation", fix=False))
    out.append(
        _equal(
            "VISO_TYPE", params, 1, "1 (MAVLink): without it VISION_POSITION_ESTIMATE is ignored; reboot after setting"
        )
    )
    out.append(_equal("EK3_SRC1_POSXY", params, 6, "6 (ExternalNav): the EKF takes horizontal position from vision"))
    has_gps = _has_gps(params)
    out.append(_velocity_source(params, has_gps))
    out.append(_one_of("EK3_SRC1_POSZ", params, (1, 6), "1 (baro) or 6 (ExternalNav)"))
    out.append(_yaw_source(params, config, has_gps))
    out.append(_delay("VISO_DELAY_MS", params, advised_delay_ms))
    out += _lever(("VISO_POS_X", "VISO_POS_Y", "VISO_POS_Z"), params, lever)
    if ekf_flags is not None:
        pos = bool(ekf_flags & _EKF_POS_HORIZ_REL) and not ekf_flags & _EKF_CONST_POS_MODE
        out.append(
            Check(
                "EKF status",
                f"flags 0x{ekf_flags:04x}",
                "horizontal position, not constant-position mode",
                Verdict.OK if pos else Verdict.WARN,
                ""
                if pos
                else "the EKF has no horizontal position yet: is vision fused (the service running, the sources above)?",
            )
        )
    if has_origin is not None:
        out.append(
            Check(
                "EKF origin",
                "set" if has_origin else "none",
                "set",
                Verdict.OK if has_origin else Verdict.BLOCK,
                "" if has_origin else "set one before arming (SET_GPS_GLOBAL_ORIGIN; Mission Planner: Set EKF Origin)",
            )
        )
    return out


def blocks_flight(results: Sequence[Check]) -> bool:
    return any(c.verdict is Verdict.BLOCK for c in results)


def table(results: Sequence[Check]) -> str:
    """The checks as an aligned text table: parameter, value, expected, verdict, what to set."""
    rows = [("parameter", "value", "expected", "verdict", "what to do")] + [
        (
            c.name,
            c.value,
            c.expected,
            c.verdict.value.upper() if c.verdict is not Verdict.OK else "ok",
            (f"set {c.set_to:g}: " if c.set_to is not None else "") + c.advice,
        )
        for c in results
    ]
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    return "\n".join("  ".join(r[i].ljust(widths[i]) for i in range(4)) + "  " + r[4] for r in rows) + "\n"
