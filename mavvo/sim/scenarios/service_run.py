"""The mavvo daemon flown against the simulated flight controller and camera, and how well it did.

The daemon runs its normal code path: MAVLink 2 over a real UDP socket on 127.0.0.1 to the simulated
flight controller, frames from the simulated camera through the frame-source interface, the
simulation clock as its host clock. In lockstep (the default) the run is as fast as the daemon and the
simulation moves only when the daemon reads a frame; in real time both follow the wall clock.

The evaluation uses what the flight controller received: each VISION_POSITION_ESTIMATE at its ``usec``
(the exposure on the simulation clock) against the true camera centre at that time.
"""

from __future__ import annotations

import dataclasses
import logging
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mavvo.evaluation.flight_safety import FlightSafety, VisionSample, flight_safety
from mavvo.evaluation.metrics import Evaluation, PoseSeries, evaluate
from mavvo.evaluation.report import GROUND_TRUTH_FILE, vision_estimates, write_report, write_tum
from mavvo.geometry.camera_model import CameraIntrinsics
from mavvo.service.camera import CameraOptions
from mavvo.service.daemon import Daemon
from mavvo.service.progress import DaemonSummary, LockstepProgress
from mavvo.service.settings import MountingOptions, ServiceConfig, as_matrix3
from mavvo.service.timing import Clock
from mavvo.sim.scenarios.flight import Simulation
from mavvo.sim.scenarios.loader import Scenario
from mavvo.sim.world.camera import CameraSpec

log = logging.getLogger(__name__)


def camera_options(spec: CameraSpec, source: str) -> CameraOptions:
    """The daemon's camera settings for the simulated camera ``spec``: its intrinsics, frame rate and
    rolling-shutter readout."""
    intrinsics = {f.name: getattr(spec, f.name) for f in dataclasses.fields(CameraIntrinsics)}
    return CameraOptions(source=source, rate_hz=spec.rate_hz, readout_ms=spec.rolling_shutter_ms, **intrinsics)


def config_for(scenario: Scenario, base: ServiceConfig, url: str) -> ServiceConfig:
    """``base`` with the scenario's camera (intrinsics, rate, mounting) and the link to ``url``; no
    state file (a simulation leaves the host's ``/var/lib/mavvo`` alone and repeats exactly)."""
    return dataclasses.replace(
        base,
        camera=camera_options(scenario.camera, f"sim:{scenario.name}"),
        mounting=MountingOptions(as_matrix3(scenario.camera.R_body_cam()), scenario.camera.lever_arm_m),
        link=dataclasses.replace(base.link, url=url),
        service=dataclasses.replace(base.service, state_file=""),
    )


@dataclass(frozen=True)
class SimRun:
    """One daemon run against the simulator."""

    scenario: str
    realtime: bool
    duration_s: float
    wall_s: float
    daemon: DaemonSummary
    received: dict[str, int]  # message type -> count, as the flight controller received them
    estimates: PoseSeries
    truth: PoseSeries
    evaluation: Evaluation | None
    resets: int
    vision_messages: list[Any]  # the VISION_POSITION_ESTIMATEs received, in order (pymavlink messages)
    statustexts: list[tuple[float, str]]  # (simulation time received, text)
    heartbeat_status: list[tuple[float, int]]  # (simulation time received, system_status) of the vision component
    safety: FlightSafety  # what the vehicle would feel: no alignment, resets included
    recording: Path | None = None  # with record.dir: the recording (with ground_truth.tum beside it)
    lockstep_waits_expired: int = 0  # lockstep: times the service did not catch up (the run may not repeat exactly)
    # The simulated EKF's horizontal error against the truth, every 50 ms: rows (t_s, north m, east m).
    fc_error_ne_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def summary(self) -> dict[str, Any]:
        """A flat JSON-ready summary (what ``mavvo sim --json`` prints)."""
        ev = self.evaluation
        return {
            "scenario": self.scenario,
            "realtime": self.realtime,
            "duration_s": round(self.duration_s, 3),
            "wall_s": round(self.wall_s, 3),
            "frames": self.daemon.counters.get("frames", 0),
            "estimates_sent": self.daemon.counters.get("estimates_sent", 0),
            "estimates_received": len(self.vision_messages),
            "resets": self.resets,
            "ate_rmse_m": None if ev is None else ev.ate_se3_m["rmse"],
            "ate_sim3_rmse_m": None if ev is None else ev.ate_sim3_m["rmse"],
            "sim3_scale": None if ev is None else ev.sim3_scale,
            "ate_percent_of_path": None if ev is None else ev.ate_se3_rmse_percent_of_path,
            "path_length_m": None if ev is None else ev.path_length_m,
            "vehicle": self.safety.to_dict(),
            "final_state": self.daemon.state,
            "latency_ms": self.daemon.latency_ms,
            "received": self.received,
            "counters": self.daemon.counters,
            "recording": None if self.recording is None else str(self.recording),
            "lockstep_waits_expired": self.lockstep_waits_expired,
        }


# Lockstep: how long (real time) a driver waits for the service to read a message or finish a frame
# before giving up on exact lockstep (counted in SimRun.lockstep_waits_expired). Generous: it is only
# ever reached when the service is stuck, never on a busy machine.
_LOCKSTEP_WAIT_S = 10.0


class _Lockstep:
    """Holds the simulation clock while the service works, so that it sees every input at the simulated
    moment it was meant for and two runs send the same bytes, however loaded the machine."""

    def __init__(self, daemon: Daemon, sim: Simulation) -> None:
        self.daemon = daemon
        self.sim = sim
        self.waits_expired = 0
        self._started = False

    def deliver(self, send: Callable[[], None]) -> None:
        """Send one flight-controller datagram (a message, or spoiled bytes), then wait until the
        service has read it and written what it made due: it stamps its arrival at the moment it was
        sent. A datagram to no one (the service has not connected yet, or is reconnecting) is not waited for."""
        before = self.daemon.progress().datagrams_done
        send()
        address = self.daemon.link.local_address()
        if address is None or not self.sim.fc.sends_to(address):
            return
        self._wait(lambda p: p.datagrams_done > before)

    def hold(self) -> None:
        """Before the clock moves on to the next frame: the service has done all it can with the frames
        it was given and written what it sent, and its link has done what the clock made due (a tick),
        so the flight controller hears it all at the same moment on every run. Before the first frame
        also: the link has said something (a listening flight controller knows the service from then
        on), however long the service took to start."""
        now = self.sim.clock.now_s()
        first, self._started = not self._started, True
        self.daemon.tick()
        self._wait(
            lambda p: p.idle_after(p.frames_queued) and p.link_tick_s >= now and (p.messages_sent > 0 or not first)
        )

    def _wait(self, done: Callable[[LockstepProgress], bool]) -> None:
        if not self.daemon.wait_progress(done, _LOCKSTEP_WAIT_S) and not self.daemon.stop_event.is_set():
            self.waits_expired += 1
            log.warning(
                "lockstep: the service did not catch up within %.0f s; this run may not repeat exactly (at %.3f s: %s)",
                _LOCKSTEP_WAIT_S,
                self.sim.clock.now_s(),
                self.daemon.progress(),
            )


def run_daemon_in_sim(
    scenario: Scenario,
    base: ServiceConfig | None = None,
    *,
    realtime: bool = False,
    duration_s: float | None = None,
    out_dir: str | Path | None = None,
    wall_clock: Clock | None = None,
    service_listens: bool = False,
    during: Callable[[Daemon, tuple[str, int]], None] | None = None,
    forward_url: str | None = None,
) -> SimRun:
    """Fly ``scenario`` with the daemon (see the module docstring) until the scenario ends or the
    daemon is stopped (SIGTERM or SIGINT when called from the main thread); evaluate, and with
    ``out_dir`` write the report (estimate.tum, truth.tum, summary.json, evaluation.png). With
    ``record.dir`` set in ``base`` the flight is recorded, and the truth (100 Hz) is written beside it as
    ``ground_truth.tum`` for ``mavvo replay``.

    ``service_listens``: the daemon listens (``udpin``) and the flight controller sends to it, as on a
    drone whose autopilot or router pushes to the companion computer; default: the flight controller
    listens. ``during(daemon, (host, port))`` runs on its own thread while the daemon runs (the fault
    suite's attacker), given the UDP address the daemon reads from. ``forward_url``: the flight
    controller forwards what the service sends it there (``mavvo monitor``'s port)."""
    sim, url, service_address = _simulation(scenario, realtime, duration_s, forward_url, service_listens)
    config = config_for(scenario, base or ServiceConfig(), url)
    stop_fc = threading.Event()
    fc_thread = None
    wall0 = time.perf_counter()
    try:
        daemon = Daemon(config, clock=sim.clock, source=sim.camera, wall_clock=wall_clock)
        lockstep = None if realtime else _Lockstep(daemon, sim)
        if lockstep is not None:
            sim.fc.deliver, sim.hold = lockstep.deliver, lockstep.hold
        if during is not None:

            def attack(d: Daemon = daemon) -> None:  # the udpout socket exists once the link has connected
                during(d, service_address or daemon_address(d))

            threading.Thread(target=attack, name="sim-during", daemon=True).start()
        if realtime:
            fc_thread = threading.Thread(
                target=sim.serve, args=(stop_fc,), kwargs={"until_s": float("inf")}, name="sim-fc", daemon=True
            )
            fc_thread.start()
        summary = daemon.run()
    finally:
        stop_fc.set()
        if fc_thread is not None:
            fc_thread.join(2.0)
        sim.fc.poll()  # what the daemon sent last
        sim.close()
    return _sim_run(scenario, sim, daemon, summary, time.perf_counter() - wall0, lockstep, out_dir)


def _simulation(
    scenario: Scenario, realtime: bool, duration_s: float | None, forward_url: str | None, service_listens: bool
) -> tuple[Simulation, str, tuple[str, int] | None]:
    """The simulated flight, the service's link.url to it, and the address the service listens on
    (``service_listens``: the flight controller sends to the service; else the service sends first)."""
    if not service_listens:
        sim = Simulation(
            scenario, "udpin:127.0.0.1:0", realtime=realtime, duration_s=duration_s, forward_url=forward_url
        )
        host, port = sim.fc.address
        return sim, f"udpout:{host}:{port}", None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        address = probe.getsockname()[:2]
    sim = Simulation(
        scenario, f"udpout:127.0.0.1:{address[1]}", realtime=realtime, duration_s=duration_s, forward_url=forward_url
    )
    return sim, f"udpin:127.0.0.1:{address[1]}", address


def _sim_run(
    scenario: Scenario,
    sim: Simulation,
    daemon: Daemon,
    summary: DaemonSummary,
    wall: float,
    lockstep: _Lockstep | None,
    out_dir: str | Path | None,
) -> SimRun:
    """What the flight controller received, against the truth: the run's record (and its report files)."""
    realtime = lockstep is None
    vpe = [r for r in sim.fc.received if r.type == "VISION_POSITION_ESTIMATE"]
    est = vision_estimates(sim.fc.received, "usec")
    truth = sim.truth_at(est.timestamps_s)
    ev = None
    if len(est) >= 3:
        ev = write_report(out_dir, est, truth, title=scenario.name) if out_dir is not None else evaluate(est, truth)[0]
    recording = daemon.recorder.path if daemon.recorder is not None else None
    if recording is not None:
        times = np.arange(0.0, sim.clock.now_s(), 0.01)
        write_tum(recording / GROUND_TRUTH_FILE, sim.truth_at(times))
    counters = np.array([r.msg.reset_counter for r in vpe])
    fc_estimates = np.array(sim.fc.estimates).reshape(-1, 3)
    fc_error = fc_estimates.copy()
    fc_error[:, 1:] -= sim.truth_at(fc_estimates[:, 0]).positions_xyz_m[:, :2] if len(fc_estimates) else 0.0
    safety = flight_safety(
        [_vision_sample(r.msg) for r in vpe],
        lambda t: sim.truth_at(t).positions_xyz_m,
        lambda t: _yaw(sim.truth_at(t).rotations),
        fc_estimates,
        [(st.t_s, st.step_m) for st in sim.fc.estimator.steps],
        [(r.t_s, r.msg.value) for r in sim.fc.received if r.type == "NAMED_VALUE_FLOAT" and r.msg.name == "VO_DRIFT"],
    )
    received: dict[str, int] = {}
    for r in sim.fc.received:
        received[r.type] = received.get(r.type, 0) + 1
    return SimRun(
        scenario.name,
        realtime,
        sim.clock.now_s(),
        wall,
        summary,
        dict(sorted(received.items())),
        est,
        truth,
        ev,
        int(np.count_nonzero(np.diff(counters))) if len(counters) else 0,
        [r.msg for r in vpe],
        [(r.t_s, r.msg.text) for r in sim.fc.received if r.type == "STATUSTEXT"],
        [(r.t_s, r.msg.system_status) for r in sim.fc.received if r.type == "HEARTBEAT"],
        safety,
        recording,
        0 if lockstep is None else lockstep.waits_expired,
        fc_error,
    )


def daemon_address(daemon: Daemon, timeout_s: float = 30.0) -> tuple[str, int]:
    """The local UDP address of a ``udpout`` daemon's socket, once its link has connected."""
    daemon.link.connected.wait(timeout_s)
    return daemon.link.local_address() or ("127.0.0.1", 0)


def _vision_sample(msg: Any) -> VisionSample:
    """A received VISION_POSITION_ESTIMATE: the position block of its upper-triangle covariance."""
    c = msg.covariance
    cov = np.array([[c[0], c[1], c[2]], [c[1], c[6], c[7]], [c[2], c[7], c[11]]], dtype=float)
    return VisionSample(msg.usec * 1e-6, np.array([msg.x, msg.y, msg.z]), cov, msg.yaw, msg.reset_counter)


def _yaw(R: np.ndarray) -> np.ndarray:
    """Yaw (Euler 3-2-1) of rotations (N, 3, 3)."""
    return np.arctan2(R[:, 1, 0], R[:, 0, 0])
