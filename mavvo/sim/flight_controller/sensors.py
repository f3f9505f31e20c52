"""What the flight controller's sensors report, drawn from the truth: attitude, rangefinder, barometer.

Pure functions of the trajectory, the time, the flight controller's spec and a random generator, so
the MAVLink flight controller and the paired-frame sequences (which skip MAVLink) report alike.
"""

from __future__ import annotations

import numpy as np

from mavvo.sim.flight_controller.spec import FlightControllerSpec
from mavvo.sim.world.trajectories import Trajectory


def attitude_sample(
    trajectory: Trajectory, t_s: float, spec: FlightControllerSpec, rng: np.random.Generator
) -> tuple[float, float, float, np.ndarray]:
    """(roll_rad, pitch_rad, yaw_rad, omega_body_rad_s) measured at ``t_s``: the truth plus Gaussian
    noise and the roll/pitch bias; yaw wrapped to [-pi, pi)."""
    s = trajectory.state(t_s)
    sig = np.radians(spec.attitude_noise_deg)
    bias = np.radians(spec.attitude_bias_deg)
    n = rng.standard_normal(3)
    roll = float(s.roll_rad + bias[0] + sig * n[0])
    pitch = float(s.pitch_rad + bias[1] + sig * n[1])
    yaw = float((s.yaw_rad + np.radians(spec.yaw_noise_deg) * n[2] + np.pi) % (2 * np.pi) - np.pi)
    return roll, pitch, yaw, s.omega_body_rad_s


def range_sample(
    trajectory: Trajectory, t_s: float, spec: FlightControllerSpec, rng: np.random.Generator
) -> float | None:
    """A downward laser's distance along the body z axis to the ground plane (boxes are not seen), with
    noise; None when out of the sensor's range, tilted beyond ~84 deg, or dropped."""
    p, R = trajectory.pose(t_s)
    cos_tilt = R[2, 2]
    if cos_tilt <= 0.1:
        return None
    if spec.rangefinder_dropout > 0 and rng.random() < spec.rangefinder_dropout:
        return None  # drawn only when asked for: scenarios without dropouts keep their noise
    r = float(-p[2] / cos_tilt + rng.normal(0.0, spec.rangefinder_noise_m))
    return r if spec.rangefinder_min_m <= r <= spec.rangefinder_max_m else None


def baro_height_sample(
    trajectory: Trajectory, t_s: float, spec: FlightControllerSpec, bias_m: float, rng: np.random.Generator
) -> float:
    """Barometric height above the start's ground, metres: truth plus a fixed bias plus noise."""
    p, _ = trajectory.pose(t_s)
    return float(-p[2] + bias_m + rng.normal(0.0, spec.baro_noise_m))
