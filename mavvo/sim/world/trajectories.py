"""Flight paths with exact truth at any time: position, velocity, acceleration and attitude.

Positions are NED metres with the origin on the ground below the start (z = -altitude). Every path is
smooth to the second derivative, and the attitude is the one a quadrotor needs to fly it: the body's
down axis opposes the specific force (acceleration minus gravity), with the yaw of the path's yaw
profile (Euler 3-2-1, as ATTITUDE reports it). So roll and pitch move with the motion, as on a real
drone. Two families:

- waypoint paths (square, lawnmower, take-off and landing) made of rest-to-rest quintic segments,
  turning in place at corners when the nose follows the path;
- phase paths (hover drift, circle, figure-eight, yaw spin) driven by a phase that ramps smoothly up
  from rest and back down.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar, Literal, Union

import numpy as np

from mavvo.evaluation.metrics import PoseSeries
from mavvo.geometry.frames import euler321_from_R
from mavvo.options import bounded

GRAVITY_M_S2 = 9.80665
_G_NED = np.array([0.0, 0.0, GRAVITY_M_S2])
YawMode = Literal["fixed", "velocity"]


@dataclass(frozen=True)
class TruthState:
    """The true state of the vehicle (body frame FRD) at ``t_s``.

    Attributes:
        p_ned_m, v_ned_m_s, a_ned_m_s2: (3,) position, velocity and acceleration in NED.
        R_ned_body: (3,3) attitude; ``roll_rad, pitch_rad, yaw_rad`` its Euler 3-2-1 angles.
        omega_body_rad_s: (3,) angular velocity in the body frame (roll, pitch, yaw rates).
    """

    t_s: float
    p_ned_m: np.ndarray
    v_ned_m_s: np.ndarray
    a_ned_m_s2: np.ndarray
    R_ned_body: np.ndarray
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    omega_body_rad_s: np.ndarray


class Trajectory(ABC):
    """A flight path defined on [0, duration_s]; outside it the vehicle holds the end state."""

    duration_s: float

    @abstractmethod
    def kinematics(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """(p_ned_m, v_ned_m_s, a_ned_m_s2, yaw_rad, yaw_rate_rad_s) at ``t_s`` in [0, duration_s]."""

    def pose(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(p_ned_m, R_ned_body) at ``t_s``: what a camera or a rangefinder needs, without the rates."""
        t = min(max(float(t_s), 0.0), self.duration_s)
        p, _, a, yaw, _ = self.kinematics(t)
        return p, attitude_from_acceleration(a, yaw)

    def state(self, t_s: float) -> TruthState:
        """The full truth at ``t_s``."""
        t = min(max(float(t_s), 0.0), self.duration_s)
        p, v, a, yaw, _ = self.kinematics(t)
        R = attitude_from_acceleration(a, yaw)
        h = 1e-4
        dR = self.pose(t + h)[1] - self.pose(t - h)[1]
        W = R.T @ dR / (2 * h)
        omega = np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]]) / 2
        roll, pitch, yaw_ = euler321_from_R(R)
        return TruthState(t, p, v, a, R, roll, pitch, yaw_, omega)

    def truth_series(
        self, times_s: np.ndarray, lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ) -> PoseSeries:
        """Positions of the point ``lever_arm_m`` (body FRD, metres; the camera centre) and the body's
        orientations at ``times_s``: what a vision estimate estimates."""
        times = np.asarray(times_s, dtype=float)
        lever = np.asarray(lever_arm_m, dtype=float)
        poses = [self.pose(t) for t in times]
        p = np.array([p + R @ lever for p, R in poses]).reshape(-1, 3)
        R = np.array([R for _, R in poses]).reshape(-1, 3, 3)
        return PoseSeries.from_rotations(times, p, R)

    def path_length_m(self, step_s: float = 0.05) -> float:
        """Length of the flown path (3D), by summing small steps."""
        t = np.arange(0.0, self.duration_s + step_s, step_s)
        p = np.array([self.kinematics(min(ti, self.duration_s))[0] for ti in t])
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def attitude_from_acceleration(a_ned_m_s2: np.ndarray, yaw_rad: float) -> np.ndarray:
    """R_ned_body of a quadrotor accelerating at ``a_ned_m_s2`` with heading ``yaw_rad``: body down
    along gravity minus acceleration, body x in the vertical plane of the heading."""
    z_b = _G_NED - a_ned_m_s2
    z_b = z_b / np.linalg.norm(z_b)
    y_c = np.array([-np.sin(yaw_rad), np.cos(yaw_rad), 0.0])
    x_b = np.cross(y_c, z_b)
    x_b /= np.linalg.norm(x_b)
    y_b = np.cross(z_b, x_b)
    return np.column_stack([x_b, y_b, z_b])


# ---------------------------------------------------------------------------------------- primitives


def _smoothstep(tau: float) -> tuple[float, float, float]:
    """Quintic rest-to-rest profile s(tau) on [0,1] and its first two derivatives."""
    t = min(max(tau, 0.0), 1.0)
    s = t**3 * (10 - 15 * t + 6 * t * t)
    ds = 30 * t * t * (1 - t) ** 2
    dds = 60 * t * (1 - t) * (1 - 2 * t)
    return s, ds, dds


_PEAK_RATE = 1.875  # max of ds: a segment of length D in time T peaks at 1.875 D / T


@dataclass(frozen=True)
class _Segment:
    t0_s: float
    duration_s: float
    p0: np.ndarray
    p1: np.ndarray
    yaw0: float
    yaw1: float


class WaypointTrajectory(Trajectory):
    """Rest-to-rest quintic segments between waypoints (NED), at most ``speed_m_s``.

    With ``yaw="velocity"`` the vehicle turns in place at each waypoint to face the next leg (at most
    ``yaw_rate_deg_s``); with ``"fixed"`` it keeps ``yaw_deg``. ``dwell_s`` is spent at each waypoint,
    ``hold_first_s`` at the first before anything moves.
    """

    def __init__(
        self,
        waypoints_ned_m: np.ndarray,
        speed_m_s: float,
        yaw: YawMode = "fixed",
        yaw_deg: float = 0.0,
        yaw_rate_deg_s: float = 45.0,
        dwell_s: float = 0.0,
        hold_first_s: float = 0.0,
    ) -> None:
        wp = np.asarray(waypoints_ned_m, dtype=float)
        if wp.ndim != 2 or wp.shape[1] != 3 or len(wp) < 2:
            raise ValueError(f"waypoints_ned_m: expected (K,3) with K >= 2, got shape {wp.shape}")
        segs: list[_Segment] = []
        t = 0.0
        heading = np.radians(yaw_deg)
        if yaw == "velocity":
            heading = _leg_heading(wp, 0, heading)
        if hold_first_s > 0:  # standing at the first waypoint (on the ground, before take-off)
            segs.append(_Segment(t, hold_first_s, wp[0], wp[0], heading, heading))
            t += hold_first_s
        for i in range(len(wp) - 1):
            target = _leg_heading(wp, i, heading) if yaw == "velocity" else heading
            turn = _wrap(target - heading)
            if abs(turn) > 1e-9:
                T = max(_PEAK_RATE * abs(turn) / np.radians(yaw_rate_deg_s), 0.5)
                segs.append(_Segment(t, T, wp[i], wp[i], heading, heading + turn))
                t += T
                heading += turn
            d = float(np.linalg.norm(wp[i + 1] - wp[i]))
            if d > 0:
                T = max(_PEAK_RATE * d / speed_m_s, 0.5)
                segs.append(_Segment(t, T, wp[i], wp[i + 1], heading, heading))
                t += T
            if dwell_s > 0:
                segs.append(_Segment(t, dwell_s, wp[i + 1], wp[i + 1], heading, heading))
                t += dwell_s
        self._segments = segs
        self._starts = np.array([s.t0_s for s in segs])
        self.duration_s = t

    def kinematics(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        i = max(int(np.searchsorted(self._starts, t_s, side="right")) - 1, 0)
        s = self._segments[i]
        u, du, ddu = _smoothstep((t_s - s.t0_s) / s.duration_s)
        d = s.p1 - s.p0
        T = s.duration_s
        dyaw = s.yaw1 - s.yaw0
        return s.p0 + d * u, d * du / T, d * ddu / T**2, float(_wrap(s.yaw0 + dyaw * u)), dyaw * du / T


def _leg_heading(wp: np.ndarray, i: int, current: float) -> float:
    d = wp[i + 1] - wp[i]
    if np.hypot(d[0], d[1]) < 1e-6:
        return current  # vertical leg: keep the heading
    return float(np.arctan2(d[1], d[0]))


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


class _Phase:
    """A phase that ramps from rest to ``rate`` in ``ramp_s``, cruises, and ramps back to rest, ending
    at ``total`` (phase units); gives (phase, rate, acceleration) at any time."""

    def __init__(self, total: float, rate: float, ramp_s: float) -> None:
        self.rate = rate
        self.ramp_s = ramp_s
        cruise = total / rate - ramp_s  # each ramp covers rate * ramp_s / 2
        if cruise < 0:
            raise ValueError("phase path too short for its ramps; lower the speed or lengthen the path")
        self.cruise_s = cruise
        self.duration_s = 2 * ramp_s + cruise

    def at(self, t: float) -> tuple[float, float, float]:
        w, Tr = self.rate, self.ramp_s
        t = min(max(t, 0.0), self.duration_s)
        if t < Tr:
            tau = t / Tr
            s, ds, _ = _smoothstep(tau)
            return w * Tr * (2.5 * tau**4 - 3 * tau**5 + tau**6), w * s, w * ds / Tr
        if t <= Tr + self.cruise_s:
            return w * (0.5 * Tr + t - Tr), w, 0.0
        tau = (self.duration_s - t) / Tr
        s, ds, _ = _smoothstep(tau)
        total = w * (Tr + self.cruise_s)
        return total - w * Tr * (2.5 * tau**4 - 3 * tau**5 + tau**6), w * s, -w * ds / Tr


class PhaseTrajectory(Trajectory):
    """A closed or open path P(phase) (NED) flown with a smoothly ramped phase.

    ``path(phase) -> (P, dP, ddP)`` gives the point and its first two derivatives in phase.
    ``yaw`` is ``"velocity"`` (nose along the path tangent) or ``"fixed"`` (``yaw_deg``), or a callable
    ``yaw(phase) -> (yaw, dyaw/dphase)``.
    """

    def __init__(self, path, phase: _Phase, yaw: YawMode = "fixed", yaw_deg: float = 0.0) -> None:
        self._path = path
        self._phase = phase
        self._yaw = yaw
        self._yaw0 = np.radians(yaw_deg)
        self.duration_s = phase.duration_s

    def kinematics(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        ph, dph, ddph = self._phase.at(t_s)
        P, dP, ddP = self._path(ph)
        v = dP * dph
        a = ddP * dph**2 + dP * ddph
        if callable(self._yaw):
            yaw, dyaw = self._yaw(ph)
            return P, v, a, yaw, dyaw * dph
        if self._yaw == "velocity":
            n2 = dP[0] ** 2 + dP[1] ** 2
            yaw = float(np.arctan2(dP[1], dP[0]))
            return P, v, a, yaw, (dP[0] * ddP[1] - dP[1] * ddP[0]) / n2 * dph
        return P, v, a, float(self._yaw0), 0.0


# ---------------------------------------------------------------------------------------- specs


@dataclass(frozen=True)
class HoverSpec:
    """Hover over the origin, drifting slowly as a position-holding drone does."""

    TYPE: ClassVar[str] = "hover"

    altitude_m: float = bounded(10.0, "height above the ground", gt=0)
    duration_s: float = bounded(60.0, "length of the hover", gt=0)
    drift_m: float = bounded(0.5, "amplitude of the horizontal drift", ge=0)
    drift_period_s: float = bounded(12.0, "typical period of the drift", gt=0)
    yaw_deg: float = bounded(0.0, "heading")
    seed: int = bounded(0, "seed of the drift's phases", ge=0)


@dataclass(frozen=True)
class SquareSpec:
    """A square flown corner to corner, stopping at each corner."""

    TYPE: ClassVar[str] = "square"

    altitude_m: float = bounded(10.0, "height above the ground", gt=0)
    side_m: float = bounded(20.0, "side of the square", gt=0)
    speed_m_s: float = bounded(3.0, "top speed on each side", gt=0)
    laps: int = bounded(1, "times around", ge=1)
    yaw: YawMode = bounded("fixed", "fixed: keep yaw_deg; velocity: turn at the corners to face the next side")
    yaw_deg: float = bounded(0.0, "heading when yaw is fixed")
    dwell_s: float = bounded(0.5, "pause at each corner", ge=0)
    ground_s: float = bounded(
        0.0, "time standing on the ground below the first corner, then a climb to altitude (0: start at altitude)", ge=0
    )
    ground_height_m: float = bounded(0.3, "camera height on the ground (landing gear)", gt=0)


@dataclass(frozen=True)
class FigureEightSpec:
    """A figure-eight (1:2 Lissajous) flown without stopping."""

    TYPE: ClassVar[str] = "figure_eight"

    altitude_m: float = bounded(10.0, "height above the ground", gt=0)
    length_m: float = bounded(40.0, "extent along north", gt=0)
    speed_m_s: float = bounded(4.0, "cruise speed at the crossing", gt=0)
    laps: int = bounded(1, "times around", ge=1)
    ramp_s: float = bounded(3.0, "time to reach cruise speed from rest, and to stop", gt=0)
    yaw: YawMode = bounded("fixed", "fixed or velocity (nose along the path)")
    yaw_deg: float = bounded(0.0, "heading when yaw is fixed")


@dataclass(frozen=True)
class LawnmowerSpec:
    """A survey: parallel legs along north, stepping east between them."""

    TYPE: ClassVar[str] = "lawnmower"

    altitude_m: float = bounded(30.0, "height above the ground", gt=0)
    leg_m: float = bounded(60.0, "length of each leg", gt=0)
    spacing_m: float = bounded(10.0, "distance between legs", gt=0)
    legs: int = bounded(4, "number of legs", ge=1)
    speed_m_s: float = bounded(4.0, "top speed", gt=0)
    yaw: YawMode = bounded("fixed", "fixed or velocity (turn to face each leg)")
    yaw_deg: float = bounded(0.0, "heading when yaw is fixed")
    dwell_s: float = bounded(0.5, "pause at each turn", ge=0)


@dataclass(frozen=True)
class TakeoffLandingSpec:
    """Take off from the ground, hover, and land."""

    TYPE: ClassVar[str] = "takeoff_landing"

    altitude_m: float = bounded(10.0, "hover height", gt=0)
    start_height_m: float = bounded(0.3, "camera height on the ground (landing gear)", gt=0)
    climb_rate_m_s: float = bounded(1.0, "top climb and descent rate", gt=0)
    hover_s: float = bounded(5.0, "time at the top", ge=0)
    yaw_deg: float = bounded(0.0, "heading")


@dataclass(frozen=True)
class YawSpinSpec:
    """Spin fast about the vertical while hovering."""

    TYPE: ClassVar[str] = "yaw_spin"

    altitude_m: float = bounded(10.0, "height above the ground", gt=0)
    rate_deg_s: float = bounded(120.0, "cruise yaw rate", gt=0)
    turns: float = bounded(2.0, "number of full turns", gt=0)
    ramp_s: float = bounded(1.0, "time to reach the yaw rate, and to stop", gt=0)
    drift_m: float = bounded(0.0, "amplitude of the horizontal drift while spinning (as a hover's)", ge=0)
    drift_period_s: float = bounded(12.0, "typical period of the drift", gt=0)
    seed: int = bounded(0, "seed of the drift's phases", ge=0)


@dataclass(frozen=True)
class CircleSpec:
    """A circle flown without stopping; with ``yaw: velocity`` a forward camera looks along the path."""

    TYPE: ClassVar[str] = "circle"

    altitude_m: float = bounded(5.0, "height above the ground", gt=0)
    radius_m: float = bounded(20.0, "radius", gt=0)
    speed_m_s: float = bounded(3.0, "cruise speed", gt=0)
    laps: float = bounded(1.0, "times around", gt=0)
    ramp_s: float = bounded(3.0, "time to reach cruise speed from rest, and to stop", gt=0)
    yaw: YawMode = bounded("velocity", "velocity (nose along the path) or fixed")
    yaw_deg: float = bounded(0.0, "heading when yaw is fixed")


@dataclass(frozen=True)
class HopsSpec:
    """A small quad indoors: around a rectangle, hopping between two heights at every waypoint (the
    corners and the middle of each side), stopping at each."""

    TYPE: ClassVar[str] = "hops"

    low_m: float = bounded(0.4, "the low height", gt=0)
    high_m: float = bounded(1.5, "the high height", gt=0)
    length_m: float = bounded(4.0, "the rectangle along north", gt=0)
    width_m: float = bounded(2.0, "the rectangle along east", gt=0)
    speed_m_s: float = bounded(1.0, "top speed between waypoints", gt=0)
    laps: int = bounded(1, "times around", ge=1)
    dwell_s: float = bounded(0.3, "pause at each waypoint", ge=0)
    yaw_deg: float = bounded(0.0, "heading")


TrajectorySpec = Union[
    HoverSpec, SquareSpec, FigureEightSpec, LawnmowerSpec, TakeoffLandingSpec, YawSpinSpec, CircleSpec, HopsSpec
]

TRAJECTORY_SPECS: dict[str, type] = {c.TYPE: c for c in TrajectorySpec.__args__}


def make_trajectory(spec: TrajectorySpec) -> Trajectory:
    """The trajectory a spec describes."""
    if isinstance(spec, HoverSpec):
        return HoverTrajectory(spec)
    if isinstance(spec, SquareSpec):
        s, z = spec.side_m, -spec.altitude_m
        corners = [[0, 0, z], [s, 0, z], [s, s, z], [0, s, z]]
        ground = [[0, 0, -spec.ground_height_m]] if spec.ground_s > 0 else []
        wp = np.array(ground + corners * spec.laps + [corners[0]], dtype=float)
        return WaypointTrajectory(
            wp, spec.speed_m_s, spec.yaw, spec.yaw_deg, dwell_s=spec.dwell_s, hold_first_s=spec.ground_s
        )
    if isinstance(spec, LawnmowerSpec):
        z = -spec.altitude_m
        wp = []
        for k in range(spec.legs):
            ends = [0.0, spec.leg_m] if k % 2 == 0 else [spec.leg_m, 0.0]
            wp += [[ends[0], k * spec.spacing_m, z], [ends[1], k * spec.spacing_m, z]]
        return WaypointTrajectory(np.array(wp), spec.speed_m_s, spec.yaw, spec.yaw_deg, dwell_s=spec.dwell_s)
    if isinstance(spec, TakeoffLandingSpec):
        lo, hi = -spec.start_height_m, -spec.altitude_m
        wp = np.array([[0, 0, lo], [0, 0, hi], [0, 0, lo]], dtype=float)
        return WaypointTrajectory(wp, spec.climb_rate_m_s, "fixed", spec.yaw_deg, dwell_s=spec.hover_s)
    if isinstance(spec, HopsSpec):
        L, W = spec.length_m, spec.width_m
        ring = [[0, 0], [L / 2, 0], [L, 0], [L, W / 2], [L, W], [L / 2, W], [0, W], [0, W / 2]] * spec.laps + [[0, 0]]
        wp = np.array([[n, e, -(spec.low_m if k % 2 == 0 else spec.high_m)] for k, (n, e) in enumerate(ring)])
        return WaypointTrajectory(wp, spec.speed_m_s, "fixed", spec.yaw_deg, dwell_s=spec.dwell_s)
    if isinstance(spec, FigureEightSpec):
        A = spec.length_m / 2
        z = -spec.altitude_m

        def eight(ph: float):
            s1, c1, s2, c2 = np.sin(ph), np.cos(ph), np.sin(2 * ph), np.cos(2 * ph)
            return (
                np.array([A * s1, A / 2 * s2, z]),
                np.array([A * c1, A * c2, 0.0]),
                np.array([-A * s1, -2 * A * s2, 0.0]),
            )

        rate = spec.speed_m_s / (A * np.sqrt(2.0))
        return PhaseTrajectory(eight, _Phase(2 * np.pi * spec.laps, rate, spec.ramp_s), spec.yaw, spec.yaw_deg)
    if isinstance(spec, CircleSpec):
        r, z = spec.radius_m, -spec.altitude_m

        def circle(ph: float):
            s, c = np.sin(ph), np.cos(ph)
            return np.array([r * s, r * (1 - c), z]), np.array([r * c, r * s, 0.0]), np.array([-r * s, r * c, 0.0])

        return PhaseTrajectory(
            circle, _Phase(2 * np.pi * spec.laps, spec.speed_m_s / r, spec.ramp_s), spec.yaw, spec.yaw_deg
        )
    if isinstance(spec, YawSpinSpec):
        z = -spec.altitude_m

        def still(ph: float):
            return np.array([0.0, 0.0, z]), np.zeros(3), np.zeros(3)

        spin = PhaseTrajectory(
            still,
            _Phase(2 * np.pi * spec.turns, np.radians(spec.rate_deg_s), spec.ramp_s),
            yaw=lambda ph: (_wrap(ph), 1.0),
        )
        return (
            _Drifting(spin, _Drift(np.zeros(3), spec.drift_m, spec.drift_period_s, spec.seed))
            if spec.drift_m > 0
            else spin
        )
    raise TypeError(f"make_trajectory: unknown spec {type(spec).__name__}")


class _Drift:
    """A position-holding drone's slow wander about ``center_ned_m``: two sines per axis (vertical a
    fifth of the horizontal), random periods and phases from the seed, exactly at the centre at t = 0."""

    def __init__(self, center_ned_m: np.ndarray, drift_m: float, period_s: float, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self._w = 2 * np.pi / (period_s * rng.uniform(0.6, 1.6, (3, 2)))
        self._phases = rng.uniform(0, 2 * np.pi, (3, 2))
        self._amps = drift_m / 2 * np.array([[1.0, 1.0], [1.0, 1.0], [0.2, 0.2]]) * rng.uniform(0.7, 1.0, (3, 2))
        self._base = center_ned_m - (self._amps * np.sin(self._phases)).sum(axis=1)

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_ned_m, v_ned_m_s, a_ned_m_s2) at ``t_s``."""
        arg = self._w * t_s + self._phases
        A, w = self._amps, self._w
        return (
            self._base + (A * np.sin(arg)).sum(axis=1),
            (A * w * np.cos(arg)).sum(axis=1),
            -(A * w * w * np.sin(arg)).sum(axis=1),
        )


class HoverTrajectory(Trajectory):
    """Hover at (0, 0, -altitude) with a slow drift (:class:`_Drift`)."""

    def __init__(self, spec: HoverSpec) -> None:
        self._drift = _Drift(np.array([0.0, 0.0, -spec.altitude_m]), spec.drift_m, spec.drift_period_s, spec.seed)
        self._yaw = float(np.radians(spec.yaw_deg))
        self.duration_s = spec.duration_s

    def kinematics(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        p, v, a = self._drift.at(t_s)
        return p, v, a, self._yaw, 0.0


class _Drifting(Trajectory):
    """A path with a hover's drift (:class:`_Drift` about the origin) added to it."""

    def __init__(self, path: Trajectory, drift: _Drift) -> None:
        self._path, self._drift = path, drift
        self.duration_s = path.duration_s

    def kinematics(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        p, v, a, yaw, yaw_rate = self._path.kinematics(t_s)
        dp, dv, da = self._drift.at(t_s)
        return p + dp, v + dv, a + da, yaw, yaw_rate
