"""Flight-controller logs as time series: a .tlog (ATTITUDE, DISTANCE_SENSOR, GLOBAL_POSITION_INT,
LOCAL_POSITION_NED) or an ArduPilot dataflash log, binary .bin or text .log of any firmware age (ATT,
else AHR2, else NKF1; RFND, BARO, XKF1; TimeUS, TimeMS or the reader's clock), and the way back to
MAVLink messages for a replay.

Times are the flight controller's boot clock in seconds (``time_boot_ms`` / ``TimeUS``). Angles are
radians (dataflash logs degrees; converted here), heights metres up, positions NED metres.
A log that ends inside a record keeps what came before and says so in ``problems``.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from mavvo.errors import ConfigError
from mavvo.service.tlog import read_tlog
from mavvo.service.mavlink import dfreader, mavutil

__all__ = ["FcSeries", "read_fc_log", "write_dataflash", "series_messages"]


@dataclass
class FcSeries:
    """What a flight controller logged, on its boot clock (see the module docstring)."""

    path: str
    kind: str  # tlog or dataflash
    attitude: np.ndarray  # (N,4): t_fc_s, roll_rad, pitch_rad, yaw_rad
    range_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (M,2): t_fc_s, downward range
    height_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (K,2): t_fc_s, height above home, up
    local_ned_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (L,4): t_fc_s, north, east, down
    problems: list[str] = field(default_factory=list)


def _array(rows: list[tuple[float, ...]], width: int) -> np.ndarray:
    a = np.array(rows, dtype=float).reshape(-1, width)
    if len(a):
        a = a[np.argsort(a[:, 0], kind="stable")]
        a = a[np.concatenate([[True], np.diff(a[:, 0]) > 0])]  # repeated stamps: keep the first
    return a


def read_fc_log(path: str | Path) -> FcSeries:
    """A .tlog or a dataflash .bin (by its extension); ConfigError if it cannot be read or holds no
    attitude."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: no such log file")
    if p.suffix.lower() == ".tlog":
        s = _read_tlog(p)
    elif p.suffix.lower() in (".bin", ".log"):
        s = _read_dataflash(p)
    else:
        raise ConfigError(f"{p}: expected a .tlog or a dataflash .bin log, got a {p.suffix or 'file without extension'}")
    if len(s.attitude) < 2:
        what = "ATTITUDE" if s.kind == "tlog" else "ATT, AHR2 or NKF1"
        raise ConfigError(f"{p}: no {what} messages in the log (found {len(s.attitude)}); roll and pitch are needed")
    return s


def _read_tlog(p: Path) -> FcSeries:
    mav = mavutil().mavlink.MAVLink(None)
    mav.robust_parsing = True
    att: list[tuple[float, ...]] = []
    rng: list[tuple[float, ...]] = []
    hgt: list[tuple[float, ...]] = []
    pos: list[tuple[float, ...]] = []
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
            if kind == "HEARTBEAT" and fc is None and msg.autopilot != 8:  # 8: MAV_AUTOPILOT_INVALID (not a flight controller)
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
    except ConfigError as e:
        problems.append(str(e))
    return FcSeries(str(p), "tlog", _array(att, 4), _array(rng, 2), _array(hgt, 2), _array(pos, 4), problems)


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
    problems: list[str] = []
    with _captured_output() as skipped:
        try:
            reader = DFReader.DFReader_text(str(p), zero_time_base=True) if text else DFReader.DFReader_binary(str(p), zero_time_base=True)
        except Exception as e:  # DFReader raises assorted errors on a file that is not a log
            raise ConfigError(f"{p}: not a readable dataflash log ({'text' if text else 'binary'}): {' '.join(str(e).split())[:200]}") from e
        while True:
            try:
                m = reader.recv_match(type=[*_DF_ATTITUDE, "RFND", "BARO", "XKF1"])
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
            except (AttributeError, TypeError, ValueError):  # a record without the fields this vintage should have
                continue
    if skipped:
        problems.append(f"{p}: the reader skipped {len(skipped)} damaged places (first: {skipped[0][:80]})")
    if not text and reader.offset < reader.data_len:
        problems.append(f"{p}: truncated: {reader.data_len - reader.offset} bytes at the end are not a whole record (the log was cut off)")
    source = next((k for k in _DF_ATTITUDE if len(att[k]) >= 2), _DF_ATTITUDE[0])
    if source != "ATT" and att[source]:
        problems.append(f"{p}: no ATT records; roll/pitch from {source}")
    return FcSeries(str(p), "dataflash", _array(att[source], 4), _array(rng, 2), _array(hgt, 2), _array(pos, 4), problems)


# ---------------------------------------------------------------------- writing dataflash (test logs)

_FMT_ID = 128
_FMT_BODY = "BB4s16s64s"


def write_dataflash(path: str | Path, formats: dict[str, tuple[int, str, str]], records: Iterable[tuple[str, tuple[Any, ...]]]) -> Path:
    """A dataflash .bin: ``formats`` maps a name to (id, format characters, comma-separated columns),
    ``records`` are (name, values) in order. Formats use pymavlink's DFReader type characters."""
    FORMAT_TO_STRUCT = dfreader().FORMAT_TO_STRUCT

    p = Path(path)
    structs = {}
    scales = {}
    with p.open("wb") as f:
        fmt_struct = struct.Struct("<" + _FMT_BODY)
        f.write(bytes([0xA3, 0x95, _FMT_ID]) + fmt_struct.pack(_FMT_ID, 3 + fmt_struct.size, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns"))
        for name, (msg_id, chars, columns) in formats.items():
            st = struct.Struct("<" + "".join(FORMAT_TO_STRUCT[c][0] for c in chars))
            structs[name], scales[name] = (msg_id, st), [FORMAT_TO_STRUCT[c][1] for c in chars]
            f.write(bytes([0xA3, 0x95, _FMT_ID]) + fmt_struct.pack(msg_id, 3 + st.size, name.encode(), chars.encode(), columns.encode()))
        for name, values in records:
            msg_id, st = structs[name]
            packed = [v if s is None else int(round(v / s)) for v, s in zip(values, scales[name])]
            packed = [v.encode() if isinstance(v, str) else v for v in packed]
            f.write(bytes([0xA3, 0x95, msg_id]) + st.pack(*packed))
    return p


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
    for t in np.arange(t0, t1 + 1e-9, 1.0 / heartbeat_hz):
        events.append((round(t * 1e6), 0, m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, m.MAV_STATE_ACTIVE, 3)))
    nan = float("nan")  # the log has no body rates: NaN says "unknown" (zero would claim a vehicle that never turns)
    for t, r, pch, y in s.attitude:
        events.append((round(t * 1e6), 1, m.MAVLink_attitude_message(int(round((t - boot_epoch_s) * 1e3)), r, pch, y, nan, nan, nan)))
    for t, d in s.range_m:
        cm = 4001 if not np.isfinite(d) else int(round(d * 100))
        events.append((round(t * 1e6), 2, m.MAVLink_distance_sensor_message(int(round((t - boot_epoch_s) * 1e3)), 20, 4000, cm, m.MAV_DISTANCE_SENSOR_LASER, 0, m.MAV_SENSOR_ROTATION_PITCH_270, 255)))
    for t, h in s.height_m:
        events.append((round(t * 1e6), 3, m.MAVLink_global_position_int_message(int(round((t - boot_epoch_s) * 1e3)), 0, 0, 0, int(round(h * 1e3)), 0, 0, 0, 65535)))
    events.sort(key=lambda e: (e[0], e[1]))
    return [(t_us, bytes(msg.pack(mav))) for t_us, _, msg in events]
