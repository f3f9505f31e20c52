"""The ``link:`` settings: the MAVLink connection string (checked without opening it), the signing key
file, the stream rates and the time-outs, each documented beside its default."""

from __future__ import annotations

import hashlib
import socket
import stat
from dataclasses import dataclass
from pathlib import Path

from mavvo.errors import ConfigError, LinkError
from mavvo.options import bounded
from mavvo.service.mavlink import SOCKET_SCHEMES

__all__ = ["LinkOptions", "check_udp_port_free", "parse_url", "read_signing_key"]


@dataclass(frozen=True)
class LinkOptions:
    """The MAVLink connection."""

    url: str = bounded(
        "/dev/ttyAMA0:921600", "serial DEVICE:BAUD, udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or tcpin:HOST:PORT"
    )
    fc_system_id: int = bounded(
        0,
        "the flight controller's MAVLink system id (0: the first autopilot that sends HEARTBEAT and ATTITUDE consistently for fc_confirm_s); mavvo uses the same",
        ge=0,
        le=255,
    )
    fc_confirm_s: float = bounded(
        1.0,
        "without fc_system_id: an autopilot is followed once its HEARTBEAT and ATTITUDE have come for this long; another one after that is reported, not followed",
        gt=0,
        le=60,
    )
    attitude_rate_hz: float = bounded(
        100.0,
        "ATTITUDE rate to request (at least the camera rate; 100 Hz brackets every exposure closely)",
        gt=0,
        le=1000,
    )
    range_rate_hz: float = bounded(
        50.0,
        "DISTANCE_SENSOR rate to request: a frame takes the reading nearest its exposure, so a slow stream costs the climb rate times up to half its period in height and scale (20 Hz at 1.5 m/s: up to 4 cm)",
        gt=0,
        le=1000,
    )
    height_rate_hz: float = bounded(10.0, "GLOBAL_POSITION_INT (height above home) rate to request", gt=0, le=1000)
    local_position_rate_hz: float = bounded(
        10.0,
        "LOCAL_POSITION_NED (the flight controller's own position, where re-initialised tracking is anchored) rate to request",
        gt=0,
        le=1000,
    )
    ekf_status_rate_hz: float = bounded(
        2.0,
        "EKF_STATUS_REPORT rate to request (the autopilot's word that its yaw is aligned: the first estimate need not wait for the yaw to stop moving)",
        gt=0,
        le=100,
    )
    request_retry_s: float = bounded(
        2.0, "first retry of a stream request that brought nothing; doubles up to 30 s", gt=0, le=30
    )
    timesync_interval_s: float = bounded(1.0, "TIMESYNC request period", gt=0, le=60)
    silence_timeout_s: float = bounded(3.0, "nothing heard for this long: reconnect", gt=0, le=600)
    reconnect_max_s: float = bounded(8.0, "longest back-off between reconnection attempts", gt=0, le=600)
    signing_key_file: str = bounded(
        "",
        "MAVLink 2 signing key: 64 hex digits, 32 raw bytes or a passphrase (SHA-256); mode 0600 or stricter; keep it at /var/lib/mavvo/signing.key (the unit's 0700 state directory); empty: unsigned",
    )


def parse_url(url: str) -> tuple[str, int | None]:
    """(pymavlink device string, serial baud rate or None) for a connection string; ConfigError when
    it is none of the supported forms."""
    if url.startswith(SOCKET_SCHEMES):
        host, _, port = url.split(":", 1)[1].rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ConfigError(f"link.url: expected {url.split(':')[0]}:HOST:PORT with a port 1-65535, got {url!r}")
        return url, None
    dev = url.removeprefix("serial:")
    if dev.startswith("/dev/") or dev.startswith("/"):
        path, _, baud = dev.rpartition(":")
        if not path or not baud.isdigit() or int(baud) <= 0:
            raise ConfigError(
                f"link.url: expected a serial device with its baud rate, like /dev/ttyAMA0:921600, got {url!r}"
            )
        return path, int(baud)
    raise ConfigError(
        f"link.url: expected /dev/DEVICE:BAUD, udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or tcpin:HOST:PORT, got {url!r}"
    )


def read_signing_key(path: str | Path) -> bytes:
    """The 32-byte signing key in ``path``: 64 hex digits, 32 raw bytes, or a passphrase hashed with
    SHA-256 (as ground stations derive it). ConfigError if the file cannot be read or group or others may
    read or write it."""
    p = Path(path)
    try:
        st = p.stat()
        raw = p.read_bytes()
    except OSError as e:
        raise ConfigError(f"link.signing_key_file {p}: cannot read: {e.strerror or e}") from e
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(
            f"link.signing_key_file {p}: expected mode 0600 or stricter (owner only), got {stat.S_IMODE(st.st_mode):04o}; run chmod 600 {p}"
        )
    text = raw.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(raw) == 32:
        return raw
    if not text:
        raise ConfigError(f"link.signing_key_file {p}: expected a key, the file is empty")
    return hashlib.sha256(text).digest()


def check_udp_port_free(url: str) -> None:
    """For ``udpin:HOST:PORT``: LinkError when another socket holds the port. (pymavlink binds with
    SO_REUSEADDR, so two services on one port would both start and split the datagrams between them.)"""
    if not url.startswith("udpin:"):
        return
    host, _, port = url.split(":", 1)[1].rpartition(":")
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host, int(port)))
    except OSError as e:
        raise LinkError(
            f"link.url {url}: cannot listen on {host}:{port}: {e.strerror or e} (another process has the port?)"
        ) from e
    finally:
        probe.close()
