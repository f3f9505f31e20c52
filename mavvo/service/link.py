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

import logging
import math
import os
import queue
import select
import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable

from mavvo.errors import LinkError
from mavvo.service import signing
from mavvo.service.autopilot_choice import AutopilotChoice
from mavvo.service.link_listener import LinkListener
from mavvo.service.link_options import LinkOptions, check_udp_port_free, parse_url, read_signing_key
from mavvo.service.mavlink import mavutil
from mavvo.service.timing import Clock
from mavvo.types import StrEnum

__all__ = ["Link", "SystemStatus", "Tap", "stamp_us", "us_to_s"]

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
        self.choice = AutopilotChoice(options, self.counters)
        self._datagram_from: Any = None  # the source address of the last UDP datagram read
        self._datagrams_read = 0
        # UDP datagrams read and done with (every message parsed from them handled, what they made due
        # written), whatever they held: a lockstep driver waits on it.
        self.datagrams_done = 0
        self._fc_address: Any = None  # the flight controller's UDP address, once chosen
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
            [(self.fc_system_id, self.fc_component_id)]
            if self.fc_component_id is not None
            else list(self.choice.candidates)
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

    @property
    def fc_system_id(self) -> int | None:
        """The flight controller's system id: configured, or chosen (None until then)."""
        return self.choice.system_id

    @property
    def fc_component_id(self) -> int | None:
        """The flight controller's component id, once chosen."""
        return self.choice.component_id

    @property
    def autopilot(self) -> int | None:
        """The flight controller's HEARTBEAT autopilot (MAV_AUTOPILOT), once chosen."""
        return self.choice.autopilot

    def _dispatch(self, msg: Any, kind: str, now: float) -> None:
        self._last_rx_s = now
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        chosen = self.choice.is_chosen(src_sys, src_comp)
        if kind == "HEARTBEAT":
            if msg.autopilot == self._mav.MAV_AUTOPILOT_INVALID:  # ground stations and companions say INVALID
                return
            if self.choice.heartbeat(src_sys, src_comp, int(msg.autopilot), now) or (
                chosen and self._fc_address is None
            ):
                self._follow_chosen()  # just chosen, or a new socket after a reconnect
            if self.choice.is_chosen(src_sys, src_comp):
                self.listener.on_armed(bool(msg.base_mode & self._mav.MAV_MODE_FLAG_SAFETY_ARMED), now)
            return
        if not chosen:
            if kind == "ATTITUDE" and self.choice.attitude(src_sys, src_comp, now):
                self._follow_chosen()
            return
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None:
            if self._last_boot_ms is not None and boot_ms < self._last_boot_ms - _REBOOT_STEP_S * 1000:
                self._rebooted(now)
            self._last_boot_ms = boot_ms
        for s in self._streams:
            if s.msg_id == msg.get_msgId():
                s.last_rx_s, s.backoff_s = now, 0.0
        self._to_listener(msg, kind, now)

    def _follow_chosen(self) -> None:
        """Speak as the chosen flight controller's system, and take datagrams only from its address."""
        self._conn.mav.srcSystem = self.choice.system_id
        self._pin_udp()

    def _to_listener(self, msg: Any, kind: str, now: float) -> None:
        """The chosen flight controller's message, handed over (or answered: TIMESYNC, COMMAND_ACK)."""
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

    def _rebooted(self, now: float) -> None:
        log.warning("flight controller rebooted (time_boot_ms went back); re-requesting streams")
        self.counters["reboots"] += 1
        self.listener.on_reboot()
        for s in self._streams:
            s.last_rx_s, s.next_request_s, s.backoff_s = -math.inf, now, 0.0
