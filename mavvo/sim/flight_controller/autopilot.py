"""A simulated flight controller that speaks MAVLink 2 on a socket, as an ArduPilot quadrotor does.

It sends HEARTBEAT at 1 Hz from boot and nothing else until asked: MAV_CMD_SET_MESSAGE_INTERVAL (with
a COMMAND_ACK) starts ATTITUDE, DISTANCE_SENSOR, LOCAL_POSITION_NED, GLOBAL_POSITION_INT or SYSTEM_TIME;
MAV_CMD_REQUEST_MESSAGE sends one. It answers TIMESYNC on its boot clock, and records every
VISION_POSITION_ESTIMATE, VISION_SPEED_ESTIMATE, ODOMETRY, HEARTBEAT, STATUSTEXT and NAMED_VALUE_FLOAT
it receives, with the arrival time, which :meth:`save_tlog` writes as a .tlog.

Time: the simulation clock (seconds since the start) drives everything; ``advance_to(t)`` emits every
message due up to ``t`` in time order, so in lockstep the byte stream is the same on every run with
the same seed. The boot clock (``time_boot_ms``) runs from ``boot_offset_s`` at the start, with a
drift in ppm, and restarts at zero after a reboot. TIMESYNC is answered on it as the autopilot named in
the spec does (ArduPilot: stamped several milliseconds before the request arrived). Faults beside the
reboot: a ``stall`` holds everything sent and lets it through at once when it ends (a buffered link);
a ``clock_step`` stops the process: nothing is sent or read, its clock stands still and runs that much
behind afterwards (an autopilot starved of CPU).

What it sends and where it comes from:
- ATTITUDE: the truth with Gaussian noise and a bias on roll and pitch, measured ``attitude_latency_ms``
  before it is sent and stamped with the boot time of the measurement;
- DISTANCE_SENSOR: a downward laser, height over cos(tilt) (the ground plane only; boxes are not seen);
- LOCAL_POSITION_NED: z from a noisy barometer; x, y, vx, vy from its position estimator
  (:mod:`mavvo.sim.flight_controller.estimator`), which fuses the VISION_POSITION_ESTIMATEs it receives as
  an EKF does, resets included, and dead-reckons between and without them;
- ATTITUDE's yaw carries the estimator's yaw error, which settles over the first seconds after boot;
- GLOBAL_POSITION_INT: the home position with the barometer altitude.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mavvo.errors import LinkError
from mavvo.service.mavlink import SOCKET_SCHEMES, mavutil
from mavvo.sim.flight_controller.estimator import SimEstimator
from mavvo.sim.flight_controller.sensors import attitude_sample, baro_height_sample, range_sample
from mavvo.sim.flight_controller.spec import VISION_READY_PARAMS, FlightControllerSpec
from mavvo.sim.world.clock import Clock
from mavvo.sim.world.faults import FaultSchedule
from mavvo.sim.world.trajectories import Trajectory

log = logging.getLogger(__name__)

RECORDED_TYPES = frozenset(
    {"VISION_POSITION_ESTIMATE", "VISION_SPEED_ESTIMATE", "ODOMETRY", "HEARTBEAT", "STATUSTEXT", "NAMED_VALUE_FLOAT"}
)
_ESTIMATOR_STEP_S = 0.02  # dead-reckoning step of the simulated EKF
_UNIX_EPOCH_AT_START_US = 1_790_000_000_000_000  # SYSTEM_TIME's wall clock at t = 0, fixed for repeatability


@dataclass(frozen=True)
class Received:
    """One message the flight controller received: simulation time, type name, the message, its bytes."""

    t_s: float
    type: str
    msg: Any
    raw: bytes


class SimFlightController:
    """The flight controller on ``url`` (a pymavlink connection string, e.g. ``udpin:127.0.0.1:14550``
    or ``tcpin:127.0.0.1:5760``), flying ``trajectory`` on ``clock``.

    Over UDP it answers whoever sent last, so a client must send first (a HEARTBEAT), as with
    ArduPilot. Not thread-safe: one thread calls ``advance_to``/``poll``.
    """

    def __init__(
        self,
        url: str,
        trajectory: Trajectory,
        clock: Clock,
        spec: FlightControllerSpec = FlightControllerSpec(),
        faults: FaultSchedule | None = None,
        seed: int = 0,
        forward_url: str | None = None,
    ) -> None:
        self._mavutil = mavutil()
        self._mav = self._mavutil.mavlink
        self.spec = spec
        self.trajectory = trajectory
        self.clock = clock
        self.faults = faults or FaultSchedule()
        self._rng = np.random.default_rng(seed)
        self._timesync_rng = np.random.default_rng([seed, 2])  # its own: answers must not shift the sensors' noise
        self._backlog: list[Any] = []  # sent during a stall, delivered when it ends
        self.estimator = SimEstimator(spec.estimator, trajectory.pose(0.0)[0], np.random.default_rng([seed, 1]))
        self.estimates: list[tuple[float, float, float]] = []  # (t_s, north, east) of the estimator, every 50 ms
        if not url.startswith(SOCKET_SCHEMES):
            raise LinkError(f"{url}: expected a socket connection string starting with {', '.join(SOCKET_SCHEMES)}")
        try:
            self._conn = self._mavutil.mavlink_connection(
                url, source_system=spec.system_id, source_component=1, autoreconnect=True
            )
        except (OSError, ValueError, OverflowError) as e:  # socket errors; a bad host or port number
            raise LinkError(f"{url}: cannot open: {getattr(e, 'strerror', None) or e}") from e
        self.received: list[Received] = []
        self.sent_counts: dict[str, int] = {}
        # Lockstep: called with each send (a function of no arguments, one datagram) so the driver can
        # hold the clock until the service has read it, and stamps it with the time it was sent.
        self.deliver: Callable[[Callable[[], None]], None] | None = None
        self.client_clock_s: list[
            float
        ] = []  # per TIMESYNC request heard: simulation time at arrival minus the request's ts1
        self.params: dict[str, float] = {
            **VISION_READY_PARAMS[spec.autopilot],
            **{name: float(v) for name, v in spec.params},
        }
        # Like an autopilot's forwarding to its ground-station port: what others send it, re-sent there.
        self._forward_to: tuple[str, int] | None = None
        self._forward_sock: socket.socket | None = None
        if forward_url is not None:
            if not forward_url.startswith("udpout:"):
                raise LinkError(f"--forward {forward_url}: expected udpout:HOST:PORT")
            host, _, port = forward_url.removeprefix("udpout:").rpartition(":")
            self._forward_to = (host, int(port))
            self._forward_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._boot_host_s = 0.0
        self._boot_offset_s = spec.boot_offset_s
        self._t_s = 0.0
        self._streams: dict[int, float] = {}  # msg id -> interval (s)
        self._next_due: dict[int, float] = {}
        self._next_heartbeat_s = 0.0
        self._last_attitude: Any = None
        self._baro_bias_m = float(self._rng.normal(0.0, 0.5))
        self._senders = {
            self._mav.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            self._mav.MAVLINK_MSG_ID_DISTANCE_SENSOR: self._distance_sensor,
            self._mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position,
            self._mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position,
            self._mav.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
            self._mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT: self._ekf_status,
        }
        if not spec.rangefinder:
            del self._senders[self._mav.MAVLINK_MSG_ID_DISTANCE_SENSOR]

    def sends_to(self, address: tuple[str, int]) -> bool:
        """Whether a message sent now goes to ``address`` (host, port): a listening flight controller
        knows a peer only after hearing from it, and a peer that reconnected has a new port."""
        conn = self._conn
        if not hasattr(conn, "udp_server"):  # a stream: whoever is connected reads it
            return True
        if conn.udp_server:
            return tuple(address) in conn.clients
        return tuple(conn.destination_addr) == tuple(address)

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) of the local socket: the port the system chose for ``udpin:127.0.0.1:0``."""
        sock = getattr(self._conn, "listen", None) or self._conn.port
        host, port = sock.getsockname()[:2]
        return host, port

    # ------------------------------------------------------------------ time

    def boot_time_ms(self, t_s: float) -> int:
        """``time_boot_ms`` at simulation time ``t_s``."""
        return int(self._boot_time_s(t_s) * 1000.0)

    def _boot_time_s(self, t_s: float) -> float:
        # A paused process's clock stands still: after a clock_step it runs that much behind for good.
        paused = sum(
            max(0.0, min(t_s, f.end_s) - max(f.start_s, self._boot_host_s))
            for f in self.faults.faults
            if f.kind == "clock_step"
        )
        return self._boot_offset_s + (t_s - self._boot_host_s - paused) * (1.0 + self.spec.clock_drift_ppm * 1e-6)

    def _down(self, t_s: float) -> bool:
        return self.faults.active("reboot", t_s)

    def _paused(self, t_s: float) -> bool:
        return self.faults.active("clock_step", t_s)

    # ------------------------------------------------------------------ the loop

    def advance_to(self, t_s: float) -> None:
        """Handle what arrived, then send everything due up to ``t_s``, in time order."""
        self.poll()
        while True:
            due = self._next_event_s()
            reboots = self.faults.reboots_ending(self._t_s, min(due, t_s))
            if reboots:
                self._t_s = reboots[0].end_s
                self._reboot(self._t_s)
                continue
            if due > t_s:
                break
            self._t_s = due
            self._propagate(due)
            self.clock.advance_to(due)  # lockstep: nothing arrives before it was sent (a no-op in real time)
            if due == self._next_heartbeat_s:
                self._next_heartbeat_s += 1.0
                self._send(self._heartbeat())
                continue
            msg_id = min(m for m, d in self._next_due.items() if d == due)
            self._next_due[msg_id] = due + self._streams[msg_id]
            msg = self._senders[msg_id](due)
            if msg is not None:
                self._send(msg)
        self._t_s = max(self._t_s, t_s)

    def _propagate(self, t_s: float) -> None:
        est = self.estimator
        while est.t_s < t_s:  # in steps short enough to follow the true velocity
            t = min(t_s, est.t_s + _ESTIMATOR_STEP_S)
            est.propagate(t, self.trajectory.state(t).v_ned_m_s)
        if not self.estimates or t_s - self.estimates[-1][0] >= 0.05:
            p = self.estimator.position_ne_m
            self.estimates.append((t_s, float(p[0]), float(p[1])))

    def _next_event_s(self) -> float:
        return min([self._next_heartbeat_s, *self._next_due.values()])

    def _reboot(self, t_s: float) -> None:
        log.info("simulated flight controller rebooted at t=%.3f s", t_s)
        self._boot_host_s = t_s
        self._boot_offset_s = 0.0
        self._streams.clear()
        self._next_due.clear()
        self._next_heartbeat_s = t_s
        self._last_attitude = None
        self.estimator.reboot()

    def poll(self) -> None:
        """Read and handle every message waiting on the socket (non-blocking)."""
        if self._paused(self.clock.now_s()):
            return  # a stopped process reads nothing: what comes waits in the socket until it runs again
        while True:
            msg = self._conn.recv_msg()
            if msg is None:
                return
            kind = msg.get_type()
            if kind == "BAD_DATA" or self._down(self.clock.now_s()):
                continue
            if self._forward_sock is not None:
                try:
                    self._forward_sock.sendto(bytes(msg.get_msgbuf()), self._forward_to)
                except OSError:
                    pass  # nobody listening: forwarding is best effort, as on an autopilot
            if kind in RECORDED_TYPES:
                self.received.append(Received(self.clock.now_s(), kind, msg, bytes(msg.get_msgbuf())))
                if kind == "VISION_POSITION_ESTIMATE":
                    now = self.clock.now_s()
                    self._propagate(now)
                    self.estimator.fuse_vision(now, msg.x, msg.y, msg.reset_counter)
            elif kind == "TIMESYNC" and msg.tc1 == 0:
                self.client_clock_s.append(
                    self.clock.now_s() - msg.ts1 * 1e-9
                )  # simulation time minus the client's, plus transit
                self._send(self._mav.MAVLink_timesync_message(self._timesync_tc1_ns(), msg.ts1))
            elif kind == "COMMAND_LONG" and msg.target_system in (0, self.spec.system_id):
                self._command(msg)
            elif kind in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET") and msg.target_system in (
                0,
                self.spec.system_id,
            ):
                self._param(msg, kind)

    def _timesync_tc1_ns(self) -> int:
        """The answer's time, as each autopilot stamps it: PX4 when it handles the request; ArduPilot
        the request's arrival as its UART estimates it (the time of the read minus the packet's
        transmission time at the port's baud rate), which comes out several milliseconds early."""
        t_fc = self._boot_time_s(self.clock.now_s())
        if self.spec.autopilot == "ardupilot":
            t_fc -= 1e-3 * float(self._timesync_rng.uniform(*self.spec.timesync_early_ms))
        return int(t_fc * 1e9)

    def _param(self, msg: Any, kind: str) -> None:
        """The parameter protocol: a read by name or index, the whole list, or a set (answered, as
        autopilots do, with the PARAM_VALUE now in effect; unknown names get no answer)."""
        names = sorted(self.params)
        if kind == "PARAM_REQUEST_LIST":
            todo = names
        else:
            name = msg.param_id.decode() if isinstance(msg.param_id, bytes) else msg.param_id
            name = name.rstrip("\x00")
            if kind == "PARAM_REQUEST_READ" and msg.param_index >= 0:
                name = names[msg.param_index] if msg.param_index < len(names) else ""
            if name not in self.params:
                return
            if kind == "PARAM_SET":
                self.params[name] = float(msg.param_value)
            todo = [name]
        for name in todo:
            self._send(
                self._mav.MAVLink_param_value_message(
                    name.encode(),
                    self.params[name],
                    self._mav.MAV_PARAM_TYPE_REAL32,
                    len(names),
                    names.index(name),
                )
            )

    def _command(self, msg: Any) -> None:
        mav = self._mav
        result = mav.MAV_RESULT_ACCEPTED
        if msg.command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(msg.param1), msg.param2
            if msg_id not in self._senders:
                result = mav.MAV_RESULT_DENIED
            elif interval_us < 0:
                self._streams.pop(msg_id, None)
                self._next_due.pop(msg_id, None)
            else:
                default_hz = (
                    self.spec.attitude_default_rate_hz
                    if msg_id == mav.MAVLINK_MSG_ID_ATTITUDE
                    else self.spec.stream_default_rate_hz
                )
                interval_s = interval_us * 1e-6 if interval_us > 0 else 1.0 / default_hz
                self._streams[msg_id] = interval_s
                self._next_due[msg_id] = self._t_s + interval_s
        elif msg.command == mav.MAV_CMD_REQUEST_MESSAGE:
            msg_id = int(msg.param1)
            reply = self._senders[msg_id](self._t_s) if msg_id in self._senders else None
            if msg_id == mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN and self.spec.ekf_origin:
                sp = self.spec
                reply = mav.MAVLink_gps_global_origin_message(
                    int(sp.home_lat_deg * 1e7), int(sp.home_lon_deg * 1e7), int(sp.home_alt_m * 1000)
                )
            if reply is not None:
                self._send(reply)
            else:
                result = mav.MAV_RESULT_DENIED
        else:
            result = mav.MAV_RESULT_UNSUPPORTED
        self._send(
            mav.MAVLink_command_ack_message(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        )

    def _send(self, msg: Any) -> None:
        t = self._t_s
        if self._down(t) or self._paused(t) or self.faults.active("link_silence", t):
            return
        if self.faults.active("stall", t):  # the link holds what is sent ...
            self._backlog.append(msg)
            return
        backlog, self._backlog = self._backlog, []
        for held in backlog:  # ... and lets it all through at once when it moves again
            self._deliver(held)
        self._deliver(msg)

    def _deliver(self, msg: Any) -> None:
        t = self._t_s
        kind = msg.get_type()
        self.sent_counts[kind] = self.sent_counts.get(kind, 0) + 1
        if not self.faults.active("corrupt_bytes", t):
            if self.deliver is None:
                self._conn.mav.send(msg)
            else:
                self.deliver(lambda: self._conn.mav.send(msg))
            return
        buf = bytearray(msg.pack(self._conn.mav))
        self._conn.mav.seq = (self._conn.mav.seq + 1) % 256
        i = int(self._rng.integers(10, len(buf)))
        buf[i] ^= 0xFF
        junk = self._rng.integers(0, 256, int(self._rng.integers(1, 8)), dtype=np.uint8).tobytes()
        if self.deliver is None:
            self._conn.write(junk + bytes(buf))
        else:
            self.deliver(lambda: self._conn.write(junk + bytes(buf)))

    # ------------------------------------------------------------------ messages

    def _armed_for_s(self, t_s: float) -> float | None:
        """How long the vehicle has been armed at ``t_s``; None while disarmed."""
        armed = self.spec.armed and t_s >= self.spec.arm_at_s
        return t_s - self.spec.arm_at_s if armed else None

    def _heartbeat(self) -> Any:
        mav = self._mav
        armed = mav.MAV_MODE_FLAG_SAFETY_ARMED if self._armed_for_s(self._t_s) is not None else 0
        autopilot = mav.MAV_AUTOPILOT_PX4 if self.spec.autopilot == "px4" else mav.MAV_AUTOPILOT_ARDUPILOTMEGA
        return mav.MAVLink_heartbeat_message(
            mav.MAV_TYPE_QUADROTOR,
            autopilot,
            mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | armed | mav.MAV_MODE_FLAG_STABILIZE_ENABLED,
            5,
            mav.MAV_STATE_ACTIVE if armed else mav.MAV_STATE_STANDBY,
            3,  # custom mode 5: LOITER
        )

    def _attitude(self, t_s: float) -> Any:
        t_meas = max(t_s - self.spec.attitude_latency_ms * 1e-3, 0.0)
        if self.faults.active("stale_attitude", t_s) and self._last_attitude is not None:
            return self._last_attitude
        roll, pitch, yaw, w = attitude_sample(self.trajectory, t_meas, self.spec, self._rng)
        error = self.estimator.yaw_error_rad(self._boot_time_s(t_meas), self._armed_for_s(t_meas))
        yaw = math.remainder(yaw + error, math.tau)
        if self.faults.active("nan_attitude", t_s):
            roll = pitch = yaw = float("nan")
        msg = self._mav.MAVLink_attitude_message(self.boot_time_ms(t_meas), roll, pitch, yaw, w[0], w[1], w[2])
        self._last_attitude = msg
        return msg

    def _distance_sensor(self, t_s: float) -> Any:
        sp = self.spec
        r = range_sample(self.trajectory, t_s, sp, self._rng)
        max_cm = int(round(sp.rangefinder_max_m * 100))
        cm = int(round(r * 100)) if r is not None else max_cm + 1
        mav = self._mav
        return mav.MAVLink_distance_sensor_message(
            self.boot_time_ms(t_s),
            int(round(sp.rangefinder_min_m * 100)),
            max_cm,
            cm,
            mav.MAV_DISTANCE_SENSOR_LASER,
            0,
            mav.MAV_SENSOR_ROTATION_PITCH_270,
            255,
        )

    def _baro_height_m(self, t_s: float) -> float:
        return baro_height_sample(self.trajectory, t_s, self.spec, self._baro_bias_m, self._rng)

    def _local_position(self, t_s: float) -> Any:
        """LOCAL_POSITION_NED, or None while the estimator has no position (after a reboot)."""
        s = self.trajectory.state(t_s)
        self._propagate(t_s)
        if not self.estimator.has_position:
            return None
        p, v = self.estimator.position_ne_m, self.estimator.velocity_ne_m_s(s.v_ned_m_s)
        return self._mav.MAVLink_local_position_ned_message(
            self.boot_time_ms(t_s),
            float(p[0]),
            float(p[1]),
            -self._baro_height_m(t_s),
            float(v[0]),
            float(v[1]),
            float(s.v_ned_m_s[2]),
        )

    def _global_position(self, t_s: float) -> Any:
        s = self.trajectory.state(t_s)
        sp = self.spec
        h = self._baro_height_m(t_s)
        hdg = int(round(np.degrees(s.yaw_rad) % 360 * 100)) % 36000
        return self._mav.MAVLink_global_position_int_message(
            self.boot_time_ms(t_s),
            int(round(sp.home_lat_deg * 1e7)),
            int(round(sp.home_lon_deg * 1e7)),
            int(round((sp.home_alt_m + h) * 1000)),
            int(round(h * 1000)),
            0,
            0,
            int(round(s.v_ned_m_s[2] * 100)),
            hdg,
        )

    def _ekf_status(self, t_s: float) -> Any:
        """ArduPilot's EKF_STATUS_REPORT: velocities and horizontal position (relative; absolute too with
        an origin) are good, and the attitude once its yaw has converged (ArduPilot sets that flag only
        after its yaw alignment): the settling error under 0.5 deg."""
        settling = self.estimator.yaw_error_rad(self._boot_time_s(t_s))  # disarmed: the settling term alone
        aligned = 0x1 if abs(math.degrees(settling)) < 0.5 else 0
        flags = aligned | 0x2 | 0x4 | 0x8 | 0x20 | (0x10 if self.spec.ekf_origin else 0)
        return self._mav.MAVLink_ekf_status_report_message(flags, 0.1, 0.1, 0.1, 0.1, 0.0)

    def _system_time(self, t_s: float) -> Any:
        return self._mav.MAVLink_system_time_message(_UNIX_EPOCH_AT_START_US + int(t_s * 1e6), self.boot_time_ms(t_s))

    # ------------------------------------------------------------------ output

    def save_tlog(self, path: str | Path) -> Path:
        """Write the received messages as a .tlog: per message a big-endian uint64 arrival time in
        microseconds of simulation time, then the message bytes (pymavlink's format)."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        with p.open("wb") as f:
            for r in self.received:
                f.write(struct.pack(">Q", int(round(r.t_s * 1e6))) + r.raw)
        return p

    def close(self) -> None:
        self._conn.close()
        if self._forward_sock is not None:
            self._forward_sock.close()
