"""One simulated flight put together from a scenario: clock, flight controller, camera and truth.

Lockstep (the default): nothing moves until the camera is read; each ``camera.read`` advances the
flight controller's streams to the moment the frame arrives, so the run is as fast as the consumer and
repeats exactly for a seed. Real time: ``serve`` drives the flight controller from the host clock
until stopped, and the camera sleeps until each frame is due.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from mavvo.evaluation.metrics import PoseSeries
from mavvo.geometry.frames import euler321_from_R
from mavvo.service.timing import FlightControllerState
from mavvo.sim.flight_controller.autopilot import SimFlightController
from mavvo.sim.scenarios.loader import Scenario, load_scenario
from mavvo.sim.world.camera import HostClock, HostTimedCamera, SimCamera
from mavvo.sim.world.clock import LockstepClock, RealClock
from mavvo.sim.world.faults import FaultSchedule
from mavvo.sim.world.scene import World
from mavvo.sim.world.trajectories import make_trajectory
from mavvo.types import Frame

log = logging.getLogger(__name__)

_SERVE_TICK_S = 0.002
_MISMATCH_DEG = 15.0  # the flight controller's attitude this far from the camera's scenario ...
_MISMATCH_S = 3.0  # ... for this long: they fly different flights
_TELL_EVERY_S = 10.0


class Simulation:
    """The flight controller on ``mavlink_url`` and the camera of ``scenario``; with ``forward_url``
    (``udpout:HOST:PORT``) the flight controller forwards what it receives there, as an autopilot
    forwards a companion's messages to its ground-station port."""

    def __init__(
        self,
        scenario: Scenario,
        mavlink_url: str,
        *,
        realtime: bool = False,
        duration_s: float | None = None,
        forward_url: str | None = None,
    ) -> None:
        self.scenario = scenario
        self.clock = RealClock() if realtime else LockstepClock()
        self.trajectory = make_trajectory(scenario.trajectory)
        self.duration_s = duration_s or scenario.duration_s or self.trajectory.duration_s
        self.faults = FaultSchedule(scenario.faults)
        seeds = np.random.SeedSequence(scenario.seed).spawn(2)
        self.fc = SimFlightController(
            mavlink_url,
            self.trajectory,
            self.clock,
            scenario.flight_controller,
            self.faults,
            seed=int(seeds[0].generate_state(1)[0]),
            forward_url=forward_url,
        )
        self.hold: Callable[[], None] | None = None
        self.world = World.build(scenario.world)
        self.camera = SimCamera(
            scenario.camera,
            self.world,
            self.trajectory,
            self.clock,
            faults=self.faults,
            seed=int(seeds[1].generate_state(1)[0]),
            advance=None if realtime else self.advance_to,
            duration_s=self.duration_s,
        )

    def advance_to(self, t_s: float) -> None:
        """Lockstep: run the flight controller up to ``t_s`` and move the clock there (after ``hold``,
        when set: a driver's wait for the service to finish what it was given)."""
        if self.hold is not None:
            self.hold()
        self.fc.advance_to(t_s)
        self.clock.advance_to(t_s)

    def serve(self, stop: threading.Event, *, until_s: float | None = None) -> None:
        """Real time: drive the flight controller from the clock until ``stop`` is set or ``until_s``
        (default: the scenario's duration; ``float('inf')`` flies on, holding the end pose)."""
        end = self.duration_s if until_s is None else until_s
        while not stop.is_set():
            now = self.clock.now_s()
            if now >= end:
                break
            self.fc.advance_to(now)
            stop.wait(_SERVE_TICK_S)

    def truth_at(self, times_s: np.ndarray) -> PoseSeries:
        """True camera-centre positions and body orientations at ``times_s`` (simulation seconds): what
        a vision estimate estimates."""
        return self.trajectory.truth_series(times_s, self.scenario.camera.lever_arm_m)

    def close(self) -> None:
        self.camera.close()
        self.fc.close()


def scenario_camera(
    name_or_path: str, host_clock: HostClock, fc: FlightControllerState | None = None
) -> HostTimedCamera | FlightSyncedCamera:
    """The camera of a scenario in real time, frames stamped on ``host_clock`` (``camera.source:
    sim:SCENARIO`` in ``mavvo run``). With ``fc`` (the service's view of the flight controller), it flies
    the scenario on the simulated flight controller's clock (``mavvo sim --fc-only``), so both fly the
    same moment of the flight whenever each was started (:class:`FlightSyncedCamera`); without, from
    now (e.g. beside ArduPilot's SITL)."""
    scenario = load_scenario(name_or_path)
    trajectory = make_trajectory(scenario.trajectory)
    if fc is not None:
        clock = _FlightClock(host_clock)
        camera = SimCamera(
            scenario.camera,
            World.build(scenario.world),
            trajectory,
            clock,  # type: ignore[arg-type]
            faults=FaultSchedule(scenario.faults),
            seed=scenario.seed,
            duration_s=scenario.duration_s,
        )
        return FlightSyncedCamera(camera, clock, fc, scenario)
    real = RealClock()
    offset = host_clock.now_s() - real.now_s()
    camera = SimCamera(
        scenario.camera,
        World.build(scenario.world),
        trajectory,
        real,
        faults=FaultSchedule(scenario.faults),
        seed=scenario.seed,
        duration_s=scenario.duration_s,
    )
    return HostTimedCamera(camera, offset)


class _FlightClock:
    """Simulation time as the flight controller keeps it: host time plus ``offset_s`` (its boot clock
    minus the host clock, minus the boot clock's value at the simulation's start)."""

    realtime = True

    def __init__(self, host: HostClock) -> None:
        self.host = host
        self.offset_s = 0.0

    def now_s(self) -> float:
        return self.host.now_s() + self.offset_s

    def advance_to(self, t_s: float) -> None:
        """Real time advances by itself."""

    def sleep_until(self, t_s: float) -> None:
        dt = t_s - self.now_s()
        if dt > 0:
            time.sleep(dt)


class FlightSyncedCamera:
    """A scenario's camera at the simulated flight controller's moment of the flight.

    No frames until the flight controller's clock is known (its boot clock is the simulation time plus
    the scenario's ``flight_controller.boot_offset_s``). It then watches that both fly the same
    scenario: the flight controller's roll, pitch and yaw against the scenario's at the same moment;
    when they differ by more than ``_MISMATCH_DEG`` for ``_MISMATCH_S`` it logs an error (again every
    ``_TELL_EVERY_S``): the estimates would be of another flight than the flight controller's.
    """

    def __init__(self, camera: SimCamera, clock: _FlightClock, fc: FlightControllerState, scenario: Scenario) -> None:
        self.camera, self.clock, self.fc, self.scenario = camera, clock, fc, scenario
        self.boot_offset_s = scenario.flight_controller.boot_offset_s
        self._synced = False
        self._mismatch_since: float | None = None
        self._told_at = -math.inf
        self.mismatch_deg = 0.0

    def read(self, timeout_s: float) -> Frame | None:
        offset = self.fc.clock_offset_s()
        if offset is None:
            time.sleep(min(timeout_s, 0.05))  # the flight controller is not heard yet
            return None
        self.clock.offset_s = offset - self.boot_offset_s
        if not self._synced:
            self._synced = True
            self.camera.skip_to(self.clock.now_s())
            log.info(
                "simulated camera: flying %s on the flight controller's clock, from t = %.1f s",
                self.scenario.name,
                self.clock.now_s(),
            )
        f = self.camera.read(timeout_s)
        if f is None:
            return None
        t_host = f.t_exposure_s - self.clock.offset_s
        self._watch(f.t_exposure_s, t_host)
        return Frame(f.image, t_host, f.seq)

    def _watch(self, t_sim_s: float, t_host_s: float) -> None:
        p = self.fc.pair(t_host_s)
        if p.status != "paired":
            return
        R = self.camera.trajectory.pose(t_sim_s)[1]
        roll, pitch, yaw = euler321_from_R(R)
        diff = max(
            abs(math.degrees(math.remainder(a - b, math.tau)))
            for a, b in ((p.roll_rad, roll), (p.pitch_rad, pitch), (p.yaw_rad, yaw))
        )
        self.mismatch_deg = diff
        if diff <= _MISMATCH_DEG:
            self._mismatch_since = None
            return
        self._mismatch_since = t_sim_s if self._mismatch_since is None else self._mismatch_since
        if t_sim_s - self._mismatch_since >= _MISMATCH_S and t_sim_s - self._told_at >= _TELL_EVERY_S:
            self._told_at = t_sim_s
            log.error(
                "camera sim:%s: the flight controller's attitude is %.0f deg off this scenario's for %.0f s: is it flying another "
                "scenario? (mavvo sim --fc-only --scenario %s)",
                self.scenario.name,
                diff,
                t_sim_s - self._mismatch_since,
                self.scenario.name,
            )

    def close(self) -> None:
        self.camera.close()
