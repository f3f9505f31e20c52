"""Each estimator the LO-RANSAC loop runs (mavvo.estimation.estimators) and the general 5-point
fallback, against exact data: a sample of noise-free correspondences gives the true model among its
hypotheses, the true model leaves no residual on any point, a refinement on all points from a
perturbed model returns the true one, and the loop, with outliers among the points, finds the true
model and exactly the true inliers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mavvo.estimation.estimators import (
    GroundHomography,
    PureRotation,
    UprightEssential,
    decompose_upright,
    upright_e,
    yaw_of,
)
from mavvo.estimation.general5pt import estimate_general_relpose
from mavvo.estimation.ransac import RansacOptions, lo_ransac
from mavvo.geometry.frames import rot_z, rotation_angle_rad
from mavvo.geometry.ground_2pt import ground_pose_from_homography
from mavvo.geometry.refine import tilt_rotation
from mavvo.geometry.residuals import ground_sq, rotation_sq
from mavvo.sim.world.twoview import TwoViewScene, add_outliers, make_scene

EXACT_SQ = 1e-24  # squared residual (rad^2) of an exact model on exact data: rounding only
THRESHOLD_RAD = 1.0 / 500  # a pixel at 500 px focal length


def _scene(seed: int, **kwargs) -> TwoViewScene:  # type: ignore[no-untyped-def]
    return make_scene(np.random.default_rng(seed), 60, **kwargs)


def _unit_e(yaw: float, t: np.ndarray) -> np.ndarray:
    e = upright_e(yaw, t)
    return e / np.linalg.norm(e)


def _distance_to(e_models: np.ndarray, e_true: np.ndarray) -> float:
    """Smallest distance of the unit e vectors (M, 6) to e_true (6,), up to sign; inf without models."""
    if len(e_models) == 0:
        return math.inf
    e = e_models / np.linalg.norm(e_models, axis=1, keepdims=True)
    return float(np.min(np.minimum(np.linalg.norm(e - e_true, axis=1), np.linalg.norm(e + e_true, axis=1))))


def _true_ground_homography(scene: TwoViewScene) -> np.ndarray:
    """``x_2 = (R_2_1 + (t_2_1 / d1) e_z^T) x_1`` for points on the ground d1 below view 1 (level z is down)."""
    d1 = float(scene.points_ned[0, 2])
    assert np.allclose(scene.points_ned[:, 2], d1) and d1 > 0
    return scene.R_2_1 + np.outer(scene.t_2_1 * scene.baseline_m / d1, [0.0, 0.0, 1.0])


@pytest.mark.parametrize("solver", ["3pt", "4pt", "linear5pt"])
def test_the_upright_essential_is_exact_on_exact_data(solver: str) -> None:
    scene = _scene(1, motion="random")
    f1, f2 = scene.f1_lvl, scene.f2_lvl
    truth = _unit_e(yaw_of(scene.R_2_1), scene.t_2_1)
    est = UprightEssential(f1, f2, solver=solver, lo_steps=10)
    k = est.sample_size
    assert k == {"3pt": 3, "4pt": 4, "linear5pt": 5}[solver]
    samples = np.arange(4 * k).reshape(4, k)
    models = est.generate(samples)
    assert _distance_to(models, truth) < 1e-9, models
    assert est.residuals_sq(truth[None]).max() < EXACT_SQ
    assert est.costs(truth[None], THRESHOLD_RAD**2)[0] < len(f1) * EXACT_SQ
    everyone = np.ones(len(f1), dtype=bool)
    off = _unit_e(yaw_of(scene.R_2_1) + 0.02, scene.t_2_1 + np.array([0.03, -0.02, 0.01]))
    refined = est.refine(off[None], everyone)
    assert len(refined) == 1 and _distance_to(refined, truth) < 1e-9
    yaw, t = decompose_upright(refined[0], f1, f2)  # type: ignore[misc]
    assert abs(math.remainder(yaw - yaw_of(scene.R_2_1), math.tau)) < 1e-9 and np.allclose(t, scene.t_2_1, atol=1e-9)


@pytest.mark.parametrize("nonminimal", ["4pt", "linear5pt"])
def test_the_upright_essential_least_squares_refit_is_exact_on_exact_data(nonminimal: str) -> None:
    scene = _scene(2, motion="sideways")
    truth = _unit_e(yaw_of(scene.R_2_1), scene.t_2_1)
    est = UprightEssential(scene.f1_lvl, scene.f2_lvl, nonminimal=nonminimal, lo_steps=0)  # the least squares alone
    off = _unit_e(yaw_of(scene.R_2_1) + 0.1, scene.t_2_1 + np.array([0.2, 0.1, -0.1]))
    refined = est.refine(off[None], np.ones(len(scene.f1_lvl), dtype=bool))
    assert len(refined) >= 1 and _distance_to(refined, truth) < 1e-9


def test_the_ground_homography_is_exact_on_exact_data() -> None:
    scene = _scene(3, motion="sideways", structure="ground")
    f1, f2 = scene.f1_lvl, scene.f2_lvl
    H_true = _true_ground_homography(scene)
    t_per_height = scene.t_2_1 * scene.baseline_m / scene.points_ned[0, 2]
    est = GroundHomography(f1, f2)
    assert est.sample_size == 2
    assert est.residuals_sq(H_true[None]).max() < EXACT_SQ
    assert est.costs(H_true[None], THRESHOLD_RAD**2)[0] < len(f1) * EXACT_SQ

    def pose_error(H: np.ndarray) -> float:
        R, t = ground_pose_from_homography(H)
        return max(rotation_angle_rad(R, scene.R_2_1), float(np.linalg.norm(t - t_per_height)))

    models = est.generate(np.arange(8).reshape(4, 2))
    assert len(models) >= 1 and min(pose_error(H) for H in models) < 1e-9
    off = H_true + 0.01 * np.array([[1.0, -2.0, 3.0], [2.0, 1.0, -1.0], [0.0, 0.0, 2.0]])
    refined = est.refine(off[None], np.ones(len(f1), dtype=bool))
    assert len(refined) == 1 and pose_error(refined[0]) < 1e-9
    assert ground_sq(refined[0], f1, f2).max() < EXACT_SQ


def test_the_pure_rotation_is_exact_on_exact_data() -> None:
    scene = _scene(4, motion="none")
    f1, f2 = scene.f1_lvl, scene.f2_lvl
    assert not np.any(scene.t_2_1)
    est = PureRotation(f1, f2)
    assert est.sample_size == 1
    models = est.generate(np.array([[5], [17]]))
    assert len(models) == 2 and all(rotation_angle_rad(R, scene.R_2_1) < 1e-12 for R in models)
    assert est.residuals_sq(scene.R_2_1[None]).max() < EXACT_SQ
    refined = est.refine(rot_z(yaw_of(scene.R_2_1) + 0.05)[None], np.ones(len(f1), dtype=bool))
    assert len(refined) == 1 and rotation_angle_rad(refined[0], scene.R_2_1) < 1e-12
    assert rotation_sq(refined[0], f1, f2).max() < EXACT_SQ


def test_the_general_five_point_is_exact_on_exact_data_whatever_the_roll_pitch() -> None:
    """The fallback's model needs no gravity: with view 2's level frame tilted 3 deg (a wrong roll/pitch)
    it still finds the relative pose exactly, tilt included."""
    scene = _scene(5, motion="sideways", max_tilt_rad=math.radians(10.0))
    T = tilt_rotation(np.radians([3.0, -2.0]))
    f2 = scene.f2_lvl @ T.T
    R_true, t_true = T @ scene.R_2_1, T @ scene.t_2_1
    out = estimate_general_relpose(scene.f1_lvl, f2, THRESHOLD_RAD, seed=1)
    assert out is not None
    R, t, E = out
    assert rotation_angle_rad(R, R_true) < 1e-7
    assert np.linalg.norm(t - t_true) < 1e-7
    assert abs(float(np.einsum("ij,jk,ik->", f2, E, scene.f1_lvl))) / len(f2) < 1e-10  # f2^T E f1 = 0 on every point


@pytest.mark.parametrize("model", ["essential", "ground", "rotation"])
def test_the_loop_finds_each_exact_model_and_exactly_its_inliers(model: str) -> None:
    rng = np.random.default_rng(6)
    kwargs = {
        "essential": dict(motion="random"),
        "ground": dict(motion="sideways", structure="ground"),
        "rotation": dict(motion="none"),
    }[model]
    scene, outlier = add_outliers(make_scene(rng, 200, **kwargs), 0.4, rng)
    f1, f2 = scene.f1_lvl, scene.f2_lvl
    est = {"essential": UprightEssential(f1, f2), "ground": GroundHomography(f1, f2), "rotation": PureRotation(f1, f2)}[
        model
    ]
    run = lo_ransac(est, RansacOptions(), THRESHOLD_RAD, np.random.default_rng(7))
    assert run.model is not None
    assert np.array_equal(run.inliers, ~outlier)
    assert run.err_sq[~outlier].max() < 1e-18  # refined on the exact inliers: rounding, squared
    if model == "essential":
        assert _distance_to(run.model, _unit_e(yaw_of(scene.R_2_1), scene.t_2_1)) < 1e-8
    elif model == "ground":
        R, t = ground_pose_from_homography(run.model[0])
        assert rotation_angle_rad(R, scene.R_2_1) < 1e-8
        assert np.linalg.norm(t - scene.t_2_1 * scene.baseline_m / scene.points_ned[0, 2]) < 1e-8
    else:
        assert rotation_angle_rad(run.model[0], scene.R_2_1) < 1e-8
