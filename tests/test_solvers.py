"""The paper's upright solvers: recovery, structure, degeneracies, the drone cases, bad input."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mavvo.geometry import (
    epipolar_rows,
    essential_from_vector,
    solve_upright_3pt,
    solve_upright_3pt_batch,
    solve_upright_4pt,
    solve_upright_linear5pt,
    upright_constraint_residual,
    upright_pose_from_essential,
)
from mavvo.geometry.frames import angle_between_rad, rotation_angle_rad
from mavvo.sim.world.twoview import TwoViewScene, make_scene

MOTIONS = ("sideways", "forward", "random")
MOUNTS = ("nadir", "oblique")
SOLVERS = {3: solve_upright_3pt, 4: solve_upright_4pt, 5: solve_upright_linear5pt}
TOL_RAD = 1e-6


def pose_errors(E: np.ndarray, scene: TwoViewScene) -> tuple[float, float]:
    """Rotation error and translation direction error (rad) of E decomposed against the truth."""
    R, t = upright_pose_from_essential(E, scene.f1_lvl, scene.f2_lvl)
    rot_err = rotation_angle_rad(R, scene.R_2_1)
    t_err = angle_between_rad(t, scene.t_2_1)
    return rot_err, t_err


def recovers(Es: np.ndarray, scene: TwoViewScene, tol: float = TOL_RAD) -> bool:
    return any(max(pose_errors(E, scene)) < tol for E in Es)


def scenes(seed: int, count: int, n_points: int, **kw) -> list[TwoViewScene]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        kw_i = {"motion": MOTIONS[i % 3], "mount": MOUNTS[(i // 3) % 2], **kw}
        out.append(make_scene(rng, n_points, **kw_i))
    return out


@pytest.mark.parametrize("n_points", [3, 4, 5])
def test_noise_free_recovery_over_1000_scenes(n_points: int) -> None:
    solver = SOLVERS[n_points]
    data = scenes(100 + n_points, 1002, n_points)
    ok = [recovers(solver(s.f1_lvl, s.f2_lvl), s) for s in data]
    assert np.mean(ok) >= 0.999, f"{n_points}-point recovered {np.mean(ok):.4f} of scenes"
    # Each motion and mount individually, so a weak case cannot hide behind the others.
    for i in range(6):
        assert np.mean(ok[i::6]) >= 0.99


def test_least_squares_solvers_recover_with_many_points() -> None:
    data = scenes(7, 60, 40)
    for solver in (solve_upright_4pt, solve_upright_linear5pt):
        assert all(recovers(solver(s.f1_lvl, s.f2_lvl), s, tol=1e-9) for s in data), solver.__name__


def test_batch_matches_single_calls() -> None:
    data = scenes(11, 300, 3)
    F1 = np.stack([s.f1_lvl for s in data])
    F2 = np.stack([s.f2_lvl for s in data])
    E_batch, valid = solve_upright_3pt_batch(F1, F2)
    assert E_batch.shape == (300, 4, 3, 3) and valid.shape == (300, 4)
    for b, s in enumerate(data):
        single = solve_upright_3pt(s.f1_lvl, s.f2_lvl)
        # Same solutions in the same order; BLAS kernels differ with batch size, so not bit for bit.
        np.testing.assert_allclose(single, E_batch[b][valid[b]], rtol=0, atol=1e-9)
    assert np.all(np.isnan(E_batch[~valid]))


def _assert_upright_structure(E: np.ndarray) -> None:
    assert E[2, 2] == 0.0
    assert E[0, 0] == E[1, 1] and E[0, 1] == -E[1, 0]
    assert abs(np.linalg.norm(E) - 1.0) < 1e-12


def _epipolar_residual(E: np.ndarray, s: TwoViewScene) -> float:
    return float(np.abs(np.einsum("ni,ij,nj->n", s.f2_lvl, E, s.f1_lvl)).max())


Run = tuple[int, int, bool, TwoViewScene, np.ndarray]


@pytest.fixture(scope="module")
def runs() -> list[Run]:
    """(solver points k, points given n, noisy, scene, solutions) over 300 scenes: each solver on its
    minimal input and (4- and 5-point) on 12 points, half of the scenes with 0.5 px noise."""
    rng = np.random.default_rng(21)
    runs = []
    for i in range(300):
        noisy = i % 2 == 1
        s = make_scene(rng, 12, motion=MOTIONS[i % 3], pixel_noise_px=0.5 if noisy else 0.0)
        for k, n in ((3, 3), (4, 4), (4, 12), (5, 5), (5, 12)):
            sub = replace(s, f1_lvl=s.f1_lvl[:n], f2_lvl=s.f2_lvl[:n])
            runs.append((k, n, noisy, sub, SOLVERS[k](sub.f1_lvl, sub.f2_lvl)))
    return runs


def test_every_solution_has_the_upright_structure(runs: list[Run]) -> None:
    for _, _, _, _, Es in runs:
        for E in Es:
            _assert_upright_structure(E)


def test_solution_counts_stay_within_the_papers_bounds(runs: list[Run]) -> None:
    for k, limit in ((3, 4), (4, 3), (5, 1)):
        counts = [len(Es) for kk, _, _, _, Es in runs if kk == k]
        assert max(counts) == limit and min(counts) >= 1, (k, min(counts), max(counts))


def test_minimal_input_is_fitted_exactly_even_with_noise(runs: list[Run]) -> None:
    minimal = [(s, Es) for k, n, _, s, Es in runs if n == k and k < 5]
    assert len(minimal) == 600
    assert all(_epipolar_residual(E, s) < 1e-9 for s, Es in minimal for E in Es)


def test_noise_free_overdetermined_input_has_a_solution_fitting_every_point(runs: list[Run]) -> None:
    # The 4-point's other det(E) = 0 roots on a least-squares pencil need not fit; the true one does.
    # The bound follows from the conditioning, not from one machine's rounding: a backward-stable SVD
    # turns the null vector by up to about eps * s_max / s_gap (s_gap: the smallest non-zero singular
    # value of the N x 6 system), which moves the residual by s_max times that; ten times it is room.
    clean = [(s, Es) for _, n, noisy, s, Es in runs if n == 12 and not noisy]
    assert len(clean) == 300
    eps = np.finfo(np.float64).eps
    worst = []
    for s, Es in clean:
        sv = np.linalg.svd(epipolar_rows(s.f1_lvl, s.f2_lvl), compute_uv=False)
        worst.append(min(_epipolar_residual(E, s) for E in Es) / (10 * eps * sv[0] ** 2 / sv[4]))
    assert max(worst) < 1.0


def test_3pt_and_linear_5pt_return_essential_matrices(runs: list[Run]) -> None:
    # The 4-point returns det(E) = 0 roots that need not satisfy the trace constraint.
    Es = np.concatenate([Es for k, _, _, _, Es in runs if k in (3, 5)])
    assert len(Es) > 1000
    assert np.all(upright_constraint_residual(Es) < 1e-7)


def test_plane_in_general_position_is_solved_by_all_three() -> None:
    rng = np.random.default_rng(31)
    for solver, n in ((solve_upright_3pt, 3), (solve_upright_4pt, 8), (solve_upright_linear5pt, 8)):
        ok = []
        for i in range(200):
            s = make_scene(rng, n, structure="plane", motion=MOTIONS[i % 3], mount="oblique")
            ok.append(recovers(solver(s.f1_lvl, s.f2_lvl), s))
        assert np.mean(ok) >= 0.99, (solver.__name__, np.mean(ok))


def test_three_collinear_points_are_solved_unless_parallel_to_the_baseline() -> None:
    rng = np.random.default_rng(41)
    ok = [
        recovers(solve_upright_3pt(s.f1_lvl, s.f2_lvl), s)
        for s in (make_scene(rng, 3, structure="line", motion=MOTIONS[i % 3]) for i in range(300))
    ]
    assert np.mean(ok) >= 0.99


def _no_wrong_solution(Es: np.ndarray, scene: TwoViewScene, check_translation: bool) -> bool:
    for E in Es:
        rot_err, t_err = pose_errors(E, scene)
        if rot_err > 1e-6 or (check_translation and t_err > 1e-6):
            return False
    return True


def test_line_parallel_to_the_baseline_gives_no_wrong_solution() -> None:
    # All three points share one epipolar plane: the true yaw fits with any translation in it.
    # Other yaws may still explain the three points exactly, as in any minimal problem; what must
    # never come back is a member of that continuum (true yaw, arbitrary translation) or a
    # matrix that does not explain its input.
    rng = np.random.default_rng(51)
    returned = 0
    for i in range(200):
        s = make_scene(rng, 3, structure="line", line_along_baseline=True, motion=MOTIONS[i % 3])
        Es = solve_upright_3pt(s.f1_lvl, s.f2_lvl)
        returned += len(Es)
        for E in Es:
            assert _epipolar_residual(E, s) < 1e-9 and upright_constraint_residual(E) < 1e-7
            rot_err, t_err = pose_errors(E, s)
            assert rot_err > 1e-3 or t_err < 1e-6, (i, rot_err, t_err)
    assert returned <= 20, "degenerate samples should mostly give no solution"
    # Control: a line across the baseline is no degeneracy for the 3-point; a solver that returns
    # nothing fails here.
    control = [
        make_scene(rng, 3, structure="line", line_along_baseline=False, motion=MOTIONS[i % 3]) for i in range(60)
    ]
    assert all(recovers(solve_upright_3pt(s.f1_lvl, s.f2_lvl), s) for s in control)


def test_zero_baseline_gives_no_wrong_solution() -> None:
    rng = np.random.default_rng(52)
    solvers = ((solve_upright_3pt, 3), (solve_upright_4pt, 6), (solve_upright_linear5pt, 6))
    for i in range(200):
        s = make_scene(rng, 6, motion="none", mount=MOUNTS[i % 2])
        for solver, n in solvers:
            Es = solver(s.f1_lvl[:n], s.f2_lvl[:n])
            # No translation to get wrong; whatever comes back must carry the true rotation.
            assert _no_wrong_solution(Es, s, check_translation=False), (i, solver.__name__)
    # Control: with a baseline every solver recovers the same kind of scene, so the loop above can
    # fail for a solver that returns wrong matrices, and one that returns nothing fails here.
    for i in range(30):
        s = make_scene(rng, 6, motion="sideways", mount=MOUNTS[i % 2])
        for solver, n in solvers:
            assert recovers(solver(s.f1_lvl[:n], s.f2_lvl[:n]), s), (i, solver.__name__)


def test_drone_case_motion_along_gravity() -> None:
    rng = np.random.default_rng(61)
    data = [
        make_scene(rng, 3, motion="vertical", mount=MOUNTS[i % 2], structure=("volume", "ground")[(i // 2) % 2])
        for i in range(1000)
    ]
    solutions = [solve_upright_3pt(s.f1_lvl, s.f2_lvl) for s in data]
    ok = [recovers(Es, s) for Es, s in zip(solutions, data)]
    assert np.mean(ok) >= 0.99, np.mean(ok)
    # Exactly vertical, both sheets give the same E: it comes back once, not twice.
    assert np.mean([len(Es) == 1 for Es in solutions]) >= 0.95


def test_nearly_pure_rotation_is_recovered() -> None:
    # Baselines of 1e-2 and 1e-3 of the scene distance: the null space passes near the vertical
    # point, where the sheet solutions of motion along gravity must not displace the true root.
    rng = np.random.default_rng(64)
    for baseline in (1e-2, 1e-3):
        ok = []
        for i in range(300):
            s = make_scene(rng, 3, motion=MOTIONS[i % 3])
            X2 = (s.f1_lvl * 10.0) @ s.R_2_1.T + baseline * s.t_2_1
            moved = replace(s, f2_lvl=X2 / np.linalg.norm(X2, axis=1, keepdims=True))
            ok.append(recovers(solve_upright_3pt(moved.f1_lvl, moved.f2_lvl), moved))
        assert np.mean(ok) >= 0.99, (baseline, np.mean(ok))


def test_drone_case_nadir_camera_over_flat_ground() -> None:
    rng = np.random.default_rng(62)
    data = [make_scene(rng, 6, motion=MOTIONS[i % 3], mount="nadir", structure="ground") for i in range(1000)]
    ok = [recovers(solve_upright_3pt(s.f1_lvl[:3], s.f2_lvl[:3]), s) for s in data]
    assert np.mean(ok) >= 0.99, np.mean(ok)
    # The 6-unknown system has rank 4 here: the 4-point and linear 5-point must decline.
    for s in data[:200]:
        assert np.linalg.matrix_rank(epipolar_rows(s.f1_lvl, s.f2_lvl), tol=1e-9) == 4
        assert len(solve_upright_4pt(s.f1_lvl, s.f2_lvl)) == 0
        assert len(solve_upright_4pt(s.f1_lvl[:4], s.f2_lvl[:4])) == 0
        assert len(solve_upright_linear5pt(s.f1_lvl, s.f2_lvl)) == 0


def test_near_vertical_motion_stays_accurate() -> None:
    # The paper's elimination degenerates as the motion approaches gravity; every tilt must work.
    rng = np.random.default_rng(63)
    for tilt in (3e-2, 1e-3, 1e-5, 1e-7, 1e-9, 1e-12):
        ok = []
        for _ in range(150):
            s = make_scene(rng, 3, motion="vertical")
            # Tilt the baseline by `tilt` rad: rebuild view 2 from the points.
            t = s.t_2_1 + tilt * np.array([1.0, 0.0, 0.0])
            t /= np.linalg.norm(t)
            X2 = (s.f1_lvl * 10.0) @ s.R_2_1.T + t
            f2 = X2 / np.linalg.norm(X2, axis=1, keepdims=True)
            moved = replace(s, f2_lvl=f2, t_2_1=t)
            ok.append(recovers(solve_upright_3pt(moved.f1_lvl, moved.f2_lvl), moved))
        assert np.mean(ok) >= 0.99, (tilt, np.mean(ok))


def test_decomposition_returns_rotation_about_z_and_unit_translation() -> None:
    rng = np.random.default_rng(71)
    for i in range(100):
        s = make_scene(rng, 3, motion=MOTIONS[i % 3])
        for E in solve_upright_3pt(s.f1_lvl, s.f2_lvl):
            R, t = upright_pose_from_essential(E, s.f1_lvl, s.f2_lvl)
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(R) == pytest.approx(1.0)
            np.testing.assert_allclose(R[2], [0, 0, 1], atol=1e-12)
            assert np.linalg.norm(t) == pytest.approx(1.0)
    # Scale and sign of E do not matter.
    s = make_scene(rng, 8, motion="sideways")
    E = solve_upright_linear5pt(s.f1_lvl, s.f2_lvl)[0]
    for scale in (-3.0, 1e-6, 1e6):
        assert max(pose_errors(E * scale, s)) < 1e-8


def test_points_behind_a_view_are_found_where_the_parallax_tells() -> None:
    """Every point of a scene lies in front of both views for the true pose; for the same pose with
    the translation reversed, the points with more parallax than the bound lie behind, and the ones
    with less are not judged (their side is noise)."""
    from mavvo.estimation.estimators import yaw_of
    from mavvo.geometry.upright_pose import behind_upright

    s = make_scene(np.random.default_rng(72), 200, motion="sideways", baseline_fraction=0.05)
    yaw = yaw_of(s.R_2_1)
    parallax = np.arccos(np.clip(np.einsum("ij,ij->i", s.f1_lvl @ s.R_2_1.T, s.f2_lvl), -1.0, 1.0))
    bound = float(np.median(parallax))
    assert not behind_upright(yaw, s.t_2_1, s.f1_lvl, s.f2_lvl, 0.0).any()
    reversed_ = behind_upright(yaw, -s.t_2_1, s.f1_lvl, s.f2_lvl, bound)
    np.testing.assert_array_equal(reversed_, parallax > bound)


def test_essential_vector_round_trip() -> None:
    e = np.arange(1.0, 7.0)
    E = essential_from_vector(e)
    assert E[0, 2] == 1 and E[1, 0] == 2 and E[1, 1] == 3 and E[1, 2] == 4 and E[2, 0] == 5 and E[2, 1] == 6
    assert E[0, 0] == 3 and E[0, 1] == -2 and E[2, 2] == 0
    f1 = np.array([[0.1, 0.2, 1.0], [0.3, -0.1, 0.9]])
    f2 = np.array([[-0.2, 0.1, 1.0], [0.0, 0.4, 0.8]])
    np.testing.assert_allclose(epipolar_rows(f1, f2) @ e, np.einsum("ni,ij,nj->n", f2, E, f1))


GOOD = np.array([[0.1, 0.2, 1.0], [0.3, -0.1, 0.9], [-0.2, 0.1, 1.1]])


@pytest.mark.parametrize(
    "f1, f2, match",
    [
        (GOOD[:2], GOOD[:2], "f1: expected exactly 3 bearings, got 2"),
        (GOOD[:, :2], GOOD, r"f1: expected an \(N,3\) array of bearings, got shape \(3, 2\)"),
        (GOOD, np.where(np.eye(3, dtype=bool), np.nan, GOOD), "f2: bearings must be finite"),
        (GOOD, np.vstack([GOOD[:2], [0.0, 0.0, 0.0]]), "f2: bearings must have non-zero length"),
        (np.full((3, 3), np.inf), GOOD, "f1: bearings must be finite"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(f1: np.ndarray, f2: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        solve_upright_3pt(f1, f2)


def test_bearings_of_any_finite_length_are_directions() -> None:
    """A bearing is a direction: rows whose squares overflow (1e200) solve as their unit rows do, alone
    and in a batch, where the single call used to end in an AssertionError."""
    rng = np.random.default_rng(11)
    s = make_scene(rng, 3, motion="forward", mount="nadir")
    scaled = s.f1_lvl * np.array([[1e200], [1.0], [3e-5]])
    expected = solve_upright_3pt(s.f1_lvl, s.f2_lvl)
    assert len(expected) > 0
    np.testing.assert_allclose(solve_upright_3pt(scaled, s.f2_lvl), expected, rtol=0, atol=1e-12)
    E, valid = solve_upright_3pt_batch(scaled[None], s.f2_lvl[None])
    np.testing.assert_allclose(E[0][valid[0]], expected, rtol=0, atol=1e-12)


def test_bad_input_for_the_other_solvers() -> None:
    with pytest.raises(ValueError, match="f1: expected at least 4"):
        solve_upright_4pt(GOOD, GOOD)
    with pytest.raises(ValueError, match="f1: expected at least 5"):
        solve_upright_linear5pt(np.vstack([GOOD, GOOD[:1]]), np.vstack([GOOD, GOOD[:1]]))
    with pytest.raises(ValueError, match="same number"):
        solve_upright_4pt(np.vstack([GOOD, GOOD]), np.vstack([GOOD, GOOD[:2]]))
    with pytest.raises(ValueError, match=r"F1: expected a \(B,3,3\)"):
        solve_upright_3pt_batch(GOOD, GOOD)
    with pytest.raises(ValueError, match="F2: bearings must be finite"):
        solve_upright_3pt_batch(GOOD[None], np.full((1, 3, 3), np.nan))
    with pytest.raises(ValueError, match=r"E: expected a finite \(3,3\)"):
        upright_pose_from_essential(np.eye(2), GOOD, GOOD)
