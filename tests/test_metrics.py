"""Trajectory metrics on trajectories with known error, and the TUM / JSON / PNG outputs."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from mavvo.errors import ConfigError
from mavvo.evaluation.metrics import PoseSeries, align_umeyama, associate, evaluate
from mavvo.evaluation.report import plot_evaluation, read_tum, write_report, write_tum
from mavvo.geometry.frames import R_from_euler321
from mavvo.sim.world.trajectories import LawnmowerSpec, make_trajectory


def _truth(step_s: float = 0.1) -> PoseSeries:
    traj = make_trajectory(LawnmowerSpec(leg_m=40.0, legs=3, speed_m_s=4.0))
    t = np.arange(0.0, traj.duration_s, step_s)
    states = [traj.state(x) for x in t]
    return PoseSeries.from_rotations(t, np.array([s.p_ned_m for s in states]), np.array([s.R_ned_body for s in states]))


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = R_from_euler321(0.3, -0.2, 1.1)
    dst = 2.5 * src @ R.T + [1.0, -2.0, 3.0]
    R_, t_, s_ = align_umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(R_, R, atol=1e-12)
    np.testing.assert_allclose(t_, [1.0, -2.0, 3.0], atol=1e-12)
    assert s_ == pytest.approx(2.5)
    assert align_umeyama(src, dst, with_scale=False)[2] == 1.0


def test_a_rigidly_moved_copy_has_zero_error():
    gt = _truth()
    est = gt.transformed(R_from_euler321(0.0, 0.0, 0.8), np.array([5.0, -3.0, 1.0]))
    ev, aligned = evaluate(est, gt)
    assert ev.ate_se3_m["rmse"] < 1e-9 and ev.ate_sim3_m["rmse"] < 1e-9
    assert ev.rpe_translation_per_m["max"] < 1e-9 and ev.rpe_rotation_deg_per_s["max"] < 1e-6
    np.testing.assert_allclose(aligned.positions_xyz_m, gt.positions_xyz_m, atol=1e-9)


def test_scale_error_shows_in_se3_not_in_sim3():
    gt = _truth()
    est = PoseSeries(gt.timestamps_s, 1.1 * gt.positions_xyz_m, gt.orientations_quat_wxyz)
    ev, _ = evaluate(est, gt)
    assert ev.sim3_scale == pytest.approx(1 / 1.1)
    assert ev.ate_sim3_m["rmse"] < 1e-9
    assert ev.ate_se3_m["rmse"] > 0.5
    # 10% too long: 0.1 per metre on straight stretches, less where the span turns a corner
    assert ev.rpe_translation_per_m["max"] == pytest.approx(0.1, abs=1e-6) and ev.rpe_translation_per_m["median"] > 0.09


def test_known_ate_and_drift_per_metre():
    gt = _truth()
    n = len(gt)
    zigzag = np.where(np.arange(n) % 2 == 0, 0.1, -0.1)  # +-10 cm up and down: ATE RMSE 0.1 m
    est = PoseSeries(
        gt.timestamps_s,
        gt.positions_xyz_m + np.column_stack([np.zeros(n), np.zeros(n), zigzag]),
        gt.orientations_quat_wxyz,
    )
    ev, _ = evaluate(est, gt)
    assert ev.ate_se3_m["rmse"] == pytest.approx(0.1, rel=0.01)
    assert ev.ate_se3_rmse_percent_of_path == pytest.approx(100 * 0.1 / gt.path_length_m(), rel=0.01)

    # 2% drift to the east per metre flown
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt.positions_xyz_m, axis=0), axis=1))])
    drift = PoseSeries(
        gt.timestamps_s, gt.positions_xyz_m + np.outer(0.02 * along, [0.0, 1.0, 0.0]), gt.orientations_quat_wxyz
    )
    ev, _ = evaluate(drift, gt, rpe_delta_m=10.0)
    assert ev.rpe_translation_per_m["median"] == pytest.approx(0.02, rel=0.02)
    assert ev.rpe_rotation_deg_per_m["max"] < 1e-9


def test_associate_nearest_within_tolerance():
    gt = PoseSeries(np.arange(10.0), np.zeros((10, 3)), np.tile([1.0, 0, 0, 0], (10, 1)))
    est = PoseSeries(np.array([0.004, 2.6, 3.001, 9.5]), np.zeros((4, 3)), np.tile([1.0, 0, 0, 0], (4, 1)))
    i, j = associate(est, gt, max_dt_s=0.01)
    assert i.tolist() == [0, 2] and j.tolist() == [0, 3]


def test_tum_round_trip_and_errors(tmp_path):
    gt = _truth(step_s=1.0)
    path = write_tum(tmp_path / "gt.tum", gt)
    assert path.read_text().startswith("# timestamp tx ty tz qx qy qz qw")
    back = read_tum(path)
    np.testing.assert_allclose(back.positions_xyz_m, gt.positions_xyz_m, atol=1e-9)
    np.testing.assert_allclose(back.orientations_quat_wxyz, gt.orientations_quat_wxyz, atol=1e-9)
    bad = tmp_path / "bad.tum"
    bad.write_text("# header\n0 1 2 3 0 0 0 1\n1 1 2 three 0 0 0 1\n")
    with pytest.raises(ConfigError, match=r"bad.tum:3: expected 8 finite numbers"):
        read_tum(bad)
    with pytest.raises(ConfigError, match="missing.tum: cannot read"):
        read_tum(tmp_path / "missing.tum")


def test_report_writes_tum_json_and_png(tmp_path):
    gt = _truth(step_s=0.5)
    rng = np.random.default_rng(3)
    est = PoseSeries(
        gt.timestamps_s, gt.positions_xyz_m + rng.normal(0, 0.05, gt.positions_xyz_m.shape), gt.orientations_quat_wxyz
    )
    ev = write_report(tmp_path / "out", est, gt, title="test")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["title"] == "test" and summary["ate_se3_m"]["rmse"] == pytest.approx(ev.ate_se3_m["rmse"])
    assert 0.06 < summary["ate_se3_m"]["rmse"] < 0.11  # sqrt(3) * 0.05, less what alignment absorbs
    png = cv2.imread(str(tmp_path / "out" / "evaluation.png"))
    assert png is not None and png.shape[1] > 600
    assert len(read_tum(tmp_path / "out" / "estimate.tum")) == len(est)


def test_pose_series_rejects_bad_input():
    with pytest.raises(ValueError, match=r"expected \(N,\), \(N,3\), \(N,4\)"):
        PoseSeries(np.zeros(3), np.zeros((2, 3)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="must not decrease"):
        PoseSeries(np.array([1.0, 0.0]), np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)))


def test_the_evaluation_plot_draws_the_estimate_as_sent_and_its_error(tmp_path):
    """Before: only the SE(3)-aligned estimate was drawn, which hides a constant offset the vehicle flies
    with. Drawn now in tab:blue, path and error, beside the aligned one (tab:orange)."""
    gt = _truth(step_s=0.5)
    shifted = PoseSeries(gt.timestamps_s, gt.positions_xyz_m + [0.0, 5.0, 0.0], gt.orientations_quat_wxyz)
    ev, aligned = evaluate(shifted, gt)

    def blue_pixels(**kw) -> int:
        path = plot_evaluation(tmp_path / f"e{len(kw)}.png", aligned, gt, ev, **kw)
        bgr = cv2.imread(str(path)).astype(int)
        return int(np.count_nonzero(np.abs(bgr - [180, 119, 31]).sum(axis=2) < 40))

    assert blue_pixels() < 20 and blue_pixels(as_sent=shifted) > 300
