"""Paired frames of a scenario straight from the truth, without MAVLink: for the odometry's tests and
the pipeline benchmark, where the link and timing layers are not under test.

Each frame is rendered by the scenario's camera (lockstep, so runs repeat exactly) and paired with
what the flight controller's sensors would report at its exposure time (:mod:`mavvo.sim.flight_controller.sensors`): roll,
pitch and yaw with the scenario's noise and bias, the rangefinder and the barometric height. Frames whose
attitude a ``nan_attitude`` fault spoils are skipped, as the daemon skips them.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from mavvo.errors import CameraError
from mavvo.evaluation.metrics import PoseSeries
from mavvo.sim.flight_controller.sensors import attitude_sample, baro_height_sample, range_sample
from mavvo.sim.scenarios.loader import Scenario
from mavvo.sim.world.camera import SimCamera
from mavvo.sim.world.clock import LockstepClock
from mavvo.sim.world.faults import FaultSchedule
from mavvo.sim.world.scene import World
from mavvo.sim.world.trajectories import make_trajectory
from mavvo.types import PairedFrame


class PairedSequence:
    """The paired frames of ``scenario`` up to ``duration_s`` (default: the scenario's)."""

    def __init__(self, scenario: Scenario, *, duration_s: float | None = None) -> None:
        self.scenario = scenario
        self.trajectory = make_trajectory(scenario.trajectory)
        self.duration_s = duration_s or scenario.duration_s or self.trajectory.duration_s
        self.faults = FaultSchedule(scenario.faults)
        clock = LockstepClock()
        # The same seed split as the MAVLink simulation: the camera's noise matches frame for frame.
        seeds = np.random.SeedSequence(scenario.seed).spawn(2)
        self.camera = SimCamera(
            scenario.camera,
            World.build(scenario.world),
            self.trajectory,
            clock,
            faults=self.faults,
            seed=int(seeds[1].generate_state(1)[0]),
            advance=clock.advance_to,
            duration_s=self.duration_s,
        )
        self._rng = np.random.default_rng(seeds[0])
        self._baro_bias_m = float(self._rng.normal(0.0, 0.5))
        self.skipped = 0

    @property
    def R_body_cam(self) -> np.ndarray:
        return self.scenario.camera.R_body_cam()

    def __iter__(self) -> Iterator[PairedFrame]:
        fc = self.scenario.flight_controller
        while True:
            try:
                frame = self.camera.read(timeout_s=1.0)
            except CameraError:
                return
            if frame is None:
                continue
            t = frame.t_exposure_s
            roll, pitch, yaw, _ = attitude_sample(self.trajectory, t, fc, self._rng)
            if self.faults.active("nan_attitude", t):
                self.skipped += 1
                continue
            rng_m = range_sample(self.trajectory, t, fc, self._rng) if fc.rangefinder else None
            height = baro_height_sample(self.trajectory, t, fc, self._baro_bias_m, self._rng)
            yield PairedFrame(frame.image, t, frame.seq, roll, pitch, yaw, rng_m, height)

    def camera_truth(self, times_s: np.ndarray) -> PoseSeries:
        """True camera-centre positions and body orientations at ``times_s``: what a
        :class:`mavvo.types.PoseEstimate` estimates."""
        return self.trajectory.truth_series(times_s, self.scenario.camera.lever_arm_m)
