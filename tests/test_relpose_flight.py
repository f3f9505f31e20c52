"""The relative pose on pairs the frontend tracked in a rendered flight, with roll/pitch off as a
flight controller's are."""

from __future__ import annotations

import math

import numpy as np
import pytest

import mavvo.estimation.relpose as relpose
from mavvo.estimation.relpose import estimate_relpose_known_gravity
from mavvo.geometry.frames import R_lvl_cam, angle_between_rad, rotation_angle_rad
from sim.scenarios.tracked_pairs import TrackedPair, tracked_pairs


@pytest.fixture(scope="module")
def survey_pairs():
    """23 pairs 0.5 s apart from the first 6 s of the nadir survey flight (slow: a few px of parallax)."""
    return tracked_pairs("survey", 6.0)


def _successes(pairs: list[TrackedPair], camera, level_deg: float, seed: int) -> int:
    """Pairs whose pose is found within 2 deg of rotation and 10 deg of translation direction, with
    roll/pitch off by ``level_deg`` per view and axis (seeded) and that sigma given."""
    rng = np.random.default_rng(seed)
    sigma = math.radians(level_deg)
    ok = 0
    for i, p in enumerate(pairs):
        e = sigma * rng.standard_normal((2, 2))
        R1 = R_lvl_cam(p.rp1[0] + e[0, 0], p.rp1[1] + e[0, 1], p.R_body_cam)
        R2 = R_lvl_cam(p.rp2[0] + e[1, 0], p.rp2[1] + e[1, 1], p.R_body_cam)
        r = estimate_relpose_known_gravity(p.uv1, p.uv2, camera, R1, R2, max_err_px=1.0, seed=i, attitude_sigma_rad=(sigma, sigma), yaw_prior_rad=p.yaw_2_1)
        ok += bool(r.success and math.degrees(rotation_angle_rad(r.R_c2_c1, p.R_c2_c1)) < 2.0 and math.degrees(angle_between_rad(r.t_c2_c1, p.t_c2_c1)) < 10.0)
    return ok


def test_the_ground_plane_start_finds_the_pose_a_tilted_hypothesis_misses(survey_pairs, monkeypatch) -> None:
    """Over flat ground with roll/pitch 0.5-1 deg off, a 3-point hypothesis can take the tilt's flow for
    translation and refine into a local minimum; the refinement started from the ground homography's
    pose finds the right one. 85 of 138 when written; 73 without the plane's start."""
    pairs, camera = survey_pairs
    runs = [(level, seed) for level in (0.5, 1.0) for seed in (1, 2, 3)]
    with_plane = sum(_successes(pairs, camera, level, seed) for level, seed in runs)
    monkeypatch.setattr(relpose, "estimate_ground_plane_relpose", lambda *args, **kwargs: None)
    without = sum(_successes(pairs, camera, level, seed) for level, seed in runs)
    assert len(pairs) == 23
    assert with_plane >= 80, with_plane
    assert with_plane >= without + 8, (with_plane, without)
