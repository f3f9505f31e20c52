"""Two-view pairs of a scenario's flight as the odometry's frontend tracks them, with the true relative
pose: for relative-pose benchmarks and tests on real tracking noise and real tracking failures.

The scenario's camera renders the flight (lockstep), mavvo's own frontend tracks it (KLT forward and
backward, corners topped up), and every ``every``-th frame is paired with the one ``gap`` frames later
on the tracks both hold. The truth is the trajectory's camera pose at both exposures.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from mavvo.geometry.camera_model import CameraModel
from mavvo.odometry.frontend import Frontend, FrontendOptions
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.paired_frames import PairedSequence

__all__ = ["TrackedPair", "tracked_pairs"]


@dataclass(frozen=True)
class TrackedPair:
    """Two views of one flight.

    Attributes:
        scenario: the scenario's name.
        uv1, uv2: (N, 2) tracked pixels of each view, undistorted onto the pinhole of the returned camera.
        rp1, rp2: the true (roll, pitch) of the body at each exposure, radians.
        yaw_2_1: true yaw between the level frames (heading at view 1 minus at view 2), radians.
        R_body_cam: (3, 3) the camera's mounting.
        R_c2_c1, t_c2_c1: true relative pose of the camera frames, ``x_c2 = R_c2_c1 @ x_c1 + t_c2_c1`` (t unit).
    """

    scenario: str
    uv1: np.ndarray
    uv2: np.ndarray
    rp1: tuple[float, float]
    rp2: tuple[float, float]
    yaw_2_1: float
    R_body_cam: np.ndarray
    R_c2_c1: np.ndarray
    t_c2_c1: np.ndarray


def tracked_pairs(
    name: str,
    duration_s: float,
    *,
    gap: int = 10,
    every: int = 5,
    min_tracks: int = 20,
    frontend_options: FrontendOptions | None = None,
    variant: int = 0,
) -> tuple[list[TrackedPair], CameraModel]:
    """The pairs of the first ``duration_s`` of scenario ``name`` (frames ``gap`` apart, one pair every
    ``every`` frames, at least ``min_tracks`` common tracks and some motion), tracked with
    ``frontend_options`` (the odometry's defaults when None), and the pinhole camera their pixels are on.

    ``variant`` 0 is the scenario as shipped; k > 0 flies the same path over another procedural
    texture (``world.texture_seed`` = k) with other camera noise (``seed`` + 100 k): other tracks,
    the same geometry."""
    if variant < 0:
        raise ValueError(f"variant: expected 0 (the scenario as shipped) or a positive texture number, got {variant}")
    sc = load_scenario(name)
    if variant:
        sc = dataclasses.replace(
            sc, seed=sc.seed + 100 * variant, world=dataclasses.replace(sc.world, texture_seed=variant)
        )
    seq = PairedSequence(sc, duration_s=duration_s)
    model = sc.camera.camera_model()
    pinhole = CameraModel(model.width_px, model.height_px, model.fx_px, model.fy_px, model.cx_px, model.cy_px)
    frontend = Frontend(model, frontend_options or FrontendOptions())
    R_body_cam = sc.camera.R_body_cam()
    lever = np.asarray(sc.camera.lever_arm_m, dtype=float)
    views = []
    for pf in seq:
        tracks = frontend.process(pf.image)
        st = seq.trajectory.state(pf.t_exposure_s)
        views.append(
            (
                tracks,
                (st.roll_rad, st.pitch_rad, st.yaw_rad),
                st.R_ned_body @ R_body_cam,
                st.p_ned_m + st.R_ned_body @ lever,
            )
        )

    def pixels(f: np.ndarray) -> np.ndarray:
        return np.column_stack(
            [model.fx_px * f[:, 0] / f[:, 2] + model.cx_px, model.fy_px * f[:, 1] / f[:, 2] + model.cy_px]
        )

    pairs = []
    for k in range(0, len(views) - gap, every):
        (ta, rpa, Ra, ca), (tb, rpb, Rb, cb) = views[k], views[k + gap]
        _, ia, ib = np.intersect1d(ta.ids, tb.ids, assume_unique=True, return_indices=True)
        if len(ia) < min_tracks or np.linalg.norm(cb - ca) < 1e-3:
            continue
        t = Rb.T @ (ca - cb)
        yaw = math.remainder(rpa[2] - rpb[2], math.tau)
        pairs.append(
            TrackedPair(
                name,
                pixels(ta.f_cam[ia]),
                pixels(tb.f_cam[ib]),
                rpa[:2],
                rpb[:2],
                yaw,
                R_body_cam,
                Rb.T @ Ra,
                t / np.linalg.norm(t),
            )
        )
    return pairs, pinhole
