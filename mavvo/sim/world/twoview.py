"""Synthetic two-view scenes with exact truth, for solver tests, the relative-pose estimator and
the paper's experiments.

A scene is two cameras on a drone looking at 3D points. Bearings are given in each camera frame and
derotated into each view's level frame with the roll/pitch the IMU reports (optionally noisy), as the
service does. Truth follows mavvo's convention ``x_2 = R_2_1 @ x_1 + t_2_1`` between level frames.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from mavvo.geometry.frames import R_BODY_CAM_FORWARD, R_BODY_CAM_NADIR, R_from_euler321, R_lvl_cam, rot_y

Motion = Literal["sideways", "forward", "random", "vertical", "none"]
Mount = Literal["nadir", "oblique", "forward"]
Structure = Literal["volume", "ground", "plane", "line"]

_MAX_ATTEMPTS = 50


@dataclass(frozen=True)
class TwoViewScene:
    """Two views of one set of points.

    Attributes:
        f1_lvl, f2_lvl: (N,3) unit bearings in the level frames, derotated with the reported roll/pitch.
        f1_cam, f2_cam: (N,3) unit bearings in the camera frames (with pixel noise if any).
        R_2_1: (3,3) true rotation between the level frames (about z).
        t_2_1: (3,) true translation direction in level frame 2 (unit; zero for no motion).
        baseline_m: distance between the camera centres.
        points_ned: (N,3) the points, with camera 1 at the origin.
        R_lvl_cam1, R_lvl_cam2: the derotations used (from the reported roll/pitch).
        R_c2_c1, t_c2_c1: true relative pose of the camera frames, ``x_c2 = R_c2_c1 @ x_c1 + t_c2_c1``
            (t unit; zero for no motion), independent of the IMU noise.
    """

    f1_lvl: np.ndarray
    f2_lvl: np.ndarray
    f1_cam: np.ndarray
    f2_cam: np.ndarray
    R_2_1: np.ndarray
    t_2_1: np.ndarray
    baseline_m: float
    points_ned: np.ndarray
    R_lvl_cam1: np.ndarray
    R_lvl_cam2: np.ndarray
    R_c2_c1: np.ndarray
    t_c2_c1: np.ndarray


def mount_rotation(mount: Mount, oblique_depression_rad: float = np.radians(45.0)) -> np.ndarray:
    """R_body_cam for a named mounting: nadir, oblique (pitched down from forward), forward."""
    if mount == "nadir":
        return R_BODY_CAM_NADIR
    if mount == "forward":
        return R_BODY_CAM_FORWARD
    if mount == "oblique":
        return rot_y(-oblique_depression_rad) @ R_BODY_CAM_FORWARD
    raise ValueError(f"mount: expected 'nadir', 'oblique' or 'forward', got {mount!r}")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _noisy_bearings(f: np.ndarray, rng: np.random.Generator, noise_px: float, focal_px: float) -> np.ndarray:
    """Perturb bearings as pixel noise of ``noise_px`` on an ideal pinhole of ``focal_px`` would."""
    if noise_px <= 0:
        return f
    # Perturb in the tangent plane of each bearing; at the image centre this equals pixel noise.
    helper = np.where(np.abs(f[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    u = _unit(np.cross(f, helper))
    w = np.cross(f, u)
    d = rng.normal(0.0, noise_px / focal_px, (len(f), 2))
    return _unit(f + d[:, :1] * u + d[:, 1:] * w)


def make_scene(
    rng: np.random.Generator,
    n_points: int,
    *,
    motion: Motion = "random",
    mount: Mount = "nadir",
    structure: Structure = "volume",
    distance_m: float = 10.0,
    depth_fraction: float = 0.5,
    baseline_fraction: float = 0.1,
    max_tilt_rad: float = np.radians(15.0),
    fov_half_rad: float = np.radians(30.0),
    pixel_noise_px: float = 0.0,
    imu_noise_rad: float = 0.0,
    focal_px: float = 500.0,
    line_along_baseline: bool = False,
) -> TwoViewScene:
    """Draw one scene.

    Args:
        rng: the generator every random draw comes from.
        n_points: number of correspondences.
        motion: direction of camera 2 from camera 1: ``sideways`` (perpendicular to camera 1's optical
            axis), ``forward`` (along it), ``random``, ``vertical`` (along gravity), ``none`` (no baseline).
        mount: camera mounting on the body.
        structure: ``volume`` (points in a slab of depth ``depth_fraction * distance_m`` in front of
            camera 1), ``ground`` (points on the horizontal plane ``distance_m`` below camera 1 along
            its optical axis), ``plane`` (a randomly tilted plane at that distance), ``line``
            (collinear points; with ``line_along_baseline`` the line is parallel to the baseline).
        distance_m: distance from camera 1 to the scene along its optical axis.
        baseline_fraction: baseline as a fraction of ``distance_m``.
        max_tilt_rad: roll and pitch of each view are drawn from +-this; yaw is uniform.
        fov_half_rad: points are drawn within this half-angle of camera 1's optical axis.
        pixel_noise_px, focal_px: bearing noise, as pixel noise on a pinhole of that focal length.
        imu_noise_rad: standard deviation of the error of the reported roll and pitch.
    """
    if n_points < 1:
        raise ValueError(f"n_points: expected at least 1, got {n_points}")
    kwargs = dict(locals())
    del kwargs["rng"], kwargs["n_points"]
    for _ in range(_MAX_ATTEMPTS):
        # A point behind a camera means drawing again (rare: wide baselines or tilted planes).
        scene = _draw(rng, n_points, **kwargs)
        if scene is not None:
            return scene
    raise ValueError(
        f"no scene with every point in front of both cameras for {structure!r} seen from a {mount!r} camera"
    )


def _draw(
    rng: np.random.Generator,
    n_points: int,
    *,
    motion: Motion,
    mount: Mount,
    structure: Structure,
    distance_m: float,
    depth_fraction: float,
    baseline_fraction: float,
    max_tilt_rad: float,
    fov_half_rad: float,
    pixel_noise_px: float,
    imu_noise_rad: float,
    focal_px: float,
    line_along_baseline: bool,
) -> TwoViewScene | None:
    """One attempt of :func:`make_scene`; None when a point falls behind a camera."""
    R_body_cam = mount_rotation(mount)
    att = [
        (rng.uniform(-max_tilt_rad, max_tilt_rad), rng.uniform(-max_tilt_rad, max_tilt_rad), rng.uniform(-np.pi, np.pi))
        for _ in range(2)
    ]
    R_ned_cam1 = R_from_euler321(*att[0]) @ R_body_cam
    axis1 = R_ned_cam1[:, 2]
    baseline_m = baseline_fraction * distance_m

    direction = _motion_direction(motion, axis1, rng)
    if motion == "none":
        baseline_m = 0.0
    p2 = baseline_m * direction
    X = _points(
        rng,
        n_points,
        structure,
        R_ned_cam1,
        distance_m,
        depth_fraction,
        fov_half_rad,
        direction,
        baseline_m,
        line_along_baseline,
    )
    return _scene_from_points(
        rng, X, att, R_body_cam, R_ned_cam1, p2, baseline_m, pixel_noise_px, imu_noise_rad, focal_px
    )


def _motion_direction(motion: Motion, axis1: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The unit direction of camera 2 from camera 1 (NED; zeros for ``none``)."""
    if motion == "sideways":
        return _unit(np.cross(axis1, _unit(rng.normal(size=3))))
    if motion == "forward":
        return axis1
    if motion == "random":
        return _unit(rng.normal(size=3))
    if motion == "vertical":
        return np.array([0.0, 0.0, rng.choice([-1.0, 1.0])])
    if motion == "none":
        return np.zeros(3)
    raise ValueError(f"motion: expected sideways, forward, random, vertical or none, got {motion!r}")


def _points(
    rng: np.random.Generator,
    n_points: int,
    structure: Structure,
    R_ned_cam1: np.ndarray,
    distance_m: float,
    depth_fraction: float,
    fov_half_rad: float,
    direction: np.ndarray,
    baseline_m: float,
    line_along_baseline: bool,
) -> np.ndarray:
    """(n_points, 3) scene points in NED, camera 1 at the origin (see :func:`make_scene`)."""
    axis1 = R_ned_cam1[:, 2]

    def rays(n: int) -> np.ndarray:
        # Directions within the field of view of camera 1, in NED.
        ang = fov_half_rad * np.sqrt(rng.uniform(0, 1, n))
        phi = rng.uniform(-np.pi, np.pi, n)
        d_cam = np.stack([np.sin(ang) * np.cos(phi), np.sin(ang) * np.sin(phi), np.cos(ang)], axis=1)
        return d_cam @ R_ned_cam1.T

    if structure == "volume":
        depth = distance_m * (1.0 + depth_fraction * rng.uniform(-0.5, 0.5, n_points))
        d = rays(n_points)
        X = d * (depth / (d @ axis1))[:, None]
    elif structure in ("ground", "plane"):
        normal = np.array([0.0, 0.0, 1.0]) if structure == "ground" else _unit(axis1 + 0.6 * _unit(rng.normal(size=3)))
        anchor = distance_m * axis1
        d = rays(n_points)
        with np.errstate(divide="ignore"):
            depth = (anchor @ normal) / (d @ normal)
        X = d * depth[:, None]
    elif structure == "line":
        # Off the optical axis, so that forward motion does not make the line cross the baseline.
        anchor = distance_m * (axis1 + 0.3 * _unit(np.cross(axis1, _unit(rng.normal(size=3)))))
        if line_along_baseline:
            if baseline_m == 0:
                raise ValueError("line_along_baseline: needs motion other than 'none'")
            along = direction
        else:
            along = _unit(np.cross(axis1, _unit(rng.normal(size=3))))
        X = anchor + np.outer(rng.uniform(-0.4, 0.4, n_points) * distance_m, along)
    else:
        raise ValueError(f"structure: expected volume, ground, plane or line, got {structure!r}")
    return X


def _scene_from_points(
    rng: np.random.Generator,
    X: np.ndarray,
    att: list[tuple[float, float, float]],
    R_body_cam: np.ndarray,
    R_ned_cam1: np.ndarray,
    p2: np.ndarray,
    baseline_m: float,
    pixel_noise_px: float,
    imu_noise_rad: float,
    focal_px: float,
) -> TwoViewScene | None:
    """The two views of points ``X`` from attitudes ``att`` (roll, pitch, yaw each), camera 2 at ``p2``;
    None when a point is behind a camera."""
    R_ned_cam2 = R_from_euler321(*att[1]) @ R_body_cam
    x1 = X @ R_ned_cam1  # rows R_cam1_ned @ X
    x2 = (X - p2) @ R_ned_cam2
    if np.any(x1[:, 2] <= 0) or np.any(x2[:, 2] <= 0) or not np.all(np.isfinite(X)):
        return None
    f1_cam = _noisy_bearings(_unit(x1), rng, pixel_noise_px, focal_px)
    f2_cam = _noisy_bearings(_unit(x2), rng, pixel_noise_px, focal_px)

    reported = [
        (r + rng.normal(0, imu_noise_rad), p + rng.normal(0, imu_noise_rad)) if imu_noise_rad > 0 else (r, p)
        for r, p, _ in att
    ]
    R_lc1 = R_lvl_cam(*reported[0], R_body_cam)
    R_lc2 = R_lvl_cam(*reported[1], R_body_cam)

    yaw1, yaw2 = att[0][2], att[1][2]
    c, s = np.cos(yaw1 - yaw2), np.sin(yaw1 - yaw2)
    R_2_1 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    c2, s2 = np.cos(yaw2), np.sin(yaw2)
    R_lvl2_ned = np.array([[c2, s2, 0.0], [-s2, c2, 0.0], [0.0, 0.0, 1.0]])
    t = R_lvl2_ned @ (-p2)
    t_2_1 = t / baseline_m if baseline_m > 0 else t
    return TwoViewScene(
        f1_lvl=f1_cam @ R_lc1.T,
        f2_lvl=f2_cam @ R_lc2.T,
        f1_cam=f1_cam,
        f2_cam=f2_cam,
        R_2_1=R_2_1,
        t_2_1=t_2_1,
        baseline_m=baseline_m,
        points_ned=X,
        R_lvl_cam1=R_lc1,
        R_lvl_cam2=R_lc2,
        R_c2_c1=R_ned_cam2.T @ R_ned_cam1,
        t_c2_c1=R_ned_cam2.T @ (-p2) / (baseline_m if baseline_m > 0 else 1.0),
    )


def add_outliers(
    scene: TwoViewScene, fraction: float, rng: np.random.Generator, fov_half_rad: float = np.radians(30.0)
) -> tuple[TwoViewScene, np.ndarray]:
    """Replace a fraction of view 2's bearings by random directions within its field of view.

    Returns the new scene and the (N,) bool mask of the replaced (outlier) correspondences; exactly
    ``round(fraction * N)`` of them.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction: expected a value in [0, 1], got {fraction}")
    n = len(scene.f2_cam)
    outlier = np.zeros(n, dtype=bool)
    outlier[rng.choice(n, int(round(fraction * n)), replace=False)] = True
    k = int(outlier.sum())
    ang = fov_half_rad * np.sqrt(rng.uniform(0.0, 1.0, k))
    phi = rng.uniform(-np.pi, np.pi, k)
    f2_cam = scene.f2_cam.copy()
    f2_cam[outlier] = np.stack([np.sin(ang) * np.cos(phi), np.sin(ang) * np.sin(phi), np.cos(ang)], axis=1)
    return replace(scene, f2_cam=f2_cam, f2_lvl=f2_cam @ scene.R_lvl_cam2.T), outlier
