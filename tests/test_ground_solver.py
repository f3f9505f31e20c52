"""The known-gravity ground-plane homography from 2 points."""

from __future__ import annotations

import numpy as np
import pytest

from mavvo.geometry import ground_pose_from_homography, solve_ground_2pt_batch
from mavvo.geometry.frames import rotation_angle_rad
from mavvo.geometry.residuals import ground_sq
from mavvo.sim.world.twoview import make_scene


def _ground_scenes(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [
        make_scene(
            rng,
            6,
            structure="ground",
            mount="nadir",
            motion=("sideways", "forward", "random", "vertical")[i % 4],
            baseline_fraction=0.3,
        )
        for i in range(n)
    ]


def test_two_points_give_the_exact_pose_per_height() -> None:
    scenes = _ground_scenes(200)
    F1 = np.stack([s.f1_lvl[:2] for s in scenes])
    F2 = np.stack([s.f2_lvl[:2] for s in scenes])
    H, valid = solve_ground_2pt_batch(F1, F2)
    assert valid.all()
    for s, h in zip(scenes, H):
        R, t_per_h = ground_pose_from_homography(h)
        height1_m = s.points_ned[0, 2]
        assert rotation_angle_rad(R, s.R_2_1) < 1e-9
        np.testing.assert_allclose(t_per_h * height1_m, s.t_2_1 * s.baseline_m, atol=1e-9 * s.baseline_m + 1e-12)
        # The other four points, not used by the solver, fit too.
        assert np.max(ground_sq(h, s.f1_lvl, s.f2_lvl)) < 1e-20


def test_points_above_the_horizon_or_coincident_are_invalid() -> None:
    s = _ground_scenes(1)[0]
    up = s.f1_lvl[:2] * np.array([1.0, 1.0, -1.0])
    same = np.repeat(s.f1_lvl[:1], 2, axis=0)
    F1 = np.stack([s.f1_lvl[:2], up, same])
    F2 = np.stack([s.f2_lvl[:2], s.f2_lvl[:2], np.repeat(s.f2_lvl[:1], 2, axis=0)])
    H, valid = solve_ground_2pt_batch(F1, F2)
    assert valid.tolist() == [True, False, False]
    assert np.all(np.isnan(H[1:]))


@pytest.mark.parametrize("shape", [(4, 3, 3), (4, 2, 2), (2, 3)])
def test_wrong_shapes_raise(shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError, match="F1"):
        solve_ground_2pt_batch(np.ones(shape), np.ones(shape))
