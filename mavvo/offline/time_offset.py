"""The time offset between a video and a flight-controller log, from the rotation both saw.

The camera's rotation rate about its optical axis (the rotation of the best similarity between the
features of frames a few apart) and the vehicle's about the same axis (from the logged attitude over
the same interval and the camera's mounting) are the same signed signal. The rotation about the
optical axis is the part of the camera's motion the image measures robustly: a nadir camera over flat
ground (the drone's usual view) leaves the full rotation ambiguous in the essential matrix, but its
image turns with every yaw. Both are put on a 10 ms grid, smoothed alike, and the offset is the lag
of the best normalised cross-correlation (computed for every lag with FFTs).

Confidence: the peak correlation, and the runner-up: the best other local maximum of the correlation
outside the peak's lobe (a repetitive flight, or one with too little rotation, has one close to the
peak). An estimate
with a peak below ``min_correlation`` or a runner-up above ``max_runner_up_ratio`` x the peak is
refused: the caller must give the offset.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import cv2
import numpy as np

from mavvo.errors import ConfigError
from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.frames import R_from_euler321

__all__ = ["OffsetEstimate", "camera_rotation_rates", "attitude_rotation_rates", "estimate_offset"]

GRID_S = 0.01
_SMOOTH_S = 0.15
_PEAK_LOBE_S = 0.25


@dataclass(frozen=True)
class OffsetEstimate:
    """``offset_s``: the log's time at the video's time zero (t_log = t_video + offset_s)."""

    offset_s: float
    correlation: float
    runner_up_correlation: float
    runner_up_offset_s: float
    overlap_s: float

    def as_dict(self) -> dict[str, float]:
        return {k: round(float(v), 4) for k, v in self.__dict__.items()}


def _roll_about_axis_rad(img0: np.ndarray, img1: np.ndarray, camera: CameraModel, max_features: int) -> float:
    """The camera's rotation about its optical axis from ``img0`` to ``img1``, radians (positive:
    clockwise as seen along the axis, the right-hand sense about camera z), NaN when unknown: the
    rotation of the best similarity between the undistorted feature positions."""
    p0 = cv2.goodFeaturesToTrack(img0, max_features, 0.01, 8)
    if p0 is None or len(p0) < 12:
        return np.nan
    p1, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, p0, None, winSize=(21, 21), maxLevel=3)
    ok = st.ravel() == 1
    if ok.sum() < 12:
        return np.nan
    f0 = camera.pixels_to_bearings(p0.reshape(-1, 2)[ok].astype(float))
    f1 = camera.pixels_to_bearings(p1.reshape(-1, 2)[ok].astype(float))
    n0, n1 = f0[:, :2] / f0[:, 2:], f1[:, :2] / f1[:, 2:]
    M, _ = cv2.estimateAffinePartial2D(n0, n1, method=cv2.RANSAC, ransacReprojThreshold=2.0 / camera.fx_px)
    if M is None:
        return np.nan
    return -float(np.arctan2(M[1, 0], M[0, 0]))  # the scene turns the other way


def camera_rotation_rates(
    frames: Iterable[tuple[float, np.ndarray]],
    camera: CameraModel,
    *,
    step: int = 2,
    max_features: int = 300,
) -> tuple[np.ndarray, np.ndarray]:
    """(t_mid_s, rate_rad_s): the camera's rotation rate about its optical axis between frames ``step``
    apart, at the middle of their interval; NaN where it could not be measured."""
    t_out, w_out = [], []
    recent: list[tuple[float, np.ndarray]] = []
    for t, img in frames:
        recent.append((t, img))
        if len(recent) > step:
            t0, img0 = recent.pop(0)
            t_out.append(0.5 * (t0 + t))
            w_out.append(_roll_about_axis_rad(img0, img, camera, max_features) / (t - t0))
    return np.array(t_out), np.array(w_out)


def attitude_rotation_rates(
    attitude: np.ndarray, axis_body: np.ndarray, interval_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """(t_s, rate_rad_s) on a 10 ms grid from an (N,4) array of t_s, roll, pitch, yaw: the body's
    rotation rate about ``axis_body`` (a unit vector in the body frame: the camera's optical axis),
    over ``interval_s`` centred on each grid time."""
    t = attitude[:, 0]
    grid = np.arange(t[0] + interval_s, t[-1] - interval_s, GRID_S)
    unwrapped = np.column_stack([attitude[:, 1], attitude[:, 2], np.unwrap(attitude[:, 3])])

    def at(times: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(times, t, unwrapped[:, k]) for k in range(3)])

    a, b = at(grid - interval_s / 2), at(grid + interval_s / 2)
    axis = np.asarray(axis_body, dtype=float)
    rates = np.empty(len(grid))
    for i in range(len(grid)):
        dR = R_from_euler321(*a[i]).T @ R_from_euler321(*b[i])  # body at the start to body at the end
        w = 0.5 * np.array(
            [dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]
        )  # small-angle rotation vector
        rates[i] = float(w @ axis) / interval_s
    return grid, rates


def _on_grid(t: np.ndarray, x: np.ndarray, start: float, n: int) -> np.ndarray:
    ok = np.isfinite(x)
    g = start + GRID_S * np.arange(n)
    y = np.interp(g, t[ok], x[ok]) if ok.sum() >= 2 else np.zeros(n)
    k = max(int(round(_SMOOTH_S / GRID_S)), 1)
    return np.convolve(y, np.ones(k) / k, mode="same")


def _ncc_valid(long: np.ndarray, short: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation of ``short`` at every lag fully inside ``long``."""
    n, m = len(short), len(long)
    s = short - short.mean()
    s_norm = np.sqrt(np.sum(s * s))
    size = 1 << int(np.ceil(np.log2(n + m)))
    num = np.fft.irfft(np.fft.rfft(long, size) * np.conj(np.fft.rfft(s, size)), size)[: m - n + 1]
    c1 = np.concatenate([[0.0], np.cumsum(long)])
    c2 = np.concatenate([[0.0], np.cumsum(long * long)])
    win_sum = c1[n:] - c1[:-n]
    win_var = np.maximum(c2[n:] - c2[:-n] - win_sum * win_sum / n, 1e-12)
    return num / (np.sqrt(win_var) * max(s_norm, 1e-12))


def estimate_offset(
    cam_t: np.ndarray,
    cam_rate: np.ndarray,
    fc_t: np.ndarray,
    fc_rate: np.ndarray,
    *,
    min_correlation: float = 0.5,
    max_runner_up_ratio: float = 0.9,
    source: str = "video",
) -> OffsetEstimate:
    """The offset (see :class:`OffsetEstimate`); ConfigError naming ``source`` when it cannot be
    estimated with confidence (too little overlap or rotation, an ambiguous peak)."""
    ok = np.isfinite(cam_rate)
    if ok.sum() < 20 or len(fc_t) < 20:
        raise ConfigError(
            f"{source}: cannot estimate the time offset: only {int(ok.sum())} frame pairs with a measured rotation; give --offset-s"
        )
    n_cam = int((cam_t[-1] - cam_t[0]) / GRID_S) + 1
    n_fc = int((fc_t[-1] - fc_t[0]) / GRID_S) + 1
    cam = _on_grid(cam_t, cam_rate, cam_t[0], n_cam)
    fc = _on_grid(fc_t, fc_rate, fc_t[0], n_fc)
    if n_cam <= n_fc:
        ncc = _ncc_valid(fc, cam)
        offsets = fc_t[0] - cam_t[0] + GRID_S * np.arange(len(ncc))
    else:
        ncc = _ncc_valid(cam, fc)
        offsets = fc_t[0] - cam_t[0] - GRID_S * np.arange(len(ncc))
    if float(np.std(cam)) < 0.02:
        raise ConfigError(
            f"{source}: cannot estimate the time offset: the camera barely turned about its axis (rate spread {np.std(cam):.3f} rad/s); give --offset-s"
        )
    i = int(np.argmax(ncc))
    peak = float(ncc[i])
    # The runner-up: the best other local maximum outside the peak's own lobe.
    peaks = np.flatnonzero((ncc[1:-1] >= ncc[:-2]) & (ncc[1:-1] >= ncc[2:])) + 1
    peaks = peaks[np.abs(offsets[peaks] - offsets[i]) > _PEAK_LOBE_S]
    j = int(peaks[np.argmax(ncc[peaks])]) if len(peaks) else i
    runner = float(ncc[j]) if len(peaks) else float("nan")
    shift = 0.0
    if 0 < i < len(ncc) - 1:  # parabola through the peak: sub-grid offset
        den = ncc[i - 1] - 2 * ncc[i] + ncc[i + 1]
        shift = 0.5 * (ncc[i - 1] - ncc[i + 1]) / den if den < 0 else 0.0
    step = offsets[1] - offsets[0] if len(offsets) > 1 else GRID_S
    est = OffsetEstimate(float(offsets[i] + shift * step), peak, runner, float(offsets[j]), min(n_cam, n_fc) * GRID_S)
    if peak < min_correlation:
        raise ConfigError(
            f"{source}: cannot estimate the time offset: best correlation {peak:.2f} at {est.offset_s:.2f} s is below {min_correlation}; give --offset-s"
        )
    if np.isfinite(runner) and runner > max_runner_up_ratio * peak:
        raise ConfigError(
            f"{source}: cannot estimate the time offset: ambiguous, correlation {peak:.2f} at {est.offset_s:.2f} s and {runner:.2f} at "
            f"{est.runner_up_offset_s:.2f} s; give --offset-s"
        )
    return est
