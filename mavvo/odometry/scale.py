"""Metric scale for a relative pose whose translation is known only in direction.

The relative pose between a keyframe (view 1) and the current frame (view 2) has a unit translation.
Triangulating its inliers with that unit baseline gives points in view 1's level frame in "baseline
units"; one metric length turns them, and the baseline, into metres. Where that length comes from:

``rangefinder``
    A downward rangefinder's distance along the body z axis, at the current frame. The inliers below
    the horizon give the ground's depth under view 1 (a horizontal plane: the robust median of their
    heights, each point weighted by its parallax); the camera of view 2 sits at that depth minus its own
    drop; the ray's vertical component turns the range into the height. Assumes flat, level ground
    under the camera; raised objects are outvoted by the median.
``altitude``
    The same with the flight controller's height above the take-off point instead of a range: flat
    ground at take-off height, and the barometer's offset, both matter.
``fixed``
    The same with a constant height (``fixed_height_m``): tests, or a flight at known height.
``carried``
    Metric depths of points triangulated in the previous keyframe pair, carried into the keyframe, and
    the same points' depths triangulated now: their median ratio. Works for any camera direction.

Which applies: the configured ``source`` first; when it has no answer (no reading, out of range, too
few ground points with parallax), the scale carried from the previous keyframe interval; for the first
interval with ``source: carried``, the rangefinder or altitude if present; and at last the keyframe
scene's median depth as the last metric frame saw it (``held``), or before any metric frame an assumed
one (``initial_depth_m``, ``assumed``). Both lower the reported quality.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from mavvo.geometry.medians import median, weighted_median
from mavvo.geometry.triangulation import triangulate_midpoints
from mavvo.options import bounded
from mavvo.types import ScaleSource

__all__ = [
    "ScaleOptions",
    "ScaleEstimate",
    "triangulate_unit",
    "ground_depth",
    "estimate_scale",
    "scale_from_scene_depth",
]

ConfiguredScale = Literal["rangefinder", "altitude", "fixed", "carried"]


@dataclass(frozen=True)
class ScaleOptions:
    """Where metric scale comes from (see the module docstring)."""

    source: ConfiguredScale = bounded("rangefinder", "rangefinder, altitude, fixed or carried (see docs/odometry.md)")
    fixed_height_m: float = bounded(10.0, "source fixed: height of the camera above flat ground", gt=0, le=10000)
    initial_depth_m: float = bounded(
        10.0, "last resort: assumed median depth of the scene at the first keyframe", gt=0, le=10000
    )
    min_points: int = bounded(12, "fewest triangulated points for a scale", ge=3, le=5000)
    min_parallax_deg: float = bounded(0.05, "points with less parallax than this are not triangulated", gt=0, le=90)
    carry_min_parallax_deg: float = bounded(
        1.0, "carried: only points triangulated with at least this parallax carry or compare depths", gt=0, le=90
    )
    max_depth_ratio: float = bounded(
        3.0, "carried: depth ratios further than this factor from their median are outliers", gt=1, le=1000
    )
    rangefinder_sigma_m: float = bounded(
        0.02, "rangefinder noise (1 sigma): its share of the scale's uncertainty is this over the range", ge=0, le=100
    )
    altitude_sigma_m: float = bounded(
        0.1, "noise of the flight controller's height (1 sigma), the same for the altitude source", ge=0, le=1000
    )
    max_ground_spread: float = bounded(
        0.5,
        "rangefinder/altitude: a ground fit whose depths spread more than this (median absolute deviation over the median) gives no scale",
        gt=0,
        le=100,
    )


@dataclass(frozen=True)
class ScaleEstimate:
    """Metres per baseline unit and where it came from.

    Attributes:
        baseline_m: the metric length of the unit translation (the baseline), metres.
        source: :class:`~mavvo.types.ScaleSource` (never ``none``).
        points: how many triangulated points voted.
        spread: relative spread of the votes (median absolute deviation over the median): how well
            the triangulated scene fits, which also says how well the translation was measured.
        sensor_spread: relative uncertainty a height source adds (its noise over the height): a new
            reading every frame, so the scale's frame-to-frame error, which moves the position along
            the translation only.
    """

    baseline_m: float
    source: ScaleSource
    points: int
    spread: float
    sensor_spread: float = 0.0


def triangulate_unit(
    f1_lvl: np.ndarray, f2_lvl: np.ndarray, R_2_1: np.ndarray, t_2_1: np.ndarray, min_parallax_rad: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Depths of matched bearings along view 1's rays for the pose ``x_2 = R_2_1 x_1 + t_2_1``.

    Midpoint of the closest approach of the two rays, in units of |t_2_1|.

    Args:
        f1_lvl, f2_lvl: (N,3) unit bearings of view 1 and view 2 (level frames).
        R_2_1, t_2_1: (3,3), (3,) relative pose.
        min_parallax_rad: rays closer in angle than this (after rotation) are not triangulated.

    Returns:
        (depth1 (N,), depth2 (N,), parallax_rad (N,), valid (N,) bool): depth of each point along f1
        and along f2; the rotation-compensated angle between the rays; valid where the parallax is
        enough and the point lies in front of both views.
    """
    # Writable copies: the relative pose's outputs are read-only, and numba compiles read-only arrays
    # as a type of their own, which the warm-up would not have seen.
    f1, f2 = np.array(f1_lvl, dtype=np.float64, order="C"), np.array(f2_lvl, dtype=np.float64, order="C")
    return triangulate_midpoints(
        f1,
        f2,
        np.array(R_2_1, dtype=np.float64, order="C"),
        np.array(t_2_1, dtype=np.float64, order="C"),
        float(min_parallax_rad),
    )


def ground_depth(points_lvl: np.ndarray, weights: np.ndarray, min_points: int) -> tuple[float, float] | None:
    """Depth of a horizontal ground plane below view 1, from triangulated points (level frame, z down).

    Returns (depth, relative spread) from the points below the horizon: the median of their z weighted
    by ``weights`` (the parallax squared: votes triangulated from almost no parallax do not move it),
    and the unweighted median of their absolute deviations from it over it (all votes: where the
    parallax came from a rotation error rather than a translation, as in a spin on the spot, the few
    with the most agree with each other while the rest do not, and the spread has to say so), or None
    with fewer than ``min_points`` of them.
    """
    below = points_lvl[:, 2] > 0
    if np.count_nonzero(below) < min_points:
        return None
    z, w = points_lvl[below, 2], weights[below]
    d = weighted_median(z, w)
    spread = median(np.abs(z - d)) / d
    return d, spread


def _carried_scale(options: ScaleOptions, carried_depth_m: np.ndarray, depth_unit: np.ndarray) -> ScaleEstimate | None:
    """The scale that makes the points' depths now (baseline units) the metric ones carried into the
    keyframe: the median ratio, after dropping those further than ``max_depth_ratio`` from it."""
    if len(depth_unit) < options.min_points:
        return None
    r = np.log(carried_depth_m / depth_unit)
    med = median(r)
    ok = np.abs(r - med) < np.log(options.max_depth_ratio)
    if np.count_nonzero(ok) < options.min_points:
        return None
    med = median(r[ok])
    return ScaleEstimate(
        float(np.exp(med)), ScaleSource.CARRIED, int(np.count_nonzero(ok)), median(np.abs(r[ok] - med))
    )


def estimate_scale(
    options: ScaleOptions,
    *,
    points_lvl: np.ndarray,
    parallax_rad: np.ndarray,
    c2_lvl1: np.ndarray,
    down_lvl2: np.ndarray,
    range_m: float | None,
    height_m: float | None,
    carried_depth_m: np.ndarray,
    depth_unit: np.ndarray,
    first_interval: bool,
) -> ScaleEstimate | None:
    """The baseline in metres for one relative pose (see the module docstring for the order).

    Args:
        points_lvl: (M,3) valid triangulated points in view 1's level frame, baseline units.
        parallax_rad: (M,) their parallax (weights of the ground fit).
        c2_lvl1: (3,) view 2's camera centre in view 1's level frame, baseline units (unit length).
        down_lvl2: (3,) the rangefinder's direction (body z) in view 2's level frame (unit).
        range_m, height_m: the rangefinder reading and the flight controller's height, or None.
        carried_depth_m: (K,) metric depths carried into the keyframe for points also triangulated now.
        depth_unit: (K,) the same points' depths now, baseline units.
        first_interval: no scale has been carried yet (the first keyframe after (re-)initialisation).

    Returns:
        :class:`ScaleEstimate`, or None when no source gives a scale (then
        :func:`scale_from_scene_depth` is the last resort).
    """
    ground = None

    def from_height(h2_m: float, source: ScaleSource, sigma_m: float) -> ScaleEstimate | None:
        nonlocal ground
        if ground is None:
            ground = ground_depth(points_lvl, parallax_rad**2, options.min_points) or (float("nan"), 0.0)
        d1, spread = ground
        h2_unit = d1 - c2_lvl1[2]
        # A spread of tens of times the depth is no plane (a forward camera's few ground points, badly
        # triangulated): its scale was 10-80x off and moved the keyframe hundreds of metres.
        if not (np.isfinite(h2_unit) and h2_unit > 0 and h2_m > 0) or spread > options.max_ground_spread:
            return None
        # A new reading every frame: its noise over the height is the scale's frame-to-frame error
        # (2 cm at 0.5 m is 4%, what moved the landing's positions by centimetres).
        return ScaleEstimate(
            h2_m / h2_unit, source, int(np.count_nonzero(points_lvl[:, 2] > 0)), spread, sigma_m / h2_m
        )

    def rangefinder() -> ScaleEstimate | None:
        if range_m is None or not (np.isfinite(range_m) and range_m > 0) or down_lvl2[2] < 0.5:
            return None
        return from_height(range_m * down_lvl2[2], ScaleSource.RANGEFINDER, options.rangefinder_sigma_m)

    def altitude() -> ScaleEstimate | None:
        if height_m is None or not np.isfinite(height_m):
            return None
        return from_height(height_m, ScaleSource.ALTITUDE, options.altitude_sigma_m)

    def carried() -> ScaleEstimate | None:
        return _carried_scale(options, carried_depth_m, depth_unit)

    def fixed() -> ScaleEstimate | None:
        return from_height(options.fixed_height_m, ScaleSource.FIXED, 0.0)

    order = {
        "rangefinder": (rangefinder, carried),
        "altitude": (altitude, carried),
        "fixed": (fixed, carried),
        "carried": (carried, rangefinder, altitude) if first_interval else (carried,),
    }[options.source]
    for attempt in order:
        s = attempt()
        if s is not None:
            return s
    return None


def scale_from_scene_depth(
    points_lvl: np.ndarray, scene_depth_m: float, source: ScaleSource, min_points: int
) -> ScaleEstimate | None:
    """The last resort: the keyframe's scene is taken to have the median depth ``scene_depth_m``
    (the last metric frame's, or ``initial_depth_m`` before any); None with too few points."""
    if len(points_lvl) < min_points:
        return None
    depth = median(np.linalg.norm(points_lvl, axis=1))
    return ScaleEstimate(scene_depth_m / depth, source, len(points_lvl), 1.0)
