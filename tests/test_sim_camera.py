"""The simulated camera's sensor effects seen in its images: rolling shutter, vignetting, a faint floor;
and the simulated rangefinder's dropouts."""

from __future__ import annotations

import cv2
import numpy as np

from mavvo.sim.flight_controller.sensors import range_sample
from mavvo.sim.flight_controller.spec import FlightControllerSpec
from mavvo.sim.world.camera import CameraSpec, SimCamera
from mavvo.sim.world.clock import LockstepClock
from mavvo.sim.world.scene import World, WorldSpec

HEIGHT_M, SPEED_M_S = 2.0, 3.0


class Glide:
    """Level flight east at SPEED_M_S, HEIGHT_M above the ground (the body frame along NED)."""

    duration_s = 10.0

    def pose(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return np.array([0.0, SPEED_M_S * t_s, -HEIGHT_M]), np.eye(3)


def _camera(**spec) -> SimCamera:
    cam = CameraSpec(noise_sigma=0.0, motion_blur=False, **spec)
    return SimCamera(cam, World.build(WorldSpec(texture_seed=2)), Glide(), LockstepClock())


def _shift_x(a: np.ndarray, b: np.ndarray) -> float:
    """How far ``b``'s content lies right of ``a``'s, pixels (phase correlation)."""
    (dx, _), _ = cv2.phaseCorrelate(a.astype(np.float32), b.astype(np.float32))
    return dx


def test_a_rolling_shutter_skews_the_image_by_the_motion_during_the_readout() -> None:
    """Moving east, a nadir camera's image content moves left by fx * v / h pixels per second; each row
    is exposed later than the one above, so the bottom quarter shows the ground further on than the
    top quarter by that rate times the time between them. The middle row is exposed at the frame's
    time: a global shutter's image then."""
    readout_ms = 20.0
    rs, gs = _camera(rolling_shutter_ms=readout_ms), _camera()
    t = 1.0
    img_rs, img_gs = rs.render_at(t), gs.render_at(t)
    h = img_rs.shape[0]
    q = h // 4
    top = _shift_x(img_gs[:q], img_rs[:q])
    bottom = _shift_x(img_gs[-q:], img_rs[-q:])
    rows_apart = h - q  # between the quarters' centre rows
    expected = -gs.spec.fx_px * SPEED_M_S / HEIGHT_M * readout_ms * 1e-3 * rows_apart / (h - 1)
    assert abs((bottom - top) - expected) < 0.1 * abs(expected) + 0.5, (top, bottom, expected)
    assert abs(top + bottom) < 0.1 * abs(expected) + 0.5  # symmetric about the middle row
    assert np.array_equal(_camera(rolling_shutter_ms=0.0).render_at(t), img_gs)


def test_vignetting_darkens_the_corners_by_its_amount() -> None:
    spec = CameraSpec(noise_sigma=0.0, motion_blur=False, vignetting=0.3)
    cam = SimCamera(spec, World.build(WorldSpec(texture="flat")), Glide(), LockstepClock())
    img = cam.render_at(0.5).astype(float)
    centre = img[int(spec.cy_px), int(spec.cx_px)]
    assert abs(centre - 128) <= 1
    for v, u in ((0, 0), (0, -1), (-1, 0), (-1, -1)):
        assert abs(img[v, u] - 0.7 * 128) <= 2, (v, u, img[v, u])


def test_a_faint_floor_keeps_its_pattern_within_the_contrast() -> None:
    full, faint = World.build(WorldSpec(texture_seed=1)), World.build(WorldSpec(texture_seed=1, contrast=0.15))
    for a, b in zip(full.layers, faint.layers):
        assert np.abs(b.tile.astype(int) - 128).max() <= round(0.15 * 128) + 1
        assert np.corrcoef(a.tile.ravel(), b.tile.ravel())[0, 1] > 0.99  # the same pattern, fainter


def test_rangefinder_dropouts_come_at_their_rate_and_only_when_asked_for() -> None:
    n = 4000
    rng = np.random.default_rng(7)
    lossy = FlightControllerSpec(rangefinder_dropout=0.3)
    lost = sum(range_sample(Glide(), 0.1 * k, lossy, rng) is None for k in range(n)) / n
    assert abs(lost - 0.3) < 4 * np.sqrt(0.3 * 0.7 / n), lost
    clean = FlightControllerSpec()
    assert all(range_sample(Glide(), 0.1 * k, clean, rng) is not None for k in range(200))
