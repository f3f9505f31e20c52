"""Recording and replay: a recorded simulated flight replays bit for bit; flight-controller logs with a
video, and EuRoC folders, replay and are evaluated; bad input gives a clear message, a non-zero exit
and the partial report."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from mavvo.cli import main
from mavvo.errors import ConfigError
from mavvo.offline.driver import replay
from mavvo.offline.recording import load_recording
from mavvo.offline.time_offset import estimate_offset
from mavvo.service.recorder import Recorder, RecordOptions
from mavvo.service.settings import ServiceConfig
from mavvo.service.timing import Pairing
from mavvo.service.tlog import payload, read_tlog, write_record
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.scenarios.service_run import run_daemon_in_sim
from mavvo.sim.world.clock import LockstepClock
from mavvo.types import Frame

sys.path.insert(0, str(Path(__file__).parent))
from flightlogs import make_euroc, make_log_flight  # noqa: E402


def _replay_cli(capsys, *args: str) -> tuple[int, dict, str]:
    code = main(["--log-level", "warning", "replay", *map(str, args), "--json"])
    out = capsys.readouterr()
    lines = [line for line in out.out.splitlines() if line.startswith("{")]
    return code, (json.loads(lines[-1]) if lines else {}), out.err


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 6 s simulated flight flown by the daemon while recording."""
    rec_dir = tmp_path_factory.mktemp("recordings")
    run = run_daemon_in_sim(
        load_scenario("figure_eight"), ServiceConfig(record=RecordOptions(dir=str(rec_dir))), duration_s=8.0
    )
    return run


def test_round_trip_replays_the_recorded_flight_bit_for_bit(recorded, tmp_path, capsys):
    live = [payload(m.get_msgbuf()) for m in recorded.vision_messages]
    assert len(live) >= 60  # from the first estimate (once the flight controller's yaw is seen settled) on
    inp = load_recording(recorded.recording)
    assert inp.problems == [] and inp.expected_vpe == live  # the recording holds what the flight controller got
    res = replay(inp)
    assert res.messages_lost == 0 and res.frames_replayed == len(inp.frames)
    assert res.vpe_payloads == live  # every estimate, byte for byte
    # The command line, again: the same answer, the report and the evaluation against the recorded truth.
    code, summary, err = _replay_cli(capsys, recorded.recording, "--out", tmp_path / "out")
    assert code == 0, err
    assert summary["identical_to_recording"] is True and summary["estimates_received"] == len(live)
    assert summary["evaluation"]["ate_se3_m"]["rmse"] < 0.1
    # The odometry's own CPU per frame: one thread's time, so within the replay's wall time.
    cpu_s = summary["odometry_cpu_ms_per_frame"] * 1e-3 * summary["frames_replayed"]
    assert 0.0 < cpu_s <= summary["wall_s"]
    for name in ("estimate.tum", "quality.csv", "quality.png", "evaluation.png", "summary.json"):
        assert (tmp_path / "out" / name).is_file(), name
    quality = (tmp_path / "out" / "quality.csv").read_text().splitlines()
    assert len(quality) == 1 + summary["paired"] and quality[0].startswith("t_exposure_s,state,")


def test_inspect_tells_what_a_recording_holds(recorded, capsys):
    code = main(["--log-level", "warning", "inspect", str(recorded.recording), "--json"])
    r = json.loads(capsys.readouterr().out)
    series = {s["name"]: s for s in r["series"]}
    inp = load_recording(recorded.recording)
    assert code == 0 and r["kind"] == "recording" and r["replayable"]
    assert series["frames"]["count"] == len(inp.frames) and series["frames"]["rate_hz"] == pytest.approx(20.0, rel=0.05)
    assert (
        series["attitude"]["rate_hz"] == pytest.approx(inp.config.link.attitude_rate_hz, rel=0.1)
        and series["distance_sensor"]["count"] > 0
    )
    assert r["facts"]["recorded_estimates"] == len(inp.expected_vpe) and r["facts"]["frames_attitude_overlap_s"] > 5.0


def test_recording_holds_config_tlog_both_directions_and_exact_frames(recorded):
    rec = recorded.recording
    meta = json.loads((rec / "meta.json").read_text())
    assert (
        meta["complete"] is True and meta["counters"].get("dropped_frames", 0) == 0 and meta["counters"]["frames"] > 100
    )
    cfg = yaml.safe_load((rec / "config.yaml").read_text())
    assert cfg["camera"]["source"] == "sim:figure_eight" and cfg["record"]["dir"]
    comps = {f[6] for _, f in read_tlog(rec / "mavlink-000.tlog")}
    assert 197 in comps and 1 in comps  # mavvo's messages and the flight controller's
    ids = {f[7] for _, f in read_tlog(rec / "mavlink-000.tlog")}
    assert 111 in ids and 30 in ids and 102 in ids  # TIMESYNC, ATTITUDE, VISION_POSITION_ESTIMATE


def test_recorder_never_blocks_counts_drops_and_stops_at_its_budget(tmp_path):
    clock = LockstepClock()
    opts = RecordOptions(dir=str(tmp_path), max_total_mb=0.03, queue_frames=2, rotate_mb=0.02)
    rec = Recorder(opts, "camera: {}\n", clock)
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (120, 160), dtype=np.uint8)  # noise: ~19 kB per PNG
    for k in range(40):  # a burst: the queue holds two, the rest are dropped at once
        rec.frame(Frame(img, k * 0.05, k), Pairing("paired", k, 0.0, 0.0, 0.0), k * 0.05)
        rec.mavlink(k * 1000, bytes([0xFD, 1, 0, 0, k, 1, 1, 30, 0, 0, 7, 0, 0]))
    deadline = time.monotonic() + 10
    while rec.counters["frames"] < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    for k in range(40, 44):  # over the budget now: the writer stops the recording
        rec.frame(Frame(img, k * 0.05, k), Pairing("paired", k, 0.0, 0.0, 0.0), k * 0.05)
        time.sleep(0.05)
    rec.close()
    c = rec.counters
    assert c["frames"] == 2 and c["frames"] + c["dropped_frames"] == 44
    assert rec.stopped_reason.startswith("the recording reached record.max_total_mb")
    assert c["segments"] >= 2  # rotated before the budget stopped it
    meta = json.loads((rec.path / "meta.json").read_text())
    assert meta["complete"] is False and "max_total_mb" in meta["stopped_reason"]
    # Reading it back says so (the replay's exit is then non-zero).
    inp_problems = load_recording(rec.path).problems
    assert any("not closed cleanly" in p for p in inp_problems) and any("dropped" in p for p in inp_problems)


def test_tlog_reader_keeps_the_records_before_a_cut(tmp_path):
    p = tmp_path / "x.tlog"
    frame = bytes([0xFD, 2, 0, 0, 0, 1, 1, 30, 0, 0, 5, 6, 0, 0])
    with p.open("wb") as f:
        for k in range(3):
            write_record(f, 1000 * k, frame)
    data = p.read_bytes()
    p.write_bytes(data[:-5])
    got = []
    with pytest.raises(ConfigError, match=r"x.tlog: truncated"):
        for rec in read_tlog(p):
            got.append(rec)
    assert got == [(0, frame), (1000, frame)]
    p.write_bytes(b"\x00" * 8 + b"\x55" * 20)
    with pytest.raises(ConfigError, match="not a .tlog"):
        list(read_tlog(p))


def test_offset_estimation_finds_a_known_lag_and_refuses_a_flat_signal():
    rng = np.random.default_rng(1)
    t_fc = np.arange(0.0, 60.0, 0.01)
    w_fc = np.convolve(rng.standard_normal(len(t_fc)), np.ones(40) / 40, mode="same")
    t_cam = np.arange(0.0, 20.0, 0.05)
    w_cam = np.interp(t_cam + 23.37, t_fc, w_fc) + 0.01 * rng.standard_normal(len(t_cam))
    est = estimate_offset(t_cam, w_cam, t_fc, w_fc)
    assert abs(est.offset_s - 23.37) < 0.02 and est.correlation > 0.9
    with pytest.raises(ConfigError, match="cannot estimate the time offset"):
        estimate_offset(t_cam, np.full(len(t_cam), 0.1), t_fc, w_fc)


def test_tlog_with_image_folder_offset_estimated_compared_with_local_position(tmp_path, capsys):
    lf = make_log_flight(tmp_path, kind="tlog", video="folder", with_local_position=True)
    code, s, err = _replay_cli(capsys, lf.log, "--video", lf.video, "--config", lf.config, "--out", tmp_path / "out")
    assert code == 0, err
    off = s["notes"]["time_offset"]
    assert off["estimated"] and abs(off["offset_s"] - lf.true_offset_s) < 0.03 and off["correlation"] > 0.9
    assert s["reference"] == "flight controller's local position"
    assert s["evaluation"]["ate_se3_m"]["rmse"] < 0.1 and s["estimates_received"] > 200


def test_dataflash_with_video_given_offset_against_ground_truth(tmp_path, capsys):
    lf = make_log_flight(tmp_path, kind="bin", video="avi")
    code, s, err = _replay_cli(
        capsys,
        lf.log,
        "--video",
        lf.video,
        "--config",
        lf.config,
        "--offset-s",
        lf.true_offset_s,
        "--ground-truth",
        lf.truth,
        "--out",
        tmp_path / "out",
    )
    assert code == 0, err
    assert s["kind"] == "dataflash" and s["notes"]["time_offset"] == {"estimated": False, "offset_s": lf.true_offset_s}
    assert s["evaluation"]["ate_se3_m"]["rmse"] < 0.15


def test_px4_ulog_with_video_against_ground_truth(tmp_path, capsys):
    """A PX4 flight: vehicle_attitude, distance_sensor, barometer, written by pyulog; offset estimated."""
    lf = make_log_flight(tmp_path, kind="ulg", video="folder", duration_s=10.0)
    code, s, err = _replay_cli(
        capsys,
        lf.log,
        "--video",
        lf.video,
        "--config",
        lf.config,
        "--ground-truth",
        lf.truth,
        "--out",
        tmp_path / "out",
    )
    assert code == 0, err
    assert s["kind"] == "ulog" and abs(s["notes"]["time_offset"]["offset_s"] - lf.true_offset_s) < 0.03
    assert s["paired"] == s["frames"] and s["evaluation"]["ate_se3_m"]["rmse"] < 0.15


def test_telemetry_log_with_2_hz_attitude_pairs_every_frame_and_reports_it_degraded(tmp_path, capsys):
    """Before: a ground station's 2 Hz ATTITUDE left every frame attitude-stale with the 50 ms limit."""
    lf = make_log_flight(tmp_path, kind="tlog", video="folder", duration_s=10.0, attitude_rate_hz=2.0)
    code, s, err = _replay_cli(
        capsys,
        lf.log,
        "--video",
        lf.video,
        "--config",
        lf.config,
        "--offset-s",
        lf.true_offset_s,
        "--ground-truth",
        lf.truth,
        "--out",
        tmp_path / "out",
    )
    assert code == 0, err
    assert s["notes"]["attitude_pairing"]["rate_hz"] == pytest.approx(2.0) and s["notes"]["attitude_pairing"][
        "max_gap_s"
    ] == pytest.approx(0.75)
    c = s["counters"]
    assert s["paired"] == s["frames"] and not any(k.startswith("skipped_attitude") for k in c), c
    ap = s["attitude_pairing"]
    assert ap["gap_s_median"] == pytest.approx(0.5, abs=1e-3) and ap["degraded"] >= s["estimates_received"] // 2
    assert 0.3 < ap["sigma_deg_p95"] < 2.0  # 1 rad/s^2 over a 0.5 s gap: up to 1.8 deg in the middle
    quality = (tmp_path / "out" / "quality.csv").read_text().splitlines()
    assert "attitude_interpolated" in "".join(quality) and "attitude_sigma_deg" in quality[0]
    # Degraded, not lost: the figure eight is still followed (the truth's own roll/pitch, sampled at 2 Hz).
    assert (
        s["evaluation"]["ate_se3_m"]["rmse"] < 0.3
    )  # 0.10 m when written; 0.35 m with degraded keyframes placed at the filter's estimate (docs/odometry.md)


def test_bad_logs_say_what_is_wrong(tmp_path, capsys):
    lf = make_log_flight(tmp_path, kind="tlog", video="folder", duration_s=8.0, with_attitude=False)
    code, _, err = _replay_cli(capsys, lf.log, "--video", lf.video, "--config", lf.config)
    assert code == 2 and "flight.tlog: no ATTITUDE messages" in err
    code, _, err = _replay_cli(capsys, tmp_path / "nothing.tlog", "--video", lf.video, "--config", lf.config)
    assert code == 2 and "nothing.tlog: no such" in err
    code, _, err = _replay_cli(capsys, lf.log, "--config", lf.config)
    assert code == 2 and "--video" in err


def test_truncated_log_and_missing_frames_exit_non_zero_with_the_partial_report(tmp_path, capsys):
    lf = make_log_flight(tmp_path, kind="tlog", video="folder", duration_s=10.0)
    data = lf.log.read_bytes()
    lf.log.write_bytes(data[: len(data) * 3 // 4 + 5])  # cut inside a record
    (lf.video / "00150.png").unlink()
    out = tmp_path / "out"
    code, s, err = _replay_cli(
        capsys, lf.log, "--video", lf.video, "--config", lf.config, "--offset-s", lf.true_offset_s, "--out", out
    )
    assert code == 1
    assert "flight.tlog: truncated" in err and "00150.png is missing" in err
    assert s["estimates_received"] > 50 and (out / "estimate.tum").is_file()  # what was processed is written
    assert len(s["problems"]) == 2


def test_offset_that_cannot_be_estimated_is_refused(tmp_path, capsys):
    lf = make_log_flight(tmp_path, kind="tlog", video="folder", scenario="hover", duration_s=8.0)
    code, _, err = _replay_cli(capsys, lf.log, "--video", lf.video, "--config", lf.config)
    assert code == 2 and "cannot estimate the time offset" in err and "--offset-s" in err


def test_euroc_folder_replays_with_truth_or_imu_attitude(tmp_path, capsys):
    root = make_euroc(tmp_path)
    over = tmp_path / "over.yaml"  # a constant-height flight: scale from the known height above flat ground
    over.write_text(yaml.safe_dump({"odometry": {"scale": {"source": "fixed", "fixed_height_m": 8.0}}}))
    code, s, err = _replay_cli(capsys, root, "--attitude", "truth", "--config", over, "--out", tmp_path / "a")
    assert code == 0, err
    assert s["kind"] == "euroc" and s["reference"] == "ground truth" and s["estimates_received"] > 150
    assert s["evaluation"]["ate_se3_m"]["rmse"] < 0.1
    code, s, err = _replay_cli(capsys, root, "--config", over, "--out", tmp_path / "b")
    assert code == 0, err
    tilt = s["notes"]["attitude_tilt_error_deg"]  # the IMU filter's roll/pitch against the ground truth, reported
    # 12 s of a fast figure eight that starts in the air: too short for the IMU's fit to tell the flight's
    # own velocity swings from gravity (docs/replay.md); 4.5 / 6.7 deg when written, 9.8 deg median before it.
    assert 0.0 < tilt["median"] <= tilt["p95"] < 10.0
    assert s["evaluation"]["ate_se3_m"]["rmse"] < 0.5  # the filter's tilt errors in turns cost some accuracy
    from mavvo.offline.sources import open_replay_source

    inp = open_replay_source(root)  # the camera's axes found (body z: the first second's mean thrust axis,
    # within the vibration's 0.3 m/s^2 averaged over 200 samples, and the flight's own accelerations)
    assert np.allclose(
        inp.config.mounting.rotation(), np.array(load_scenario("figure_eight").camera.R_body_cam()), atol=0.01
    )


def test_euroc_folder_without_ground_truth_warns_and_takes_its_height_from_the_configuration(tmp_path, capsys):
    """Before: it ran silently with no reference and no scale source: every estimate (0, 0, 0)."""
    root = make_euroc(tmp_path, duration_s=5.0)
    truth = tmp_path / "gt.csv"
    (root / "mav0" / "state_groundtruth_estimate0" / "data.csv").rename(truth)
    code, s, err = _replay_cli(capsys, root, "--out", tmp_path / "a")
    assert code == 0, err
    assert (
        "warning:" in err and "state_groundtruth_estimate0/data.csv: missing" in err and "fixed height of 10 m" in err
    )
    assert s["warnings"] and s["reference"] is None and s["estimates_received"] > 50
    est = np.loadtxt(tmp_path / "a" / "estimate.tum")
    assert np.ptp(est[:, 1:3], axis=0).max() > 1.0  # it moves: a scale, not zeros
    over = tmp_path / "over.yaml"  # the flight's real height, 8 m, and the truth from elsewhere
    over.write_text(yaml.safe_dump({"odometry": {"scale": {"source": "fixed", "fixed_height_m": 8.0}}}))
    code, s, err = _replay_cli(
        capsys, root, "--config", over, "--ground-truth", truth, "--attitude", "imu", "--out", tmp_path / "b"
    )
    assert code == 0 and "fixed height of 8 m" in err
    assert s["evaluation"]["ate_se3_m"]["rmse"] < 0.5 and abs(s["evaluation"]["sim3_scale"] - 1.0) < 0.05


def test_not_a_source_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code, _, err = _replay_cli(capsys, tmp_path / "empty")
    assert code == 2 and "expected a mavvo recording" in err


def test_a_slow_disk_holds_a_lockstep_recording_back_instead_of_losing_frames(tmp_path, monkeypatch):
    """Before: `mavvo sim --record` at load 6 on 2 cores lost 12 of 949 frames (the recorder's queue of 16
    full, the simulation not waiting) and said nothing; the replay then read 'estimates DIFFERENT'. Here a
    queue of one frame and a disk that takes 20 ms a frame: every frame is recorded, and the replay agrees."""
    real = Recorder._write_frame

    def slow(self, *args):
        time.sleep(0.02)
        return real(self, *args)

    monkeypatch.setattr(Recorder, "_write_frame", slow)
    rec_dir = tmp_path / "recordings"
    run = run_daemon_in_sim(
        load_scenario("hover"),
        ServiceConfig(record=RecordOptions(dir=str(rec_dir), queue_frames=1, queue_messages=4)),
        duration_s=3.0,
    )
    meta = json.loads((run.recording / "meta.json").read_text())
    assert meta["counters"].get("dropped_frames", 0) == 0 and meta["counters"].get("dropped_messages", 0) == 0
    assert meta["counters"]["frames"] == run.daemon.counters["frames"]
    inp = load_recording(run.recording)
    assert inp.problems == [] and len(inp.frames) == run.daemon.counters["frames"]


def test_euroc_replay_starts_at_the_first_frame_and_ends_at_the_last(tmp_path, capsys):
    """Before: the first second of frames went to waiting for a settled yaw (there is no EKF to settle),
    and the replay played the IMU for as long as it ran after the camera stopped, logging health lines
    and ending 'failed (no_frames)'. Here the IMU runs 30 s past the last frame."""
    root = make_euroc(tmp_path, duration_s=5.0)
    imu = root / "mav0" / "imu0" / "data.csv"
    lines = imu.read_text().splitlines()
    last_ns, rest = int(lines[-1].split(",")[0]), lines[-1].split(",", 1)[1]
    imu.write_text("\n".join(lines + [f"{last_ns + k * 5_000_000},{rest}" for k in range(1, 6001)]) + "\n")
    over = tmp_path / "over.yaml"
    over.write_text(yaml.safe_dump({"odometry": {"scale": {"source": "fixed", "fixed_height_m": 8.0}}}))
    code, s, err = _replay_cli(capsys, root, "--config", over, "--out", tmp_path / "a")  # attitude from the IMU
    assert code == 0, err
    assert s["counters"].get("waiting_for_heading", 0) == 0  # no frame waits for a yaw to settle
    # The IMU's 30 s tail is read but not played: before, all of it, and the run ended 'failed'.
    assert s["final_state"] == "tracking" and s["counters"]["link_rx"] < s["messages"] / 2, s["counters"]
    assert "height" in s["notes"] and "no rangefinder" in s["notes"]["height"]


def test_an_image_folder_stamped_on_the_flight_controllers_clock_replays_with_offset_0(tmp_path, capsys):
    """Before: timestamps.txt was read relative to its first line, so frames already stamped with the
    flight controller's boot time still needed --offset-s (their first time) to replay."""
    lf = make_log_flight(tmp_path, kind="tlog", video="folder", duration_s=8.0)
    index = lf.video / "timestamps.txt"
    rows = [line.split() for line in index.read_text().splitlines()]
    index.write_text("".join(f"{float(t) + lf.true_offset_s!r} {name}\n" for t, name in rows))  # the log's clock
    code, s, err = _replay_cli(
        capsys,
        lf.log,
        "--video",
        lf.video,
        "--config",
        lf.config,
        "--offset-s",
        0,
        "--ground-truth",
        lf.truth,
        "--out",
        tmp_path / "out",
    )
    assert code == 0, err
    assert s["estimates_received"] > 100 and s["evaluation"]["ate_se3_m"]["rmse"] < 0.15


def test_euroc_with_the_truths_attitude_needs_no_imu_folder(tmp_path, capsys):
    """Before: imu0/ was required even with --attitude truth (it only told which way is up)."""
    import shutil

    root = make_euroc(tmp_path, duration_s=4.0)
    shutil.rmtree(root / "mav0" / "imu0")
    over = tmp_path / "over.yaml"
    over.write_text(yaml.safe_dump({"odometry": {"scale": {"source": "fixed", "fixed_height_m": 8.0}}}))
    code, s, err = _replay_cli(capsys, root, "--attitude", "truth", "--config", over, "--out", tmp_path / "a")
    assert code == 0, err
    assert s["estimates_received"] > 40 and s["evaluation"]["ate_se3_m"]["rmse"] < 0.1
    code, _, err = _replay_cli(capsys, root, "--config", over, "--out", tmp_path / "b")  # the IMU's attitude
    assert code == 2 and "imu0/data.csv" in err
