"""The simulated camera: a :class:`mavvo.service.camera.FrameSource` that renders the world at the true pose of
each exposure and stamps the frame with its exposure time on the simulation clock.

In lockstep, ``read`` first advances the simulation (the flight controller's streams) to the moment
the frame would reach the companion computer (exposure plus ``readout_latency_ms``), then hands the
frame out at once. In real time it sleeps until that moment, and drops frames it fell behind on, as
a real camera driver does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal, Protocol

import numpy as np

from mavvo.errors import CameraEnded, CameraError
from mavvo.geometry.camera_model import CameraIntrinsics
from mavvo.options import bounded
from mavvo.sim.world.clock import Clock
from mavvo.sim.world.faults import FaultSchedule
from mavvo.sim.world.render import Renderer, apply_effects
from mavvo.sim.world.scene import World
from mavvo.sim.world.trajectories import Trajectory
from mavvo.sim.world.twoview import mount_rotation
from mavvo.types import Frame

_DARK_GAIN = 0.05


class HostClock(Protocol):
    def now_s(self) -> float: ...


_TEXTURELESS_LEVEL = 120
# Bands of a rolling-shutter image: at 320x240, 1 m/s and 0.4 m (575 px/s) with a 20 ms readout the
# image moves 0.7 px from one band to the next.
_ROLLING_BANDS = 16


def _vignette(spec: CameraSpec) -> np.ndarray:
    """(H,W) float32 gain: 1 at the principal point, 1 - vignetting at the farthest corner, falling off
    with the squared distance (a cos^4 law's first term)."""
    v, u = np.mgrid[0 : spec.height_px, 0 : spec.width_px].astype(np.float32)
    r2 = (u - spec.cx_px) ** 2 + (v - spec.cy_px) ** 2
    return (1.0 - spec.vignetting * r2 / r2.max()).astype(np.float32)


@dataclass(frozen=True)
class CameraSpec(CameraIntrinsics):
    """The simulated camera: intrinsics (:class:`CameraIntrinsics`), mounting, timing and image effects."""

    mount: Literal["nadir", "forward", "oblique"] = bounded(
        "nadir", "nadir: down, image top forward; forward: along the nose; oblique: forward, pitched down"
    )
    oblique_depression_deg: float = bounded(45.0, "oblique mount: angle below the horizon", ge=0, le=90)
    lever_arm_m: tuple[float, float, float] = bounded((0.0, 0.0, 0.0), "camera centre in the body frame (FRD)")
    rate_hz: float = bounded(20.0, "frames per second", gt=0, le=240)
    exposure_ms: float = bounded(4.0, "exposure time (sets the motion blur)", ge=0)
    readout_latency_ms: float = bounded(20.0, "from mid-exposure until the frame reaches the host", ge=0)
    noise_sigma: float = bounded(2.0, "Gaussian pixel noise, grey levels", ge=0)
    motion_blur: bool = bounded(True, "blur along the image motion during the exposure")
    gain_variation: float = bounded(0.0, "auto-exposure wander: relative amplitude of a slow gain change", ge=0, lt=1)
    gain_period_s: float = bounded(10.0, "period of the gain change", gt=0)
    rolling_shutter_ms: float = bounded(
        0.0,
        "rolling shutter: time from the first row's exposure to the last's (0: a global shutter); the frame's time is its middle row's",
        ge=0,
        le=100,
    )
    vignetting: float = bounded(0.0, "how much darker the image corners are than its centre (0.3: 30%)", ge=0, lt=1)

    def R_body_cam(self) -> np.ndarray:
        return mount_rotation(self.mount, np.radians(self.oblique_depression_deg))


class SimCamera:
    """Renders frames of ``world`` along ``trajectory`` on ``clock`` (see the module docstring).

    Args:
        advance: called with a simulation time before each frame in lockstep (the simulation's
            ``advance_to``); None in real time, where another thread drives the flight controller.
        duration_s: no frames after this time; ``read`` then raises CameraEnded.
    """

    def __init__(
        self,
        spec: CameraSpec,
        world: World,
        trajectory: Trajectory,
        clock: Clock,
        *,
        faults: FaultSchedule | None = None,
        seed: int = 0,
        advance: Callable[[float], None] | None = None,
        duration_s: float | None = None,
    ) -> None:
        self.spec = spec
        self.model = spec.camera_model()
        self.renderer = Renderer(world, self.model)
        self.trajectory = trajectory
        self.clock = clock
        self.faults = faults or FaultSchedule()
        self._advance = advance
        self._rng = np.random.default_rng(seed)
        self._R_body_cam = spec.R_body_cam()
        self._lever = np.asarray(spec.lever_arm_m, dtype=float)
        self._period_s = 1.0 / spec.rate_hz
        self._latency_s = spec.readout_latency_ms * 1e-3
        self._duration_s = trajectory.duration_s if duration_s is None else duration_s
        self._next = 0
        self.dropped = 0
        self._vignette = _vignette(spec) if spec.vignetting > 0 else None
        self._closed = False

    def camera_pose(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(R_ned_cam, p_ned_cam_m) at ``t_s``."""
        p, R = self.trajectory.pose(t_s)
        return R @ self._R_body_cam, p + R @ self._lever

    def skip_to(self, t_s: float) -> None:
        """Skip ahead: the next frame read is the first exposed at or after ``t_s`` (a frame source
        that starts mid-flight). Skipped frames are not counted as dropped."""
        self._next = max(self._next, int(np.ceil(t_s / self._period_s - 1e-9)))

    def read(self, timeout_s: float) -> Frame | None:
        """The next frame (see the module docstring); CameraEnded after the scenario's end."""
        if self._closed:
            raise CameraError("simulated camera: read after close")
        while True:
            k = self._next
            t_exp = k * self._period_s
            if t_exp > self._duration_s:
                raise CameraEnded(f"simulated camera: the scenario ended at {self._duration_s:.1f} s")
            t_ready = t_exp + self._latency_s
            missing = self.faults.active("frames_missing", t_exp)
            image = None
            if self.clock.realtime:
                now = self.clock.now_s()
                behind = int((now - t_ready) // self._period_s)
                if behind > 0:  # keep only the newest frame, as a driver with a short queue does
                    self.dropped += behind
                    self._next += behind
                    continue
                if t_ready - now > timeout_s:
                    self.clock.sleep_until(now + timeout_s)
                    return None
            elif self._advance is not None:
                if not missing:  # rendered before the advance, which may wait for the service's previous frame
                    image = self.render_at(t_exp)
                self._advance(t_ready)
            self.clock.sleep_until(t_ready)
            self._next += 1
            if missing:
                continue
            return Frame(self.render_at(t_exp) if image is None else image, t_exp, k)

    def render_at(self, t_exp_s: float) -> np.ndarray:
        """The (H,W) uint8 image exposed at ``t_exp_s``, with the configured effects and faults."""
        spec = self.spec
        if self.faults.active("textureless_frames", t_exp_s):
            img = np.full((spec.height_px, spec.width_px), _TEXTURELESS_LEVEL, np.uint8)
            return apply_effects(img, noise_sigma=spec.noise_sigma, rng=self._rng)
        R, p = self.camera_pose(t_exp_s)
        img = self.renderer.render(R, p) if spec.rolling_shutter_ms <= 0 else self._rolling(t_exp_s)
        gain = 1.0 + spec.gain_variation * np.sin(2 * np.pi * t_exp_s / spec.gain_period_s)
        if self._vignette is not None:
            gain = gain * self._vignette
        if self.faults.active("dark_frames", t_exp_s):
            gain *= _DARK_GAIN
        blur = self._blur_px(t_exp_s, R, p) if spec.motion_blur and spec.exposure_ms > 0 else (0.0, 0.0)
        return apply_effects(img, gain=gain, blur_px=blur, noise_sigma=spec.noise_sigma, rng=self._rng)

    def _rolling(self, t_exp_s: float) -> np.ndarray:
        """The image of a rolling shutter: each band of rows rendered at the pose of its own exposure
        time, the middle row at ``t_exp_s``; enough bands that the image moves under a pixel between
        neighbours at 1 m/s over the nearest ground (_ROLLING_BANDS)."""
        h = self.spec.height_px
        readout_s = self.spec.rolling_shutter_ms * 1e-3
        out = np.empty((h, self.spec.width_px), np.uint8)
        edges = np.linspace(0, h, _ROLLING_BANDS + 1).round().astype(int)
        for top, bottom in zip(edges[:-1], edges[1:]):
            row = 0.5 * (top + bottom - 1)
            R, p = self.camera_pose(t_exp_s + readout_s * (row / (h - 1) - 0.5))
            out[top:bottom] = self.renderer.render(R, p)[top:bottom]
        return out

    def _blur_px(self, t_s: float, R: np.ndarray, p: np.ndarray) -> tuple[float, float]:
        """Image motion over the exposure of the point seen at the image centre from pose (R, p) at
        ``t_s``, pixels."""
        centre = self.model.pixels_to_bearings(np.array([[self.model.cx_px, self.model.cy_px]]))[0]
        ray = R @ centre
        depth = -p[2] / ray[2] if ray[2] > 0.05 else 50.0
        X = p + depth * ray
        half = self.spec.exposure_ms * 5e-4
        uv = []
        for t in (t_s - half, t_s + half):
            Rt, pt = self.camera_pose(t)
            uv.append(self.model.bearings_to_pixels(((X - pt) @ Rt)[None])[0])
        d = uv[1] - uv[0]
        return (float(d[0]), float(d[1])) if np.all(np.isfinite(d)) else (0.0, 0.0)

    def close(self) -> None:
        self._closed = True


class HostTimedCamera:
    """A simulated camera on its own real-time clock, its frames restamped on the host clock."""

    def __init__(self, camera: SimCamera, offset_s: float) -> None:
        self.camera = camera
        self.offset_s = offset_s

    def read(self, timeout_s: float) -> Frame | None:
        f = self.camera.read(timeout_s)
        return None if f is None else Frame(f.image, f.t_exposure_s + self.offset_s, f.seq)

    def close(self) -> None:
        self.camera.close()
