"""The MAVLink link to the flight controller (pymavlink through :mod:`mavvo.service.mavlink`).

One thread (:meth:`Link.run`) owns the connection: it reads, hands the flight controller's state to a
:class:`LinkListener` (attitude, rangefinder, height, TIMESYNC answers, reboots), and writes what other
threads queued with :meth:`Link.send`. It also keeps the link alive:

- HEARTBEAT at 1 Hz as MAV_TYPE_ONBOARD_CONTROLLER / MAV_AUTOPILOT_INVALID, component 197
  (MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY), ``system_status`` from the service's health;
- ATTITUDE, DISTANCE_SENSOR and GLOBAL_POSITION_INT (height above home) requested with
  MAV_CMD_SET_MESSAGE_INTERVAL, and requested again (with back-off) until they arrive, whenever a
  stream goes quiet, and after a flight-controller reboot (``time_boot_ms`` going back);
- TIMESYNC requests every second; the flight controller's own TIMESYNC requests are answered with the
  host clock that stamps every estimate (what PX4 needs to map ``usec``);
- reconnect with back-off when the link dies: a read or write error (serial unplugged) or nothing heard
  for ``silence_timeout_s`` (UDP silent);
- optional MAVLink 2 signing with a key read from a file that only its owner may read; incoming
  signatures are checked before their timestamps count (:mod:`mavvo.service.signing`).

Connection strings: ``/dev/ttyAMA0:921600`` (serial through pyserial; ``serial:`` prefix optional),
``udpin:HOST:PORT`` (listen), ``udpout:HOST:PORT`` (send first), ``tcp:HOST:PORT`` (connect),
``tcpin:HOST:PORT`` (listen).
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import queue
import select
import socket
import stat
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol

from mavvo.errors import ConfigError, LinkError
from mavvo.options import bounded
from mavvo.service import signing
from mavvo.service.mavlink import SOCKET_SCHEMES, mavutil
from mavvo.service.timing import Clock
from mavvo.types import StrEnum

__all__ = [
    "LinkOptions",
    "LinkListener",
    "Link",
    "SystemStatus",
    "Tap",
    "parse_url",
    "read_signing_key",
    "stamp_us",
    "us_to_s",
]

log = logging.getLogger(__name__)


class SystemStatus(StrEnum):
    """HEARTBEAT ``system_status`` of the vision component. Never FLIGHT_TERMINATION: that tells the
    ground station the vehicle is terminating itself."""

    STANDBY = "standby"  #: no estimate yet
    ACTIVE = "active"  #: tracking
    CRITICAL = "critical"  #: degraded or failed


COMPONENT_ID = 197  # MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
_REBOOT_STEP_S = 1.0  # time_boot_ms going back by more than this is a reboot, not a reordered packet
_SEND_QUEUE = 128
_MAX_REQUEST_BACKOFF_S = 30.0
# A TIMESYNC answer is ours when its ts1 reads as a moment of our own clock at most this long ago: it
# then measures our clock whoever asked. (No dictionary of requests: a replayed answer must count as it
# did in flight, and pymavlink's TIMESYNC has no target fields to tell requesters apart.)
_TIMESYNC_MAX_RTT_S = 1.0
_TIMESYNC_PROMPT_S = 0.1  # a TIMESYNC request the clock asks for goes out at least this long after the last
_READ_BUDGET = 200  # messages read per loop turn at most: sending keeps its rate under any input flood
_WAIT_SLICE_S = 0.25  # long back-off waits are cut into slices, each a turn of the loop (see ``turns``)


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
    range_rate_hz: float = bounded(20.0, "DISTANCE_SENSOR rate to request", gt=0, le=1000)
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


class LinkListener(Protocol):
    """Receives the flight controller's state from the link thread (see :mod:`mavvo.service.timing`)."""

    def on_attitude(
        self,
        t_fc_ms: int,
        roll_rad: float,
        pitch_rad: float,
        yaw_rad: float,
        t_arrival_host_s: float | None = None,
        body_rates_rad_s: tuple[float, float, float] | None = None,
    ) -> None: ...
    def on_local_position(
        self,
        t_fc_ms: int,
        p_ned_m: tuple[float, float, float],
        v_ned_m_s: tuple[float, float, float],
        t_arrival_host_s: float | None = None,
    ) -> None: ...
    def on_range(self, t_fc_ms: int, range_m: float | None, t_arrival_host_s: float | None = None) -> None: ...
    def on_height(self, t_fc_ms: int, height_m: float, t_arrival_host_s: float | None = None) -> None: ...
    def on_timesync(self, t_sent_host_s: float, t_fc_s: float, t_arrival_host_s: float | None = None) -> None: ...
    def on_reboot(self) -> None: ...
    def on_armed(self, armed: bool, t_arrival_host_s: float | None = None) -> None: ...
    def on_ekf_status(
        self, attitude_good: bool, compass_ratio: float, t_arrival_host_s: float | None = None
    ) -> None: ...
    def wants_timesync(self) -> bool: ...


Tap = Callable[[int, bytes], None]
"""Sees every message the link reads or writes: (host clock in whole microseconds, the message's bytes;
mavvo's own are from component 197). It must not block: it runs on the link thread."""


def stamp_us(clock: Clock) -> int:
    """Now on ``clock`` in whole microseconds: the one arrival stamp a message gets. Whole microseconds
    (what a .tlog stores) so that a recorded flight replays with exactly the stamps it had."""
    return round(clock.now_s() * 1e6)


def us_to_s(t_us: int) -> float:
    """Microseconds to seconds, the one way both recording and replay convert."""
    return t_us / 1_000_000


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


@dataclass
class _Candidate:
    """An autopilot heard before one was chosen: (first HEARTBEAT, HEARTBEATs, ATTITUDEs, MAV_AUTOPILOT)."""

    first_heartbeat_s: float
    autopilot: int
    heartbeats: int = 1
    attitudes: int = 0


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


@dataclass
class _Stream:
    msg_id: int
    rate_hz: float
    last_rx_s: float = -math.inf
    next_request_s: float = -math.inf
    backoff_s: float = 0.0


class Link:
    """The connection thread (see the module docstring).

    Args:
        options: :class:`LinkOptions`.
        clock: the host clock (stamps TIMESYNC and latency; decides time-outs).
        listener: gets the flight controller's state.
        system_status: called once a second for the HEARTBEAT's ``system_status``.

    Counters (``counters``): ``rx`` messages, ``bad_data`` (corrupt bytes), ``sent``, ``send_dropped``
    (queue full), ``stale_dropped`` (older than their ``max_age_s`` when their turn came),
    ``handler_errors`` (a message that raised while handled: skipped), ``connects``, ``reconnects``,
    ``reboots``, ``stream_requests``, ``denied``. ``rx`` counts a message once the listener has absorbed
    it. ``turns`` counts the thread's loop turns (the daemon's watchdog watches it move).
    """

    def __init__(
        self,
        options: LinkOptions,
        clock: Clock,
        listener: LinkListener,
        system_status: Callable[[], SystemStatus] = lambda: SystemStatus.STANDBY,
        tap: Tap | None = None,
    ) -> None:
        self.options = options
        self.tap = tap
        self.clock = clock
        self.listener = listener
        self.system_status = system_status
        self.device, self.baud = parse_url(options.url)
        check_udp_port_free(options.url)
        self.signing_key = read_signing_key(options.signing_key_file) if options.signing_key_file else None
        self.counters: Counter[str] = Counter()
        self.fc_system_id: int | None = options.fc_system_id or None
        self.fc_component_id: int | None = None  # set once the flight controller is chosen
        self._candidates: dict[tuple[int, int], _Candidate] = {}
        self._others_told: set[tuple[int, int]] = set()
        self._datagram_from: Any = None  # the source address of the last UDP datagram read
        self._datagrams_read = 0
        # UDP datagrams read and done with (every message parsed from them handled, what they made due
        # written), whatever they held: a lockstep driver waits on it.
        self.datagrams_done = 0
        self._fc_address: Any = None  # the flight controller's UDP address, once chosen
        self.autopilot: int | None = None  # the flight controller's HEARTBEAT autopilot (MAV_AUTOPILOT)
        self.connected = threading.Event()
        self._mavutil = mavutil()  # MAVLink 2 checked here, whoever imported pymavlink first
        self._mav = self._mavutil.mavlink
        self._conn: Any = None
        self._queue: queue.Queue[tuple[str, dict[str, Any], float]] = queue.Queue(_SEND_QUEUE)
        self.turns = 0
        self._tick = threading.Event()
        self.tick_clock_s = -math.inf  # lockstep: the host clock at the last tick the link has finished
        self._wake_r, self._wake_w = os.pipe()
        self._closed = False  # the link has stopped: send() is a no-op (its pipe's descriptors may be reused)
        self._close_lock = threading.Lock()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._last_boot_ms: int | None = None
        mav = self._mav
        self._streams = [
            _Stream(mav.MAVLINK_MSG_ID_ATTITUDE, options.attitude_rate_hz),
            _Stream(mav.MAVLINK_MSG_ID_DISTANCE_SENSOR, options.range_rate_hz),
            _Stream(mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, options.height_rate_hz),
            _Stream(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, options.local_position_rate_hz),
            _Stream(mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT, options.ekf_status_rate_hz),
        ]
        self._status_map = {
            SystemStatus.STANDBY: mav.MAV_STATE_STANDBY,
            SystemStatus.ACTIVE: mav.MAV_STATE_ACTIVE,
            SystemStatus.CRITICAL: mav.MAV_STATE_CRITICAL,
        }

    # ------------------------------------------------------------------ other threads

    def send(self, name: str, fields: dict[str, Any], *, send_by_s: float = math.inf) -> None:
        """Queue message ``name`` (e.g. ``VISION_POSITION_ESTIMATE``) with its fields; thread-safe,
        never blocks (when the queue is full the oldest message is dropped and counted). A message not
        written by ``send_by_s`` (host clock) is dropped, never sent late (counted as ``stale_dropped``).
        After the link has stopped it does nothing (counted as ``sent_after_stop``)."""
        if self._closed:
            self.counters["sent_after_stop"] += 1
            return
        item = (name, fields, send_by_s)
        while True:
            try:
                self._queue.put_nowait(item)
                break
            except queue.Full:
                try:
                    self._queue.get_nowait()
                    self._queue.task_done()
                    self.counters["send_dropped"] += 1
                except queue.Empty:
                    pass
        self._wake()

    def tick(self) -> None:
        """Lockstep: the driver has moved the host clock. The link takes a turn at once and does what
        time has made due (heartbeat, TIMESYNC and stream requests, the silence check, the end of a
        reconnect back-off), then reports the clock it did it at in :attr:`tick_clock_s`. On a lockstep
        clock these happen only at ticks (and on the messages that make them due), so at the same
        simulated moments on every run; in real time the link keeps time itself and this only wakes it."""
        self._tick.set()
        self._wake()

    def _wake(self) -> None:
        with self._close_lock:  # never write to a descriptor the stop has closed (it may be another file's now)
            if self._closed:
                return
            try:
                os.write(self._wake_w, b"x")
            except BlockingIOError:
                pass  # the pipe is full: the link thread is already awake

    def sends_pending(self) -> int:
        """Messages queued by :meth:`send` and not yet written or dropped (thread-safe)."""
        return self._queue.unfinished_tasks

    def local_address(self) -> tuple[str, int] | None:
        """The local (host, port) of a UDP or TCP connection; None for serial or while disconnected."""
        port = getattr(self._conn, "port", None)
        if not isinstance(port, socket.socket):
            return None
        host, number = port.getsockname()[:2]
        return host, number

    # ------------------------------------------------------------------ the link thread

    def run(self, stop: threading.Event) -> None:
        """Connect, serve and reconnect until ``stop`` is set; then send what is queued and close."""
        backoff = 0.25
        try:
            while not stop.is_set():
                self.turns += 1
                if self._conn is None:
                    if not self._connect():
                        self._pause(stop, backoff)
                        backoff = min(backoff * 2, self.options.reconnect_max_s)
                        continue
                    backoff = 0.25
                try:
                    self._serve_once()
                except (OSError, LinkError) as e:  # serial unplugged, socket gone, silence
                    log.warning("link %s: %s; reconnecting", self.options.url, e)
                    self._disconnect()
                    self.counters["reconnects"] += 1
                    self._pause(stop, backoff)
                    backoff = min(backoff * 2, self.options.reconnect_max_s)
            self._drain()
        finally:
            self._disconnect()
            with self._close_lock:
                self._closed = True
                for fd in (self._wake_r, self._wake_w):
                    try:
                        os.close(fd)
                    except OSError:
                        pass

    def _pause(self, stop: threading.Event, seconds: float) -> None:
        """Wait ``seconds`` or until ``stop``, in slices that each count as a turn. Real time: on the
        monotonic clock. Lockstep: on the host clock, looked at on each tick; the tick that ends the
        pause is left to the turn after it (the reconnect's first)."""
        if not self.clock.realtime:
            end_s = self.clock.now_s() + seconds
            while not stop.is_set():
                if self._tick.is_set():
                    now = self.clock.now_s()
                    if now >= end_s:
                        return
                    self._tick.clear()
                    self.tick_clock_s = now
                select.select([self._wake_r], [], [], _WAIT_SLICE_S)
                self._drain_wake()
                self.turns += 1
            return
        end = time.monotonic() + seconds
        while not stop.is_set() and (left := end - time.monotonic()) > 0:
            stop.wait(min(left, _WAIT_SLICE_S))
            self.turns += 1

    def _drain_wake(self) -> None:
        try:
            while os.read(self._wake_r, 4096):
                pass
        except BlockingIOError:
            pass

    def _connect(self) -> bool:
        try:
            kw: dict[str, Any] = {"source_system": self.fc_system_id or 1, "source_component": COMPONENT_ID}
            if self.baud is not None:
                kw["baud"] = self.baud
            conn = self._mavutil.mavlink_connection(self.device, **kw)
            if self.options.url.startswith("udpout:"):
                # Connected: the kernel sends from the route's address (127.0.0.1 for a local flight
                # controller) and drops datagrams from any other sender.
                conn.port.connect((socket.gethostbyname(conn.destination_addr[0]), conn.destination_addr[1]))
            if self.options.url.startswith(("udpin:", "udpout:")):
                conn.recv = self._udp_reader(conn)
        except Exception as e:  # pyserial, socket and pymavlink raise many kinds; all mean "not now"
            self.counters["connect_failures"] += 1
            if self.counters["connect_failures"] in (1, 10) or self.counters["connect_failures"] % 100 == 0:
                log.warning("link %s: cannot connect: %s (retrying)", self.options.url, e)
            return False
        if self.signing_key is not None:
            conn.setup_signing(self.signing_key, sign_outgoing=True, link_id=0)
            signing.install(conn.mav, self.counters)  # the signature is checked before its timestamp counts
        self._conn = conn
        self.counters["connects"] += 1
        now = self.clock.now_s()
        self._last_rx_s = now
        self._next_heartbeat_s = now
        self._next_timesync_s = now
        for s in self._streams:
            s.last_rx_s, s.next_request_s, s.backoff_s = -math.inf, now, 0.0
        self.connected.set()
        log.info("link %s: connected", self.options.url)
        return True

    def _udp_reader(self, conn: Any) -> Callable[[int | None], bytes]:
        """pymavlink's UDP read, counting datagrams (:attr:`datagrams_done`) and keeping each one's
        sender, so that a ``udpin`` flight controller's address can be pinned once it is chosen
        (:meth:`_pin_udp`)."""

        def recv(n: int | None = None) -> bytes:
            try:
                data, addr = conn.port.recvfrom(65535)
            except (BlockingIOError, ConnectionRefusedError):
                return b""
            self._datagrams_read += 1
            self._datagram_from = addr
            if not self._fc_address:
                conn.clients.add(addr)  # pymavlink answers every sender until the flight controller is known
                conn.clients_last_alive[addr] = time.monotonic()
            return data

        return recv

    def _pin_udp(self) -> None:
        """``udpin``: from now on only the flight controller's address is read and written to."""
        if not self.options.url.startswith("udpin:") or self._datagram_from is None:
            return
        self._fc_address = self._datagram_from
        self._conn.port.connect(self._fc_address)
        self._conn.clients = {self._fc_address}
        self._conn.clients_last_alive = {self._fc_address: time.monotonic()}

    def _disconnect(self) -> None:
        self.connected.clear()
        self._fc_address = None
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # closing a dead port may raise anything; it is gone either way
                pass
            self._conn = None

    def _serve_once(self) -> None:
        """One turn: wait for bytes or queued messages (at most 20 ms), read, write, keep alive."""
        fd = getattr(self._conn, "fd", None)
        fds = [self._wake_r] + ([fd] if fd is not None else [])
        select.select(fds, [], [], 0.02)
        self._drain_wake()
        ticked = self._tick.is_set()
        if ticked:
            self._tick.clear()
        try:
            now = self._turn(timed=ticked or self.clock.realtime)
        except (OSError, LinkError):
            if ticked:
                self._tick.set()  # answered by the reconnect's back-off, once the port is closed
            raise
        if ticked:
            self.tick_clock_s = now

    def _turn(self, *, timed: bool) -> float:
        """Read, write, and with ``timed`` do what time has made due; returns the host clock it used."""
        for _ in range(_READ_BUDGET):
            msg = self._conn.recv_msg()
            if msg is None:
                break
            counted = self._handle(msg)
            # Requests (TIMESYNC, streams) go out on the message that made them due, not at the end of a
            # batch of reads: on a lockstep clock their stamps are then the same on every run.
            self._keep_alive(self.clock.now_s())
            if counted:
                self.counters["rx"] += 1
            self.datagrams_done = self._datagrams_read  # after what it made due is written
        self.datagrams_done = self._datagrams_read  # those that held no whole message too
        now = self.clock.now_s()
        self._flush()
        if timed:
            self._keep_alive(now)
            if now - self._last_rx_s > self.options.silence_timeout_s:
                raise LinkError(f"nothing heard for {now - self._last_rx_s:.1f} s")
        return now

    def _flush(self) -> None:
        now = self.clock.now_s()
        while True:
            try:
                name, fields, send_by_s = self._queue.get_nowait()
            except queue.Empty:
                return
            try:
                if now > send_by_s:
                    self.counters["stale_dropped"] += 1
                    continue
                self._write(name, fields)
            finally:
                self._queue.task_done()

    def _write(self, name: str, fields: dict[str, Any]) -> None:
        msg = getattr(self._conn.mav, f"{name.lower()}_encode")(**fields)
        self._conn.mav.send(msg)
        self.counters["sent"] += 1
        if self.tap is not None:
            self.tap(stamp_us(self.clock), bytes(msg.get_msgbuf()))

    def _drain(self) -> None:
        """Send what is still queued (the stop's bounded drain: one pass, no waiting)."""
        if self._conn is not None:
            try:
                self._flush()
            except OSError:
                pass

    def _keep_alive(self, now: float) -> None:
        mav = self._mav
        if now >= self._next_heartbeat_s:
            self._next_heartbeat_s = now + 1.0
            status = self._status_map[self.system_status()]
            self._write(
                "HEARTBEAT",
                {
                    "type": mav.MAV_TYPE_ONBOARD_CONTROLLER,
                    "autopilot": mav.MAV_AUTOPILOT_INVALID,
                    "base_mode": 0,
                    "custom_mode": 0,
                    "system_status": status,
                },
            )
        targets = (
            [(self.fc_system_id, self.fc_component_id)] if self.fc_component_id is not None else list(self._candidates)
        )
        if not targets:
            return  # requests go to a flight controller we have heard
        # Also soon after the clock has come to doubt the offset: an answer settles whether it stepped.
        prompt = now >= self._next_timesync_s - self.options.timesync_interval_s + _TIMESYNC_PROMPT_S
        if self.fc_component_id is not None and (
            now >= self._next_timesync_s or (prompt and self.listener.wants_timesync())
        ):
            self._next_timesync_s = now + self.options.timesync_interval_s
            self._write("TIMESYNC", {"tc1": 0, "ts1": stamp_us(self.clock) * 1000})  # whole microseconds, like arrivals
        for s in self._streams:
            quiet = now - s.last_rx_s > max(3.0 / s.rate_hz, self.options.request_retry_s)
            if quiet and now >= s.next_request_s:
                s.backoff_s = min(max(2 * s.backoff_s, self.options.request_retry_s), _MAX_REQUEST_BACKOFF_S)
                s.next_request_s = now + s.backoff_s
                for target_system, target_component in targets[:4]:  # candidates: a few at most
                    self.counters["stream_requests"] += 1
                    self._write(
                        "COMMAND_LONG",
                        {
                            "target_system": target_system,
                            "target_component": target_component,
                            "command": mav.MAV_CMD_SET_MESSAGE_INTERVAL,
                            "confirmation": 0,
                            "param1": s.msg_id,
                            "param2": 1e6 / s.rate_hz,
                            "param3": 0,
                            "param4": 0,
                            "param5": 0,
                            "param6": 0,
                            "param7": 0,
                        },
                    )

    # ------------------------------------------------------------------ what arrives

    def _handle(self, msg: Any) -> bool:
        """Stamp and dispatch one message read; False for bytes that were no message (BAD_DATA)."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.counters["bad_data"] += 1
            return False
        t_us = stamp_us(self.clock)
        if self.tap is not None:
            self.tap(t_us, bytes(msg.get_msgbuf()))
        try:
            self._dispatch(msg, kind, us_to_s(t_us))
        except (AttributeError, TypeError, ValueError, OverflowError) as e:  # a malformed message: skipped, not fatal
            self.counters["handler_errors"] += 1
            if self.counters["handler_errors"] <= 3:
                log.warning("link %s: %s message skipped: %s", self.options.url, kind, e)
        return True

    def _dispatch(self, msg: Any, kind: str, now: float) -> None:
        self._last_rx_s = now
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if kind == "HEARTBEAT":
            if msg.autopilot != self._mav.MAV_AUTOPILOT_INVALID:  # ground stations and companions say INVALID
                self._autopilot_heartbeat(src_sys, src_comp, int(msg.autopilot), now)
                if (src_sys, src_comp) == (self.fc_system_id, self.fc_component_id):
                    self.listener.on_armed(bool(msg.base_mode & self._mav.MAV_MODE_FLAG_SAFETY_ARMED), now)
            return
        if src_sys != self.fc_system_id or src_comp != self.fc_component_id:
            c = self._candidates.get((src_sys, src_comp))
            if kind == "ATTITUDE" and c is not None:
                c.attitudes += 1
                self._confirm_if_consistent(src_sys, src_comp, c, now)
            return
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None:
            if self._last_boot_ms is not None and boot_ms < self._last_boot_ms - _REBOOT_STEP_S * 1000:
                self._rebooted(now)
            self._last_boot_ms = boot_ms
        for s in self._streams:
            if s.msg_id == msg.get_msgId():
                s.last_rx_s, s.backoff_s = now, 0.0
        if kind == "ATTITUDE":
            self.listener.on_attitude(
                msg.time_boot_ms, msg.roll, msg.pitch, msg.yaw, now, (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
            )
        elif kind == "LOCAL_POSITION_NED":
            self.listener.on_local_position(msg.time_boot_ms, (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz), now)
        elif kind == "DISTANCE_SENSOR":
            if msg.orientation == self._mav.MAV_SENSOR_ROTATION_PITCH_270:
                ok = msg.min_distance <= msg.current_distance <= msg.max_distance
                self.listener.on_range(msg.time_boot_ms, msg.current_distance * 0.01 if ok else None, now)
        elif kind == "GLOBAL_POSITION_INT":
            self.listener.on_height(msg.time_boot_ms, msg.relative_alt * 1e-3, now)
        elif kind == "EKF_STATUS_REPORT":
            self.listener.on_ekf_status(bool(msg.flags & self._mav.EKF_ATTITUDE), msg.compass_variance, now)
        elif kind == "TIMESYNC":
            if msg.tc1 == 0:  # the flight controller asks for our clock: the one estimates are stamped with
                self._write("TIMESYNC", {"tc1": int(now * 1e9), "ts1": msg.ts1})
            elif 0.0 <= now - msg.ts1 * 1e-9 <= _TIMESYNC_MAX_RTT_S:
                self.listener.on_timesync(msg.ts1 * 1e-9, msg.tc1 * 1e-9, now)
        elif (
            kind == "COMMAND_ACK"
            and msg.command == self._mav.MAV_CMD_SET_MESSAGE_INTERVAL
            and msg.result != self._mav.MAV_RESULT_ACCEPTED
        ):
            self.counters["denied"] += 1
            if self.counters["denied"] <= 3:
                log.info("flight controller refused a stream request (result %d); retrying with back-off", msg.result)

    def _autopilot_heartbeat(self, sys_id: int, comp_id: int, autopilot: int, now: float) -> None:
        """Choose the flight controller: the configured system id at its first HEARTBEAT, else the first
        autopilot whose HEARTBEAT and ATTITUDE have both come for ``fc_confirm_s``. Any other after
        that is reported (logged once, counted as ``other_autopilots``), never followed."""
        key = (sys_id, comp_id)
        if self.fc_component_id is not None:
            if key == (self.fc_system_id, self.fc_component_id) and self._fc_address is None:
                self._pin_udp()  # a new socket after a reconnect
            elif key != (self.fc_system_id, self.fc_component_id):
                self.counters["other_autopilots"] += 1
                if key not in self._others_told and len(self._others_told) < 16:
                    self._others_told.add(key)
                    log.warning(
                        "another autopilot on the link (system %d component %d): ignored; following system %d component %d",
                        sys_id,
                        comp_id,
                        self.fc_system_id,
                        self.fc_component_id,
                    )
            return
        if self.options.fc_system_id and sys_id != self.options.fc_system_id:
            self.counters["other_autopilots"] += 1
            return
        c = self._candidates.get(key)
        if c is None:
            if len(self._candidates) >= 16:  # a flood of forged ids must not grow this without bound
                return
            c = self._candidates[key] = _Candidate(now, autopilot)
        else:
            c.heartbeats += 1
        if self.options.fc_system_id:
            self._choose(sys_id, comp_id, autopilot)
        else:
            self._confirm_if_consistent(sys_id, comp_id, c, now)

    def _confirm_if_consistent(self, sys_id: int, comp_id: int, c: _Candidate, now: float) -> None:
        """Chosen once its HEARTBEAT (twice) and ATTITUDE have come for ``fc_confirm_s``."""
        if c.heartbeats >= 2 and c.attitudes >= 3 and now - c.first_heartbeat_s >= self.options.fc_confirm_s:
            self._choose(sys_id, comp_id, c.autopilot)

    def _choose(self, sys_id: int, comp_id: int, autopilot: int) -> None:
        self.fc_system_id, self.fc_component_id, self.autopilot = sys_id, comp_id, autopilot
        self._conn.mav.srcSystem = sys_id
        self._candidates.clear()
        self._pin_udp()
        log.info("flight controller: system %d component %d (autopilot type %d)", sys_id, comp_id, autopilot)

    def _rebooted(self, now: float) -> None:
        log.warning("flight controller rebooted (time_boot_ms went back); re-requesting streams")
        self.counters["reboots"] += 1
        self.listener.on_reboot()
        for s in self._streams:
            s.last_rx_s, s.next_request_s, s.backoff_s = -math.inf, now, 0.0
