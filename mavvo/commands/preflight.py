"""``mavvo preflight``: will the flight controller use mavvo's output? Its parameters, EKF origin and
delay, read over MAVLink and checked (:mod:`mavvo.service.preflight`); ``--fix`` writes the safe ones."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from mavvo.errors import ConfigError, LinkError, MavvoError
from mavvo.service.link_options import parse_url
from mavvo.service.mavlink import mavutil
from mavvo.service.preflight import blocks_flight, checks, params_to_read, table
from mavvo.service.settings import ServiceConfig, load_config

_COMPONENT = 191  # MAV_COMP_ID_ONBOARD_COMPUTER: not mavvo's 197, so it may run beside the service
_TRIES = 3
_AUTOPILOTS = {3: "ardupilot", 12: "px4"}


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "preflight",
        help="check the flight controller's parameters for vision (and fix the safe ones)",
        description="Connect to the flight controller like the service does, identify ArduPilot or PX4, read the parameters "
        "that decide whether it uses vision (and the EKF origin, and mavvo's measured latency if the service's messages are "
        "heard), and print what to set. Exit 0 only when nothing blocks flight. --fix writes the safe ones, confirmed by "
        "reading them back, never while the vehicle is armed.",
    )
    p.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="FILE",
        help="the service's settings (link.url, mounting.lever_arm_m); default: built-in",
    )
    p.add_argument(
        "--mavlink",
        default=None,
        metavar="URL",
        help="connect here instead of link.url (a ground station's port works too)",
    )
    p.add_argument(
        "--latency-ms",
        type=float,
        default=None,
        metavar="MS",
        help="the delay mavvo's health log advises, when its messages are not heard here",
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="wait this long for the flight controller's HEARTBEAT (default 10)",
    )
    p.add_argument("--fix", action="store_true", help="write the parameters marked 'set', then check again")
    p.set_defaults(handler=main)


class _Session:
    """The MAVLink exchange with one flight controller."""

    def __init__(self, url: str, timeout_s: float, fc_system_id: int) -> None:
        device, baud = parse_url(url)
        kw: dict[str, Any] = {"source_system": 255, "source_component": _COMPONENT}
        if baud is not None:
            kw["baud"] = baud
        try:
            self.conn = mavutil().mavlink_connection(device, **kw)
        except (OSError, ValueError) as e:
            raise LinkError(f"{url}: cannot open: {getattr(e, 'strerror', None) or e}") from e
        self.mav = mavutil().mavlink
        self.latency_ms: float | None = None
        self.url = url
        deadline = time.monotonic() + timeout_s
        next_beat = 0.0
        while True:
            if time.monotonic() >= next_beat:  # so that a flight controller listening on UDP learns where we are
                self.conn.mav.heartbeat_send(
                    self.mav.MAV_TYPE_ONBOARD_CONTROLLER, self.mav.MAV_AUTOPILOT_INVALID, 0, 0, 0
                )
                next_beat = time.monotonic() + 1.0
            msg = self._recv(0.2)
            if (
                msg is not None
                and msg.get_type() == "HEARTBEAT"
                and msg.autopilot != self.mav.MAV_AUTOPILOT_INVALID
                and fc_system_id in (0, msg.get_srcSystem())
            ):
                break
            if time.monotonic() > deadline:
                self.conn.close()
                raise LinkError(
                    f"{url}: no flight controller HEARTBEAT in {timeout_s:g} s (check the URL, the baud rate, SERIALn_PROTOCOL)"
                )
        self.target = (msg.get_srcSystem(), msg.get_srcComponent())
        self.autopilot = _AUTOPILOTS.get(msg.autopilot)
        if self.autopilot is None:
            raise LinkError(f"{url}: autopilot type {msg.autopilot} is neither ArduPilot (3) nor PX4 (12)")
        self.armed = bool(msg.base_mode & self.mav.MAV_MODE_FLAG_SAFETY_ARMED)

    def _recv(self, timeout_s: float) -> Any:
        msg = self.conn.recv_match(blocking=True, timeout=timeout_s)
        if msg is not None and msg.get_type() == "NAMED_VALUE_FLOAT" and msg.get_srcComponent() == 197:
            name = msg.name.decode() if isinstance(msg.name, bytes) else msg.name
            if name.rstrip("\x00") == "VO_LAT_MS" and msg.value == msg.value:
                self.latency_ms = float(msg.value)
        return msg

    def read_params(self, names: tuple[str, ...]) -> dict[str, float]:
        """The named parameters; one the flight controller does not have is absent."""
        got: dict[str, float] = {}
        for _ in range(_TRIES):
            missing = [n for n in names if n not in got]
            if not missing:
                break
            for n in missing:
                self.conn.mav.param_request_read_send(*self.target, n.encode(), -1)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline and any(n not in got for n in missing):
                msg = self._recv(0.1)
                if msg is not None and msg.get_type() == "PARAM_VALUE":
                    pid = msg.param_id.decode() if isinstance(msg.param_id, bytes) else msg.param_id
                    got[pid.rstrip("\x00")] = float(msg.param_value)
        return got

    def has_origin(self) -> bool:
        """Whether the EKF has an origin: GPS_GLOBAL_ORIGIN answers MAV_CMD_REQUEST_MESSAGE."""
        m = self.mav
        for _ in range(_TRIES):
            self.conn.mav.command_long_send(
                *self.target, m.MAV_CMD_REQUEST_MESSAGE, 0, m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0
            )
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                msg = self._recv(0.1)
                if msg is not None and msg.get_type() == "GPS_GLOBAL_ORIGIN":
                    return True
        return False

    def ekf_flags(self) -> int | None:
        """ArduPilot's EKF_STATUS_REPORT flags, asked for with MAV_CMD_REQUEST_MESSAGE; None if none came."""
        m = self.mav
        self.conn.mav.command_long_send(
            *self.target, m.MAV_CMD_REQUEST_MESSAGE, 0, m.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 0, 0, 0, 0, 0, 0
        )
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            msg = self._recv(0.1)
            if msg is not None and msg.get_type() == "EKF_STATUS_REPORT":
                return int(msg.flags)
        return None

    def set_param(self, name: str, value: float) -> bool:
        """PARAM_SET, confirmed by the PARAM_VALUE that comes back."""
        for _ in range(_TRIES):
            self.conn.mav.param_set_send(*self.target, name.encode(), float(value), self.mav.MAV_PARAM_TYPE_REAL32)
            if abs(self.read_params((name,)).get(name, float("nan")) - value) < 1e-6:
                return True
        return False

    def close(self) -> None:
        self.conn.close()


def main(args: argparse.Namespace) -> int:
    config = load_config(args.config) if args.config is not None else ServiceConfig()
    url = args.mavlink or config.link.url
    if not args.timeout > 0:
        raise ConfigError(f"--timeout: expected a positive number of seconds, got {args.timeout}")
    s = _Session(url, args.timeout, config.link.fc_system_id)
    try:
        print(
            f"flight controller: {s.autopilot}, system {s.target[0]} component {s.target[1]}, {'ARMED' if s.armed else 'disarmed'} ({url})"
        )
        params = s.read_params(params_to_read(s.autopilot))
        origin = s.has_origin() if s.autopilot == "ardupilot" else None
        ekf = s.ekf_flags() if s.autopilot == "ardupilot" else None
        advised = args.latency_ms if args.latency_ms is not None else s.latency_ms
        results = checks(s.autopilot, params, config, advised_delay_ms=advised, has_origin=origin, ekf_flags=ekf)
        print(table(results), end="")
        fixes = [c for c in results if c.set_to is not None]
        if args.fix and fixes:
            if s.armed:
                raise MavvoError(
                    "the vehicle is armed: preflight --fix writes no parameter while armed; disarm and run it again"
                )
            for c in fixes:
                assert c.set_to is not None
                ok = s.set_param(c.name, c.set_to)
                print(f"set {c.name} = {c.set_to:g}: {'confirmed' if ok else 'NOT confirmed (read back differs)'}")
                if ok:
                    params[c.name] = c.set_to
            if any(c.name == "VISO_TYPE" for c in fixes):
                print("VISO_TYPE takes effect after the flight controller reboots")
            results = checks(s.autopilot, params, config, advised_delay_ms=advised, has_origin=origin, ekf_flags=ekf)
            print(table(results), end="")
        elif fixes:
            print(f"mavvo preflight --fix would set: {', '.join(f'{c.name} = {c.set_to:g}' for c in fixes)}")
    finally:
        s.close()
    blocked = blocks_flight(results)
    print(
        "preflight: " + ("BLOCKED: vision would not be used as it should" if blocked else "ok: nothing blocks flight"),
        file=sys.stderr,
    )
    return 1 if blocked else 0
