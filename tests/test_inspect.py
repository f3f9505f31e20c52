"""``mavvo inspect``: what replay would read from each kind of source, and what it lacks, on logs,
videos and data sets the tests write with the formats' own libraries."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from mavvo.cli import main

sys.path.insert(0, str(Path(__file__).parent))
from flightlogs import BOOT_S, make_euroc, make_log_flight  # noqa: E402


def _inspect(capsys, *args) -> tuple[int, dict, str]:
    code = main(["--log-level", "warning", "inspect", *map(str, args), "--json"])
    out = capsys.readouterr()
    return code, (json.loads(out.out) if out.out.strip() else {}), out.err


def _series(report: dict) -> dict:
    return {s["name"]: s for s in report["series"]}


def test_a_telemetry_log_with_slow_attitude_and_its_video(tmp_path, capsys):
    lf = make_log_flight(tmp_path, kind="tlog", video="folder", duration_s=6.0, attitude_rate_hz=2.0)
    code, r, err = _inspect(capsys, lf.log, "--video", lf.video, "--offset-s", lf.true_offset_s, "--config", lf.config)
    assert code == 0, err
    s = _series(r)
    assert r["kind"] == "tlog" and r["replayable"]
    assert (
        s["attitude"]["source"] == "ATTITUDE"
        and s["attitude"]["rate_hz"] == pytest.approx(2.0)
        and s["attitude"]["longest_gap_s"] == pytest.approx(0.5)
    )
    assert s["range"]["rate_hz"] == pytest.approx(20.0) and s["height"]["source"] == "GLOBAL_POSITION_INT.relative_alt"
    assert s["frames"]["count"] == len((lf.video / "timestamps.txt").read_text().splitlines())
    assert s["attitude"]["start_s"] == pytest.approx(BOOT_S)
    assert (
        r["facts"]["attitude_pairing_max_gap_s"] == pytest.approx(0.75)
        and "slow stream" in r["facts"]["attitude_pairing"]
    )
    # frames from 1.5 s to 5.65 s of the flight; attitude to 5.5 s
    assert r["facts"]["frames_attitude_overlap_s"] == pytest.approx(4.0, abs=0.01)
    assert [m["fix"].split()[0] for m in r["missing"]] == ["--ground-truth"] and not r["missing"][0]["blocking"]


def test_a_log_alone_names_the_video_and_config_it_needs(tmp_path, capsys):
    lf = make_log_flight(tmp_path, kind="bin", video="folder", duration_s=4.0)
    code, r, _ = _inspect(capsys, lf.log)
    assert code == 1 and not r["replayable"] and r["kind"] == "dataflash"
    assert {m["fix"].split()[0] for m in r["missing"] if m["blocking"]} == {"--video", "--config"}
    assert _series(r)["attitude"]["source"] == "ATT" and _series(r)["attitude"]["rate_hz"] == pytest.approx(
        50.0, rel=0.01
    )
    code = main(["inspect", str(lf.log)])  # the table for people
    out = capsys.readouterr().out
    assert code == 1 and "MISSING: the flight's video; --video FILE_OR_FOLDER" in out and "ATT " in out


def test_a_px4_log_names_its_topics(tmp_path, capsys):
    lf = make_log_flight(tmp_path, kind="ulg", video="folder", duration_s=4.0)
    code, r, _ = _inspect(capsys, lf.log, "--video", lf.video, "--config", lf.config)
    s = _series(r)
    assert code == 0 and r["kind"] == "ulog"
    assert s["attitude"]["source"] == "vehicle_attitude" and s["range"]["source"] == "distance_sensor"
    assert s["height"]["source"] == "vehicle_air_data.baro_alt_meter" and s["height"]["rate_hz"] == pytest.approx(
        10.0, rel=0.01
    )
    assert r["facts"]["time_offset_s"].startswith("estimated by replay")


def test_a_dataset_without_ground_truth_is_replayable_with_what_it_lacks(tmp_path, capsys):
    root = make_euroc(tmp_path, duration_s=4.0)
    code, r, _ = _inspect(capsys, root)
    s = _series(r)
    assert (
        code == 0
        and r["kind"] == "euroc"
        and s["imu"]["rate_hz"] == pytest.approx(200.0, rel=0.01)
        and s["ground_truth"]["count"] > 0
    )
    assert r["missing"] == [] and r["facts"]["frames_imu_overlap_s"] > 3.0
    (root / "mav0" / "state_groundtruth_estimate0" / "data.csv").unlink()
    code, r, _ = _inspect(capsys, root)
    assert code == 0 and _series(r)["ground_truth"]["count"] == 0
    assert len(r["missing"]) == 1 and "fixed_height_m" in r["missing"][0]["fix"] and not r["missing"][0]["blocking"]


def test_what_is_not_a_source_is_one_line_exit_2(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("hello\n")
    code, _, err = _inspect(capsys, tmp_path / "notes.txt")
    assert code == 2 and err.count("\n") == 1 and "notes.txt: not a source mavvo can replay" in err
    (tmp_path / "bad.ulg").write_bytes(b"\x00" * 100)
    code, _, err = _inspect(capsys, tmp_path / "bad.ulg")
    assert code == 2 and "bad.ulg: not a readable PX4 ULog" in err


def test_columns_widen_for_long_names_and_stay_aligned():
    """Before: fixed widths (16 and 36 characters); a long source pushed its row's numbers out of line."""
    import numpy as np

    from mavvo.commands.inspect import series_table
    from mavvo.offline.inspect import series_info

    t = np.arange(0.0, 2.0, 0.02)
    rows = series_table(
        [
            series_info("attitude", "ATT", t),
            series_info("range", "distance_sensor.current_distance (orientation 25, downward facing)", t[::5]),
        ]
    )
    assert rows[0].startswith("series ") and rows[2].startswith("range ")
    ends = {len(r) for r in rows}  # the last column right-aligned: every row ends at the same column
    assert len(ends) == 1, rows
    count_end = rows[0].index("count") + len("count")
    assert rows[1][:count_end].endswith(" 100") and rows[2][:count_end].endswith(" 20"), rows
