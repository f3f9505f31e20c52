"""A rolling shutter's skew undone: tracks moved to the frame's time by their own velocity, or by the
affine field of the others for a track born in the frame."""

from __future__ import annotations

import numpy as np
import pytest

from mavvo.odometry.frontend import Tracks
from mavvo.odometry.rolling_shutter import RollingShutter
from mavvo.sim.world.camera import CameraSpec

CAMERA = CameraSpec(width_px=320, height_px=240, fx_px=230.0, fy_px=230.0, cx_px=159.5, cy_px=119.5).camera_model()
READOUT_S = 0.015
H = CAMERA.height_px


def _velocity(uv: np.ndarray) -> np.ndarray:
    """An affine image velocity field (px/s): a drift, a zoom and a turn, as a hop and a yaw give."""
    c = uv - [159.5, 119.5]
    return np.array([250.0, -120.0]) + 0.8 * c + 0.3 * c[:, ::-1] * [-1, 1]


def _seen(uv_at_frame_time: np.ndarray) -> np.ndarray:
    """Where a rolling shutter records points that are at ``uv_at_frame_time`` at the frame's time:
    row r is read readout (r / (H - 1) - 1/2) later, by when the point has moved on (solved by
    iteration: the row is the recorded one)."""
    uv = uv_at_frame_time.copy()
    for _ in range(20):
        uv = uv_at_frame_time + _velocity(uv_at_frame_time) * (READOUT_S * (uv[:, 1] / (H - 1) - 0.5))[:, None]
    return uv


def _tracks(ids: np.ndarray, uv: np.ndarray) -> Tracks:
    return Tracks(ids=ids, uv_px=uv, f_cam=CAMERA.pixels_to_bearings(uv), tracked=len(ids))


def test_tracks_are_moved_to_the_frame_time() -> None:
    rng = np.random.default_rng(3)
    uv0 = rng.uniform([20, 20], [300, 220], (60, 2))
    dt = 0.02
    uv1 = uv0 + _velocity(uv0) * dt  # the points at the next frame's time (the field is nearly steady)
    born = rng.uniform([20, 20], [300, 220], (10, 2))  # first seen in the second frame
    rs = RollingShutter(CAMERA, READOUT_S)
    first = _tracks(np.arange(60), _seen(uv0))
    rs.bearings(first, 1.0)
    ids = np.arange(70)
    truth = np.vstack([uv1, born])
    second = _tracks(ids, _seen(truth))
    f = rs.bearings(second, 1.0 + dt)
    err_px = np.arccos(np.clip(np.sum(f * CAMERA.pixels_to_bearings(truth), axis=1), -1, 1)) * CAMERA.fx_px
    raw_px = np.linalg.norm(second.uv_px - truth, axis=1)
    # The skew is up to a few pixels; what is left is the field's change over a frame times the readout.
    assert raw_px.max() > 2.0
    assert err_px[:60].max() < 0.1 and err_px[60:].max() < 0.1, (err_px[:60].max(), err_px[60:].max())


def test_a_global_shutter_and_the_first_frame_keep_the_bearings() -> None:
    uv = np.array([[10.0, 10.0], [300.0, 200.0], [160.0, 120.0]] * 3)
    t = _tracks(np.arange(9), uv)
    assert RollingShutter(CAMERA, 0.0).bearings(t, 1.0) is t.f_cam
    assert RollingShutter(CAMERA, READOUT_S).bearings(t, 1.0) is t.f_cam  # no velocity yet


def test_a_negative_readout_is_refused() -> None:
    with pytest.raises(ValueError, match="readout_s"):
        RollingShutter(CAMERA, -0.001)
