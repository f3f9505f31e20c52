"""Flight-controller logs as time series, and the way back to MAVLink messages for a replay:

- MAVLink telemetry ``.tlog``: ATTITUDE, DISTANCE_SENSOR (downward), GLOBAL_POSITION_INT (height),
  LOCAL_POSITION_NED, CAMERA_FEEDBACK / CAMERA_TRIGGER (shutter times);
- ArduPilot dataflash, binary ``.bin`` or text ``.log``, of any firmware age: ATT, else AHR2, else NKF1;
  RFND, BARO, XKF1, CAM; time from TimeUS, TimeMS or the reader's clock;
- PX4 ``.ulg`` (read with pyulog, PX4's own reader): vehicle_attitude (q), distance_sensor (downward),
  vehicle_local_position (position, height), vehicle_air_data (barometric height, when there is no
  local height), camera_capture / camera_trigger.

Times are the flight controller's boot clock in seconds (``time_boot_ms``, ``TimeUS``, ULog
``timestamp``). Angles are radians (dataflash logs degrees, ULog quaternions; converted here), heights
metres up, positions NED metres. A log that ends inside a record keeps what came before and says so in
``problems``; what a reader prints about damage is kept off the terminal and summarised there in one
line.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from mavvo.errors import ConfigError
from mavvo.service.mavlink import dfreader, mavutil
from mavvo.service.tlog import read_tlog

__all__ = ["FcSeries", "read_fc_log", "series_messages"]

log = logging.getLogger(__name__)


@dataclass
class FcSeries:
    """What a flight controller logged, on its boot clock (see the module docstring)."""

    path: str
    kind: str  # tlog, dataflash, ulog (or euroc, for a dataset made into a series)
    attitude: np.ndarray  # (N,4): t_fc_s, roll_rad, pitch_rad, yaw_rad
    range_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (M,2): t_fc_s, downward range
    height_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (K,2): t_fc_s, height above home, up
    local_ned_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (L,4): t_fc_s, north, east, down
    problems: list[str] = field(default_factory=list)
    triggers_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,): camera shutter times the log holds
    sources: dict[str, str] = field(
        default_factory=dict
    )  # what each series was read from: attitude, range, height, position, triggers


def _array(rows: list[tuple[float, ...]], width: int) -> np.ndarray:
    a = np.array(rows, dtype=float).reshape(-1, width)
    if len(a):
        a = a[np.argsort(a[:, 0], kind="stable")]
        a = a[np.concatenate([[True], np.diff(a[:, 0]) > 0])]  # repeated stamps: keep the first
    return a


def read_fc_log(path: str | Path) -> FcSeries:
    """A .tlog, a dataflash .bin/.log or a PX4 .ulg (by its extension); ConfigError if it cannot be read
    or holds no attitude."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: no such log file")
    suffix = p.suffix.lower()
    if suffix == ".tlog":
        s = _read_tlog(p)
    elif suffix in (".bin", ".log"):
        s = _read_dataflash(p)
    elif suffix == ".ulg":
        s = _read_ulog(p)
    else:
        raise ConfigError(
            f"{p}: expected a flight-controller log (.tlog, dataflash .bin or .log, PX4 .ulg), got a {p.suffix or 'file without extension'}"
        )
    if len(s.attitude) < 2:
        what = {"tlog": "ATTITUDE", "dataflash": "ATT, AHR2 or NKF1", "ulog": "vehicle_attitude"}[s.kind]
        raise ConfigError(f"{p}: no {what} messages in the log (found {len(s.attitude)}); roll and pitch are needed")
    return s


def _read_tlog(p: Path) -> FcSeries:
    mav = mavutil().mavlink.MAVLink(None)
    mav.robust_parsing = True
    att: list[tuple[float, ...]] = []
    rng: list[tuple[float, ...]] = []
    hgt: list[tuple[float, ...]] = []
    pos: list[tuple[float, ...]] = []
    trig: list[tuple[float, ...]] = []
    problems: list[str] = []
    fc: tuple[int, int] | None = None
    try:
        for _, frame in read_tlog(p):
            try:
                msg = mav.decode(bytearray(frame))
            except Exception:  # pymavlink raises its own and struct errors on a bad frame: skip it
                continue
            kind = msg.get_type()
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            if (
                kind == "HEARTBEAT" and fc is None and msg.autopilot != 8
            ):  # 8: MAV_AUTOPILOT_INVALID (not a flight controller)
                fc = src
            if fc is not None and src != fc:
                continue
            t = getattr(msg, "time_boot_ms", 0) * 1e-3
            if kind == "ATTITUDE":
                att.append((t, msg.roll, msg.pitch, msg.yaw))
            elif kind == "DISTANCE_SENSOR" and msg.orientation == 25:  # MAV_SENSOR_ROTATION_PITCH_270: down
                ok = msg.min_distance <= msg.current_distance <= msg.max_distance
                rng.append((t, msg.current_distance * 0.01 if ok else np.nan))
            elif kind == "GLOBAL_POSITION_INT":
                hgt.append((t, msg.relative_alt * 1e-3))
            elif kind == "LOCAL_POSITION_NED":
                pos.append((t, msg.x, msg.y, msg.z))
            elif kind in ("CAMERA_FEEDBACK", "CAMERA_TRIGGER"):
                trig.append((msg.time_usec * 1e-6 if kind == "CAMERA_TRIGGER" else t,))
    except ConfigError as e:
        problems.append(str(e))
    sources = {
        "attitude": "ATTITUDE",
        "range": "DISTANCE_SENSOR",
        "height": "GLOBAL_POSITION_INT.relative_alt",
        "position": "LOCAL_POSITION_NED",
        "triggers": "CAMERA_FEEDBACK/CAMERA_TRIGGER",
    }
    return FcSeries(
        str(p),
        "tlog",
        _array(att, 4),
        _array(rng, 2),
        _array(hgt, 2),
        _array(pos, 4),
        problems,
        _array(trig, 1)[:, 0],
        sources,
    )


# Roll/pitch/yaw in a dataflash log, by preference: the attitude the vehicle flew on, then the
# secondary AHRS, then the first EKF2 core (older firmware).
_DF_ATTITUDE = ("ATT", "AHR2", "NKF1")


@contextlib.contextmanager
def _captured_output() -> Iterator[list[str]]:
    """Everything printed meanwhile, by Python or by a C extension (pymavlink's dataflash indexer writes
    to the file descriptors), kept from the terminal; the lines land in the yielded list at the end."""
    lines: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), 1)
        os.dup2(sink.fileno(), 2)
        py = io.StringIO()
        try:
            with contextlib.redirect_stdout(py), contextlib.redirect_stderr(py):
                yield lines
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            text = sink.read().decode("utf-8", errors="replace") + py.getvalue()
            lines.extend(line for line in text.splitlines() if line.strip())


def _df_time_s(m: Any) -> float:
    """A dataflash record's boot time: ``TimeUS`` (current firmware), ``TimeMS`` (older), else the
    time pymavlink's reader gave it (from the GPS clock of logs without either)."""
    t_us = getattr(m, "TimeUS", None)
    if t_us is not None:
        return float(t_us) * 1e-6
    t_ms = getattr(m, "TimeMS", None)
    return float(t_ms) * 1e-3 if t_ms is not None else float(m._timestamp)


_TIME_COLUMNS = ("TimeUS", "TimeMS")


def _clock_types(reader: Any, p: Path) -> list[str]:
    """Where the log's attitude records carry no time of their own (ArduCopter 3.1's ATT has none), the
    types that do: read alongside, they move pymavlink's clock, which then stamps each attitude record
    with the time of the timed record before it. ConfigError when no record type in the log has a time."""
    formats = {f.name: f.columns for f in reader.formats.values()}
    untimed = [n for n in _DF_ATTITUDE if n in formats and not set(_TIME_COLUMNS) & set(formats[n])]
    if not untimed or any(n in formats and set(_TIME_COLUMNS) & set(formats[n]) for n in _DF_ATTITUDE):
        return []
    timed = sorted(n for n, cols in formats.items() if set(_TIME_COLUMNS) & set(cols))
    if not timed:
        raise ConfigError(
            f"{p}: the {', '.join(untimed)} records carry no time (their format has no TimeMS or TimeUS column) and no "
            "other record type in the log has one: the attitude cannot be placed in time"
        )
    return timed


def _read_dataflash(p: Path) -> FcSeries:
    """An ArduPilot dataflash log, binary (.bin) or text (.log, as the LogAnalyzer examples are), of
    any firmware age. pymavlink's reader prints every bad header it skips: that goes into ``problems``
    as one line, not onto the terminal."""
    DFReader = dfreader()
    with p.open("rb") as f:
        head = f.read(4)
    text = head.startswith(b"FMT") or (p.suffix.lower() == ".log" and head[:2] != b"\xa3\x95")
    att: dict[str, list[tuple[float, ...]]] = {k: [] for k in _DF_ATTITUDE}
    rng: list[tuple[float, ...]] = []
    hgt: list[tuple[float, ...]] = []
    pos: list[tuple[float, ...]] = []
    trig: list[tuple[float, ...]] = []
    problems: list[str] = []
    with _captured_output() as skipped:
        try:
            reader = (
                DFReader.DFReader_text(str(p), zero_time_base=True)
                if text
                else DFReader.DFReader_binary(str(p), zero_time_base=True)
            )
        except Exception as e:  # DFReader raises assorted errors on a file that is not a log
            log.debug("%s: pymavlink's DFReader: %r", p, e)  # the Python detail, for a developer's -v
            raise ConfigError(
                f"{p}: not a readable dataflash log ({'text' if text else 'binary'}): pymavlink's reader could not make "
                "sense of its format (FMT) records or of the times of its first records; a text log must begin with FMT lines"
            ) from e
        wanted = [*_DF_ATTITUDE, "RFND", "BARO", "XKF1", "CAM"]
        clocks = _clock_types(reader, p)
        wanted += clocks
        if clocks:
            problems.append(
                f"{p}: the attitude records carry no time of their own: each takes the time of the timed record "
                f"before it ({', '.join(clocks)})"
            )
        while True:
            try:
                m = reader.recv_match(type=wanted)
            except Exception as e:  # a corrupt record: keep what came before
                problems.append(f"{p}: unreadable record: {e}")
                break
            if m is None:
                break
            kind = m.get_type()
            try:
                t = _df_time_s(m)
                if kind in att and getattr(m, "C", 0) == 0:
                    att[kind].append((t, np.radians(m.Roll), np.radians(m.Pitch), np.radians(m.Yaw)))
                elif kind == "RFND" and getattr(m, "Orient", 25) == 25:
                    rng.append((t, m.Dist if getattr(m, "Stat", 4) == 4 else np.nan))  # Stat 4: good
                elif kind == "BARO" and getattr(m, "I", 0) == 0:
                    hgt.append((t, m.Alt))
                elif kind == "XKF1" and getattr(m, "C", 0) == 0:
                    pos.append((t, m.PN, m.PE, m.PD))
                elif kind == "CAM":
                    trig.append((t,))
            except (AttributeError, TypeError, ValueError):  # a record without the fields this vintage should have
                continue
    if skipped:
        problems.append(f"{p}: the reader skipped {len(skipped)} damaged places (first: {skipped[0][:80]})")
    if not text and reader.offset < reader.data_len:
        problems.append(
            f"{p}: truncated: {reader.data_len - reader.offset} bytes at the end are not a whole record (the log was cut off)"
        )
    source = next((k for k in _DF_ATTITUDE if len(att[k]) >= 2), _DF_ATTITUDE[0])
    if source != "ATT" and att[source]:
        problems.append(f"{p}: no ATT records; roll/pitch from {source}")
    sources = {"attitude": source, "range": "RFND", "height": "BARO.Alt", "position": "XKF1", "triggers": "CAM"}
    return FcSeries(
        str(p),
        "dataflash",
        _array(att[source], 4),
        _array(rng, 2),
        _array(hgt, 2),
        _array(pos, 4),
        problems,
        _array(trig, 1)[:, 0],
        sources,
    )


# ---------------------------------------------------------------------- PX4 ULog

_ULOG_TOPICS = [
    "vehicle_attitude",
    "distance_sensor",
    "vehicle_local_position",
    "vehicle_air_data",
    "camera_capture",
    "camera_trigger",
]
_PX4_DOWNWARD = 25  # distance_sensor.orientation ROTATION_DOWNWARD_FACING


def _read_ulog(p: Path) -> FcSeries:
    """A PX4 ULog through pyulog. Each topic's first instance (``multi_id`` 0); a sample's time is its
    ``timestamp_sample`` when the topic has one (when it was measured), else ``timestamp``."""
    from pyulog import ULog  # only for PX4 logs

    problems: list[str] = []
    with _captured_output() as printed:
        try:
            ulog = ULog(str(p), _ULOG_TOPICS)
        except Exception as e:  # pyulog raises its ULogException, struct and index errors on a file that is not a log
            log.debug("%s: pyulog: %r", p, e)  # the Python detail, for a developer's -v
            raise ConfigError(
                f"{p}: not a readable PX4 ULog (expected the 'ULog' header and the message definitions after it)"
            ) from e
    if printed or ulog.file_corruption:
        problems.append(
            f"{p}: damaged: pyulog skipped corrupt data ({len(printed)} messages; first: {(printed or ['-'])[0][:80]})"
        )
    topics = {d.name: d.data for d in ulog.data_list if d.multi_id == 0}

    def times(d: dict[str, np.ndarray]) -> np.ndarray:
        return np.asarray(d.get("timestamp_sample", d["timestamp"]), dtype=float) * 1e-6

    att = np.zeros((0, 4))
    if "vehicle_attitude" in topics:
        d = topics["vehicle_attitude"]
        w, x, y, z = (np.asarray(d[f"q[{i}]"], dtype=float) for i in range(4))
        # Euler 3-2-1 of the FRD-to-NED quaternion (Hamilton, w first), as ATTITUDE carries it.
        roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
        yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        ok = np.isfinite(roll) & np.isfinite(pitch)
        att = _array(list(zip(times(d)[ok], roll[ok], pitch[ok], yaw[ok])), 4)
    rng = np.zeros((0, 2))
    if "distance_sensor" in topics:
        d = topics["distance_sensor"]
        down = np.asarray(d.get("orientation", np.full(len(d["timestamp"]), _PX4_DOWNWARD))) == _PX4_DOWNWARD
        dist = np.asarray(d["current_distance"], dtype=float)
        valid = np.ones(len(dist), bool)
        if "min_distance" in d and "max_distance" in d:
            valid &= (dist >= d["min_distance"]) & (dist <= d["max_distance"])
        if "signal_quality" in d:
            valid &= np.asarray(d["signal_quality"]) != 0  # 0: invalid; -1: unknown
        rng = _array(list(zip(times(d)[down], np.where(valid, dist, np.nan)[down])), 2)
    hgt, pos = np.zeros((0, 2)), np.zeros((0, 4))
    height_source = ""
    if "vehicle_local_position" in topics:
        d = topics["vehicle_local_position"]
        t = times(d)
        z_ok = np.asarray(d.get("z_valid", np.ones(len(t))), bool)
        xy_ok = np.asarray(d.get("xy_valid", np.ones(len(t))), bool) & z_ok
        pos = _array(list(zip(t[xy_ok], d["x"][xy_ok], d["y"][xy_ok], d["z"][xy_ok])), 4)
        hgt = _array(list(zip(t[z_ok], -np.asarray(d["z"], dtype=float)[z_ok])), 2)
        height_source = "vehicle_local_position.z"
    if not len(hgt) and "vehicle_air_data" in topics:
        d = topics["vehicle_air_data"]
        alt = np.asarray(d["baro_alt_meter"], dtype=float)
        hgt = _array(list(zip(times(d), alt - alt[0])), 2)  # above where the log started
        height_source = "vehicle_air_data.baro_alt_meter"
    trig = np.zeros(0)
    for name in ("camera_capture", "camera_trigger"):
        if name in topics:
            trig = np.sort(times(topics[name]))
            break
    sources = {
        "attitude": "vehicle_attitude",
        "range": "distance_sensor",
        "height": height_source,
        "position": "vehicle_local_position",
        "triggers": "camera_capture/camera_trigger",
    }
    return FcSeries(str(p), "ulog", att, rng, hgt, pos, problems, trig, sources)


# ---------------------------------------------------------------------- back to MAVLink


def series_messages(s: FcSeries, *, heartbeat_hz: float = 1.0, boot_epoch_s: float = 0.0) -> list[tuple[int, bytes]]:
    """The log as the MAVLink 2 messages a flight controller (system 1, component 1) would have sent,
    each arriving on the host clock at its own time: ``(t_host_us, frame)`` in time order. The series'
    times are the host clock of the replay; ``time_boot_ms`` counts from ``boot_epoch_s`` (a dataset's
    Unix-time stamps do not fit its 32 bits). A HEARTBEAT opens the stream."""
    m = mavutil().mavlink
    mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
    events: list[tuple[int, int, Any]] = []  # (t_us, order, message)
    t0, t1 = s.attitude[0, 0], s.attitude[-1, 0]
    autopilot = m.MAV_AUTOPILOT_PX4 if s.kind == "ulog" else m.MAV_AUTOPILOT_ARDUPILOTMEGA
    for t in np.arange(t0, t1 + 1e-9, 1.0 / heartbeat_hz):
        events.append(
            (
                round(t * 1e6),
                0,
                m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, autopilot, 0, 0, m.MAV_STATE_ACTIVE, 3),
            )
        )
    nan = float("nan")  # the log has no body rates: NaN says "unknown" (zero would claim a vehicle that never turns)
    for t, r, pch, y in s.attitude:
        events.append(
            (
                round(t * 1e6),
                1,
                m.MAVLink_attitude_message(int(round((t - boot_epoch_s) * 1e3)), r, pch, y, nan, nan, nan),
            )
        )
    for t, d in s.range_m:
        cm = 4001 if not np.isfinite(d) else int(round(d * 100))
        events.append(
            (
                round(t * 1e6),
                2,
                m.MAVLink_distance_sensor_message(
                    int(round((t - boot_epoch_s) * 1e3)),
                    20,
                    4000,
                    cm,
                    m.MAV_DISTANCE_SENSOR_LASER,
                    0,
                    m.MAV_SENSOR_ROTATION_PITCH_270,
                    255,
                ),
            )
        )
    for t, h in s.height_m:
        events.append(
            (
                round(t * 1e6),
                3,
                m.MAVLink_global_position_int_message(
                    int(round((t - boot_epoch_s) * 1e3)), 0, 0, 0, int(round(h * 1e3)), 0, 0, 0, 65535
                ),
            )
        )
    events.sort(key=lambda e: (e[0], e[1]))
    return [(t_us, bytes(msg.pack(mav))) for t_us, _, msg in events]
