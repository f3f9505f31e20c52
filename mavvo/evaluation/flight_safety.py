"""What the vehicle would feel: the sent estimates and the flight controller's own estimate against the
truth, without any alignment, as an EKF fuses them.

Pure functions on arrays. Positions are NED metres in the truth's frame (mavvo anchors its world frame
where the flight controller believes the vehicle is, and the simulated flight controller starts at the
truth's position), times in seconds on the simulation clock.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Callable

import numpy as np

__all__ = ["FlightSafety", "VisionSample", "flight_safety", "motion_consistency"]

# 99% quantile of chi-square with 3 degrees of freedom (statistics tables).
_CHI2_3DOF_99 = 11.345


@dataclass(frozen=True)
class VisionSample:
    """One VISION_POSITION_ESTIMATE as received: ``t_s`` its usec stamp, ``p_ned_m`` (3,), ``cov_m2``
    (3, 3) the position block of its covariance, ``yaw_rad``, ``reset_counter``."""

    t_s: float
    p_ned_m: np.ndarray
    cov_m2: np.ndarray
    yaw_rad: float
    reset_counter: int


@dataclass(frozen=True)
class FlightSafety:
    """The figures of :func:`flight_safety` (metres, degrees; None where there was nothing to measure)."""

    sent_end_error_m: float | None  # horizontal, last estimate against the truth at its time
    sent_max_error_m: float | None
    fc_end_error_m: float | None  # the flight controller's estimate at the end against the truth
    fc_max_error_m: float | None
    largest_reset_step_m: float | None  # how far a reset moved the flight controller's estimate
    reset_steps_m: list[float]
    reset_step_excess_m: (
        float | None
    )  # the largest step minus what it may be: 0.3 m + 10% of the motion since the previous estimate
    heading_end_error_deg: float | None  # the sent yaw against the truth's
    heading_median_error_deg: float | None
    nees_median: float | None  # 1 s windows without a reset: motion error against the difference's covariance
    nees_inside_99_fraction: float | None
    drift_within_3x_fraction: float | None  # true error <= 3 x VO_DRIFT at each VO_DRIFT report
    path_length_m: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def motion_consistency(
    samples: list[VisionSample], truth_p: Callable[[np.ndarray], np.ndarray], window_s: float = 1.0
) -> tuple[float | None, float | None]:
    """(median NEES, fraction inside the 99% ellipse) of the motion over ``window_s`` windows.

    For each sample i and the first j at least ``window_s`` later with the same ``reset_counter`` (no
    reset inside), the error of the sent motion ``p_j - p_i`` against the true motion, weighed by the
    covariance of the difference ``C_i + C_j`` (3 degrees of freedom).
    """
    if len(samples) < 2:
        return None, None
    t = np.array([s.t_s for s in samples])
    tp = truth_p(t)
    nees = []
    for i, s in enumerate(samples):
        j = int(np.searchsorted(t, s.t_s + window_s))
        if j >= len(samples) or t[j] - s.t_s > 1.5 * window_s:
            continue
        if any(samples[k].reset_counter != s.reset_counter for k in range(i, j + 1)):
            continue
        e = (samples[j].p_ned_m - s.p_ned_m) - (tp[j] - tp[i])
        C = samples[j].cov_m2 + s.cov_m2
        try:
            nees.append(float(e @ np.linalg.solve(C, e)))
        except np.linalg.LinAlgError:
            continue
    if not nees:
        return None, None
    n = np.array(nees)
    return float(np.median(n)), float(np.mean(n <= _CHI2_3DOF_99))


def flight_safety(
    samples: list[VisionSample],
    truth_p: Callable[[np.ndarray], np.ndarray],
    truth_yaw: Callable[[np.ndarray], np.ndarray],
    fc_estimates: np.ndarray,
    reset_steps: list[tuple[float, float]],
    drift_reports: list[tuple[float, float]],
) -> FlightSafety:
    """The figures of :class:`FlightSafety`.

    Args:
        samples: the VISION_POSITION_ESTIMATEs received, in time order.
        truth_p: times (N,) -> true positions (N, 3) NED.
        truth_yaw: times (N,) -> true yaw (N,), radians.
        fc_estimates: (M, 3) rows (t_s, north, east) of the flight controller's estimate.
        reset_steps: (t_s, metres): when and how far each reset moved the flight controller's estimate.
        drift_reports: (t_s, VO_DRIFT metres) as received.
    """
    sent_end = sent_max = fc_end = fc_max = hd_end = hd_med = None
    path = 0.0
    if samples:
        t = np.array([s.t_s for s in samples])
        p = np.array([s.p_ned_m for s in samples])
        tp = truth_p(t)
        err = np.linalg.norm(p[:, :2] - tp[:, :2], axis=1)
        sent_end, sent_max = float(err[-1]), float(err.max())
        dyaw = np.degrees(np.abs(_wrap(np.array([s.yaw_rad for s in samples]) - truth_yaw(t))))
        hd_end, hd_med = float(dyaw[-1]), float(np.median(dyaw))
        path = float(np.linalg.norm(np.diff(tp, axis=0), axis=1).sum())
    if len(fc_estimates):
        tf = fc_estimates[:, 0]
        # Only once the flight controller has fused vision: before, its estimate is whatever it started with.
        start = samples[0].t_s if samples else math.inf
        keep = tf >= start
        if np.any(keep):
            ferr = np.linalg.norm(fc_estimates[keep, 1:3] - truth_p(tf[keep])[:, :2], axis=1)
            fc_end, fc_max = float(ferr[-1]), float(ferr.max())
    nees_med, inside = motion_consistency(samples, truth_p)
    excess = None
    if reset_steps and samples:
        t = np.array([s.t_s for s in samples])
        over = []
        for t_step, step in reset_steps:
            i = max(int(np.searchsorted(t, t_step - 1e-6)) - 1, 0)  # the last estimate before the one that reset
            motion = float(np.linalg.norm(truth_p(np.array([t_step]))[0, :2] - truth_p(np.array([t[i]]))[0, :2]))
            over.append(step - (0.3 + 0.1 * motion))
        excess = max(over)
    within = None
    if drift_reports and samples:
        t = np.array([s.t_s for s in samples])
        tp = truth_p(t)
        ok = []
        for t_r, drift in drift_reports:
            i = int(np.searchsorted(t, t_r, side="right")) - 1
            if i < 0 or not math.isfinite(drift) or t_r - t[i] > 1.0:
                continue  # no estimate sent lately: nothing the vehicle fuses
            e = float(np.linalg.norm(samples[i].p_ned_m[:2] - tp[i, :2]))
            ok.append(e <= 3.0 * drift)
        within = float(np.mean(ok)) if ok else None
    return FlightSafety(
        sent_end,
        sent_max,
        fc_end,
        fc_max,
        max((m for _, m in reset_steps), default=None),
        [m for _, m in reset_steps],
        excess,
        hd_end,
        hd_med,
        nees_med,
        inside,
        within,
        path,
    )
