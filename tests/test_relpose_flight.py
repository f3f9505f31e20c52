"""The relative pose on pairs the frontend tracked in a rendered flight, with roll/pitch off as a
flight controller's are."""

from __future__ import annotations

import math

import numpy as np
import pytest

import mavvo.estimation.attitude_refine as attitude_refine
import mavvo.estimation.model_selection as model_selection
from mavvo.estimation.relpose import estimate_relpose_known_gravity
from mavvo.geometry.frames import R_lvl_cam, angle_between_rad, rotation_angle_rad
from mavvo.odometry.frontend import FrontendOptions
from mavvo.sim.scenarios.tracked_pairs import TrackedPair, tracked_pairs


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
        r = estimate_relpose_known_gravity(
            p.uv1,
            p.uv2,
            camera,
            R1,
            R2,
            max_err_px=1.0,
            seed=i,
            attitude_sigma_rad=(sigma, sigma),
            yaw_prior_rad=p.yaw_2_1,
        )
        ok += bool(
            r.success
            and math.degrees(rotation_angle_rad(r.R_c2_c1, p.R_c2_c1)) < 2.0
            and math.degrees(angle_between_rad(r.t_c2_c1, p.t_c2_c1)) < 10.0
        )
    return ok


def test_both_ways_out_of_a_tilted_hypothesis_find_the_pose(survey_pairs, monkeypatch) -> None:
    """Over flat ground with roll/pitch 0.5-1 deg off, a 3-point hypothesis can take the tilt's flow for
    translation. Two things put it right, each needed: the refinement started from the ground
    homography's pose (the first's local minimum is another answer), and on pairs with less parallax
    than the attitude's relative sigma, correcting roll/pitch where that fits significantly better
    (kept as given, the tilt's flow stays in the translation). 121 of 138 when written; 94 without the
    plane's start; 85 with roll/pitch kept as given at low parallax."""
    pairs, camera = survey_pairs
    runs = [(level, seed) for level in (0.5, 1.0) for seed in (1, 2, 3)]

    def found() -> int:
        return sum(_successes(pairs, camera, level, seed) for level, seed in runs)

    both = found()
    with monkeypatch.context() as m:
        m.setattr(attitude_refine, "estimate_ground_plane_relpose", lambda *args, **kwargs: None)
        m.setattr(attitude_refine, "estimate_general_start", lambda *args, **kwargs: None)
        without_plane = found()
    monkeypatch.setattr(attitude_refine, "_CORRECTION_MIN_COST_DROP", math.inf)
    as_given = found()
    assert len(pairs) == 23
    assert both >= 112, both
    assert both >= without_plane + 15, (both, without_plane)
    assert both >= as_given + 20, (both, as_given)


@pytest.fixture(scope="module")
def forward_pairs():
    """7 pairs from the first 2 s of the forward flight (climbing away over mixed terrain)."""
    return tracked_pairs("forward", 2.0)


def test_off_the_ground_the_general_five_point_is_the_second_start(forward_pairs, monkeypatch) -> None:
    """Where the scene is not a ground plane, a hypothesis made with roll/pitch 0.5-1 deg off can refine
    into a local minimum too (forward pair 2 of ``benchmarks/relpose_flight.py`` at 0.5 deg: 42 deg
    off, at 4.6x the cost of the refinement started from the truth). The general 5-point does not use
    roll/pitch; refined from its pose, the better answer is kept. 104 of 140 when written, 79 without."""
    pairs, camera = forward_pairs
    runs = [(level, seed) for level in (0.5, 1.0) for seed in range(1, 11)]

    def found() -> int:
        return sum(_successes(pairs, camera, level, seed) for level, seed in runs)

    with_start = found()
    monkeypatch.setattr(attitude_refine, "estimate_general_start", lambda *args, **kwargs: None)
    without = found()
    assert len(pairs) == 7
    assert with_start >= 95, with_start
    assert with_start >= without + 15, (with_start, without)


def test_the_translation_sign_is_decided_on_the_corrected_bearings(survey_pairs) -> None:
    """With roll/pitch 1 deg off per view and axis, the relative tilt's flow can outweigh a pair's
    parallax, and the sign of the translation decided on the bearings as given comes out flipped. The
    Sampson cost of the refinement is the same for t and -t, so the sign must be decided again on the
    bearings it corrected. Five pairs of 184 (eight seeds) came out 180 deg off when it was not; none
    since."""
    pairs, camera = survey_pairs
    sigma = math.radians(1.0)
    flipped, found = [], 0
    for seed in range(1, 9):
        rng = np.random.default_rng(seed)
        for i, p in enumerate(pairs):
            e = sigma * rng.standard_normal((2, 2))
            R1 = R_lvl_cam(p.rp1[0] + e[0, 0], p.rp1[1] + e[0, 1], p.R_body_cam)
            R2 = R_lvl_cam(p.rp2[0] + e[1, 0], p.rp2[1] + e[1, 1], p.R_body_cam)
            r = estimate_relpose_known_gravity(
                p.uv1,
                p.uv2,
                camera,
                R1,
                R2,
                max_err_px=1.0,
                seed=i,
                attitude_sigma_rad=(sigma, sigma),
                yaw_prior_rad=p.yaw_2_1,
            )
            off_deg = math.degrees(angle_between_rad(r.t_c2_c1, p.t_c2_c1))
            if r.success and off_deg > 170.0:
                flipped.append((seed, i))
            found += bool(r.success and off_deg < 10.0)
    assert len(pairs) == 23
    assert flipped == []
    assert found >= 150, found  # the poses are found, not merely never flipped


def test_the_ground_models_pose_is_refined_with_the_corrections(monkeypatch) -> None:
    """The ground homography is fitted with the essential fit's roll/pitch corrections held, and its
    transfer error carries their residual error into yaw and translation; refined jointly with the
    corrections on the epipolar error, from the homography's pose, the pose is closer to the truth
    where roll/pitch are off. Over the 40 s survey at 0.5 and 1 deg per view, of the 137 pairs the ground
    model took when written, the refined rotation was the lower on 65%, the medians 0.0060 against
    0.0075 deg (translation 0.23 against 0.28 deg)."""
    pairs, camera = tracked_pairs("survey", 40.0)

    def ground_errors() -> list[tuple[int, float, float]]:
        out = []
        for level, seed in ((0.5, 1), (1.0, 2)):
            rng = np.random.default_rng(seed)
            sigma = math.radians(level)
            for i, p in enumerate(pairs):
                e = sigma * rng.standard_normal((2, 2))
                R1 = R_lvl_cam(p.rp1[0] + e[0, 0], p.rp1[1] + e[0, 1], p.R_body_cam)
                R2 = R_lvl_cam(p.rp2[0] + e[1, 0], p.rp2[1] + e[1, 1], p.R_body_cam)
                r = estimate_relpose_known_gravity(
                    p.uv1,
                    p.uv2,
                    camera,
                    R1,
                    R2,
                    max_err_px=1.0,
                    seed=i,
                    attitude_sigma_rad=(sigma, sigma),
                    yaw_prior_rad=p.yaw_2_1,
                )
                if r.upright.model == "ground":
                    out.append(
                        (
                            i + 1000 * seed,
                            math.degrees(rotation_angle_rad(r.R_c2_c1, p.R_c2_c1)),
                            math.degrees(angle_between_rad(r.t_c2_c1, p.t_c2_c1)),
                        )
                    )
        return out

    refined = ground_errors()
    monkeypatch.setattr(model_selection, "_ground_refined", lambda f1, f2, ground, *args: ground)
    held = ground_errors()
    assert [k for k, _, _ in refined] == [k for k, _, _ in held]  # the same pairs took the ground model
    assert len(refined) >= 100, len(refined)
    rot_refined, rot_held = np.array([r for _, r, _ in refined]), np.array([r for _, r, _ in held])
    assert np.mean(rot_refined < rot_held) >= 0.58, np.mean(rot_refined < rot_held)
    assert np.median(rot_refined) <= 0.9 * np.median(rot_held), (np.median(rot_refined), np.median(rot_held))
    assert np.all(rot_refined < 0.1)  # refined, no pose left the homography's basin


def test_the_ground_start_is_taken_from_five_noise_sigmas_of_parallax(monkeypatch) -> None:
    """Survey pair 134 of ``benchmarks/relpose_flight.py`` (495 tracks of 0.026 px, 0.29 px of parallax)
    with roll/pitch biased 0.5 deg: the ground homography's start has 9.9 noise sigmas of parallax,
    and at the pure-rotation rule's ten it was not taken; the first refinement then ended in the
    plane's other pose (a near-vertical translation), which leaves too little parallax about z and is
    reported as a rotation. Over 30 draws of the bias: 30 found when written, 26 with the floor at ten."""
    pairs, camera = tracked_pairs(
        "survey", 35.0, frontend_options=FrontendOptions(max_features=500, min_distance_px=6.0)
    )
    p = pairs[134]
    s = math.radians(0.5)

    def found() -> int:
        ok = 0
        for draw in range(30):
            rng = np.random.default_rng(draw)
            e = s * rng.standard_normal(2)[None, :] + math.radians(0.05) * rng.standard_normal((2, 2))
            R1 = R_lvl_cam(p.rp1[0] + e[0, 0], p.rp1[1] + e[0, 1], p.R_body_cam)
            R2 = R_lvl_cam(p.rp2[0] + e[1, 0], p.rp2[1] + e[1, 1], p.R_body_cam)
            r = estimate_relpose_known_gravity(
                p.uv1,
                p.uv2,
                camera,
                R1,
                R2,
                max_err_px=1.0,
                seed=134,
                attitude_sigma_rad=(s, s),
                yaw_prior_rad=p.yaw_2_1,
            )
            ok += bool(
                r.success
                and math.degrees(rotation_angle_rad(r.R_c2_c1, p.R_c2_c1)) < 2.0
                and math.degrees(angle_between_rad(r.t_c2_c1, p.t_c2_c1)) < 10.0
            )
        return ok

    at_five = found()
    monkeypatch.setattr(attitude_refine, "_PLANE_START_NOISE_SIGMAS", 10.0)
    at_ten = found()
    assert len(p.uv1) > 400
    assert at_five >= 29, at_five
    assert at_five >= at_ten + 3, (at_five, at_ten)


def test_the_widened_rounds_weigh_with_one_noise_sigma(monkeypatch) -> None:
    """While the attitude rounds' threshold is still widened for the tilt error a hypothesis inherits,
    the set holds outliers and the pose is off; a Cauchy loss of one noise sigma there (2.385 at the
    tight threshold, as before) keeps them from pulling the rounds to another fixed point. The forward
    camera over texture 4 (20 s, 79 pairs at the flight benchmark's density), roll/pitch exact and
    0.2 deg off per view, 0.2 deg told: when written, 154 of 158 found either way (the first two pairs
    are called rotations both ways), median rotation error 0.0343 against 0.0384 deg with 2.385
    throughout, the lower on 71% of the pairs found and the higher on 29%."""
    pairs, camera = tracked_pairs(
        "forward", 20.0, frontend_options=FrontendOptions(max_features=500, min_distance_px=6.0), variant=4
    )
    sigma = math.radians(0.2)

    def rotation_errors() -> np.ndarray:
        out = []
        for level, seed in ((0.0, 0), (0.2, 20)):
            rng = np.random.default_rng(seed)
            for i, p in enumerate(pairs):
                e = math.radians(level) * rng.standard_normal((2, 2))
                R1 = R_lvl_cam(p.rp1[0] + e[0, 0], p.rp1[1] + e[0, 1], p.R_body_cam)
                R2 = R_lvl_cam(p.rp2[0] + e[1, 0], p.rp2[1] + e[1, 1], p.R_body_cam)
                r = estimate_relpose_known_gravity(
                    p.uv1,
                    p.uv2,
                    camera,
                    R1,
                    R2,
                    max_err_px=1.0,
                    seed=i,
                    attitude_sigma_rad=(sigma, sigma),
                    yaw_prior_rad=p.yaw_2_1,
                )
                out.append(math.degrees(rotation_angle_rad(r.R_c2_c1, p.R_c2_c1)) if r.success else math.inf)
        return np.array(out)

    tight = rotation_errors()
    monkeypatch.setattr(attitude_refine, "_CAUCHY_WIDE_NOISE_SIGMAS", attitude_refine._CAUCHY_NOISE_SIGMAS)
    efficient = rotation_errors()
    found = np.isfinite(tight)
    assert len(pairs) >= 70 and np.count_nonzero(found) >= np.count_nonzero(np.isfinite(efficient)) >= 0.9 * found.size
    lower, higher = np.mean(tight[found] < efficient[found]), np.mean(tight[found] > efficient[found])
    assert lower >= 0.6 and lower >= higher + 0.2, (lower, higher)
    assert np.median(tight) <= 0.95 * np.median(efficient), (np.median(tight), np.median(efficient))


def test_the_tight_loss_is_kept_to_pairs_whose_parallax_resolves_a_tilt(
    forward_pairs, survey_pairs, monkeypatch
) -> None:
    """With less parallax than the relative attitude sigma and three thresholds a tilt and a translation
    explain the same flow, and a tight loss in the widened rounds let the fit settle on a subset (in a
    spin on the spot, essential fits on 72-85 points where a rotation explained 218-229): there the
    rounds keep the efficient scale. The forward camera's pairs are resolved once it is under way; the
    survey's slow start (a few px of parallax from 30 m, 0.5 deg per view) is not."""
    scales: list[float | None] = []
    rounds_from = attitude_refine._attitude_rounds_from

    def spy(*args, **kwargs):  # type: ignore[no-untyped-def]
        scales.append(args[10] if len(args) > 10 else kwargs.get("wide_c_sigmas"))
        return rounds_from(*args, **kwargs)

    monkeypatch.setattr(attitude_refine, "_attitude_rounds_from", spy)

    def first_scales(pairs: list[TrackedPair], camera, level_deg: float) -> list[float | None]:
        out = []
        sigma = math.radians(level_deg)
        for i, p in enumerate(pairs):
            scales.clear()
            R1 = R_lvl_cam(p.rp1[0], p.rp1[1], p.R_body_cam)
            R2 = R_lvl_cam(p.rp2[0], p.rp2[1], p.R_body_cam)
            estimate_relpose_known_gravity(
                p.uv1,
                p.uv2,
                camera,
                R1,
                R2,
                max_err_px=1.0,
                seed=i,
                attitude_sigma_rad=(sigma, sigma),
                yaw_prior_rad=p.yaw_2_1,
            )
            out.append(scales[0])  # the refinement from the sampling's hypothesis
        return out

    forward = first_scales(*forward_pairs, 0.2)
    survey = first_scales(*survey_pairs, 0.5)
    tight, efficient = attitude_refine._CAUCHY_WIDE_NOISE_SIGMAS, attitude_refine._CAUCHY_NOISE_SIGMAS
    assert tight < efficient
    # When written: forward 2.385 on the first three pairs (the circle's start), then 1.0; the survey
    # 2.385 on its first 14 pairs, then 1.0 as it gathers speed.
    assert forward[3:] == [tight] * (len(forward) - 3) and efficient in forward, forward
    assert survey[:10] == [efficient] * 10 and tight in survey, survey
