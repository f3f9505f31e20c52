"""One simulated flight put together from a scenario: clock, flight controller, camera and truth.

Lockstep (the default): nothing moves until the camera is read; each ``camera.read`` advances the
flight controller's streams to the moment the frame arrives, so the run is as fast as the consumer and
repeats exactly for a seed. Real time: ``serve`` drives the flight controller from the host clock
until stopped, and the camera sleeps until each frame is due.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from sim.world.camera import HostClock, HostTimedCamera, SimCamera
from sim.world.clock import LockstepClock, RealClock
from sim.world.faults import FaultSchedule
from sim.flight_controller.autopilot import SimFlightController
from sim.evaluation.metrics import PoseSeries
from sim.scenarios.loader import Scenario, load_scenario
from sim.world.trajectories import make_trajectory
from sim.world.scene import World

log = logging.getLogger(__name__)

_SERVE_TICK_S = 0.002


class Simulation:
    """The flight controller on ``mavlink_url`` and the camera of ``scenario``; with ``forward_url``
    (``udpout:HOST:PORT``) the flight controller forwards what it receives there, as an autopilot
    forwards a companion's messages to its ground-station port."""

    def __init__(
        self, scenario: Scenario, mavlink_url: str, *, realtime: bool = False, duration_s: float | None = None, forward_url: str | None = None,
    ) -> None:
        self.scenario = scenario
        self.clock = RealClock() if realtime else LockstepClock()
        self.trajectory = make_trajectory(scenario.trajectory)
        self.duration_s = duration_s or scenario.duration_s or self.trajectory.duration_s
        self.faults = FaultSchedule(scenario.faults)
        seeds = np.random.SeedSequence(scenario.seed).spawn(2)
        self.fc = SimFlightController(
            mavlink_url, self.trajectory, self.clock, scenario.flight_controller, self.faults, seed=int(seeds[0].generate_state(1)[0]),
            forward_url=forward_url,
        )
        self.world = World.build(scenario.world)
        self.camera = SimCamera(
            scenario.camera, self.world, self.trajectory, self.clock, faults=self.faults,
            seed=int(seeds[1].generate_state(1)[0]), advance=None if realtime else self.advance_to, duration_s=self.duration_s,
        )

    def advance_to(self, t_s: float) -> None:
        """Lockstep: run the flight controller up to ``t_s`` and move the clock there."""
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


def scenario_camera(name_or_path: str, host_clock: HostClock) -> HostTimedCamera:
    """The camera of a scenario, rendering in real time from now, frames stamped on ``host_clock``
    (``camera.source: sim:SCENARIO`` in ``mavvo run``, e.g. beside ArduPilot's SITL). It flies the
    scenario's trajectory whatever the flight controller does, and ends with the scenario."""
    scenario = load_scenario(name_or_path)
    clock = RealClock()
    offset = host_clock.now_s() - clock.now_s()
    trajectory = make_trajectory(scenario.trajectory)
    camera = SimCamera(
        scenario.camera, World.build(scenario.world), trajectory, clock,
        faults=FaultSchedule(scenario.faults), seed=scenario.seed, duration_s=scenario.duration_s,
    )
    return HostTimedCamera(camera, offset)
