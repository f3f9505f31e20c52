"""Bearings of a rolling-shutter camera's tracks, moved to the frame's time.

A rolling shutter exposes row ``r`` of an ``H``-row image ``readout (r / (H - 1) - 1/2)`` after the
frame's time (the middle row's, as the simulator renders and ``picamera2:`` stamps). A track moving at
``v`` px/s is therefore seen ``v`` times that offset away from where it was at the frame's time; every
estimate after the tracker assumes one instant per frame. To first order

    uv(t_frame) = uv - v (readout (r / (H - 1) - 1/2))

with ``v`` the track's own pixel velocity since the last frame it was seen in, or for a track born in
this frame (no velocity of its own) the affine field ``v = A [u, v, 1]`` fitted to the tracks that have
one. The velocities are measured between skewed images, which only matters to second order.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.camera_model import CameraModel
from mavvo.odometry.frontend import Tracks

__all__ = ["RollingShutter"]

_MIN_FIELD_TRACKS = 6  # an affine velocity field has 6 unknowns


class RollingShutter:
    """Undoes the skew of a camera with top-to-bottom readout time ``readout_s`` (0: a global
    shutter, bearings as the tracker gives them). Feed it every tracked frame in order."""

    def __init__(self, camera: CameraModel, readout_s: float) -> None:
        if not readout_s >= 0:
            raise ValueError(f"readout_s: expected >= 0, got {readout_s}")
        self.camera = camera
        self.readout_s = readout_s
        self._last: tuple[np.ndarray, np.ndarray, float] | None = None  # ids, uv_px, t_s of the last frame

    def bearings(self, tracks: Tracks, t_s: float) -> np.ndarray:
        """(N,3) unit bearings in the camera frame of ``tracks`` at the frame's time ``t_s`` (s)."""
        if self.readout_s == 0:
            return tracks.f_cam
        last, self._last = self._last, (tracks.ids, tracks.uv_px, t_s)
        if last is None or not t_s > last[2] or len(tracks.ids) == 0:
            return tracks.f_cam
        ids0, uv0, t0 = last
        # Track ids increase with creation, so both id arrays are sorted.
        both, i_now, i_then = np.intersect1d(tracks.ids, ids0, assume_unique=True, return_indices=True)
        if len(both) < _MIN_FIELD_TRACKS:
            return tracks.f_cam
        uv = tracks.uv_px
        v = np.empty_like(uv)
        v[i_now] = (uv[i_now] - uv0[i_then]) / (t_s - t0)
        born = np.ones(len(uv), bool)
        born[i_now] = False
        if np.any(born):
            # The affine field of the tracked ones, least squares: v = [u, v, 1] A.
            A, *_ = np.linalg.lstsq(np.column_stack([uv[i_now], np.ones(len(i_now))]), v[i_now], rcond=None)
            v[born] = np.column_stack([uv[born], np.ones(int(np.count_nonzero(born)))]) @ A
        dt = self.readout_s * (uv[:, 1] / (self.camera.height_px - 1) - 0.5)
        f = self.camera.pixels_to_bearings(uv - v * dt[:, None])
        # A pixel moved off what the model can undistort keeps its bearing as seen.
        bad = ~np.isfinite(f.sum(axis=1))
        f[bad] = tracks.f_cam[bad]
        return f
