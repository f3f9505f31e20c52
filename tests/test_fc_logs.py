"""Flight-controller logs of every age: dataflash with TimeUS, with TimeMS (older firmware), with AHR2
or NKF1 instead of ATT, the text format, and a damaged file whose parser noise stays off the terminal.
The binary logs are written in pymavlink's own format description; the text log as ArduPilot's
LogAnalyzer examples are."""

from __future__ import annotations

import numpy as np
import pytest
from log_writers import write_dataflash, write_ulog

from mavvo.errors import ConfigError
from mavvo.offline.fc_logs import read_fc_log

ROLL_DEG = [1.0, 2.0, 3.0, 4.0]


def test_current_firmware_time_us_and_att(tmp_path):
    log = write_dataflash(
        tmp_path / "a.bin",
        {"ATT": (60, "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")},
        [("ATT", (1_000_000 + 20_000 * k, 0.0, r, 0.0, -r, 0.0, 90.0)) for k, r in enumerate(ROLL_DEG)],
    )
    s = read_fc_log(log)
    assert np.allclose(s.attitude[:, 0], [1.0, 1.02, 1.04, 1.06]) and np.allclose(
        np.degrees(s.attitude[:, 1]), ROLL_DEG
    )
    assert s.problems == []


def test_older_firmware_time_ms(tmp_path):
    """Before: AttributeError: TimeUS, exit 1."""
    log = write_dataflash(
        tmp_path / "old.bin",
        {"ATT": (60, "Iccccc", "TimeMS,RollIn,Roll,PitchIn,Pitch,Yaw")},
        [("ATT", (5_000 + 20 * k, 0.0, r, 0.0, -r, 90.0)) for k, r in enumerate(ROLL_DEG)],
    )
    s = read_fc_log(log)
    assert np.allclose(s.attitude[:, 0], [5.0, 5.02, 5.04, 5.06]) and np.allclose(
        np.degrees(s.attitude[:, 1]), ROLL_DEG, atol=0.01
    )


def test_ahr2_when_there_is_no_att(tmp_path):
    log = write_dataflash(
        tmp_path / "ahr2.bin",
        {"AHR2": (61, "Qccf", "TimeUS,Roll,Pitch,Yaw")},
        [("AHR2", (2_000_000 + 100_000 * k, r, 0.5, 45.0)) for k, r in enumerate(ROLL_DEG)],
    )
    s = read_fc_log(log)
    assert np.allclose(np.degrees(s.attitude[:, 1]), ROLL_DEG, atol=0.01)
    assert any("roll/pitch from AHR2" in p for p in s.problems)


def test_text_dataflash_log(tmp_path):
    """Before: parsed as binary, 179 000 'bad header' lines on stderr, then 'no ATT messages'."""
    lines = [
        "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns",
        "FMT, 60, 31, ATT, Qffffff, TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw",
    ]
    lines += [f"ATT, {1_000_000 + 20_000 * k}, 0.0, {r}, 0.0, {-r}, 0.0, 90.0" for k, r in enumerate(ROLL_DEG)]
    log = tmp_path / "flight.log"
    log.write_text("\n".join(lines) + "\n")
    s = read_fc_log(log)
    assert np.allclose(np.degrees(s.attitude[:, 1]), ROLL_DEG) and np.allclose(
        s.attitude[:, 0], [1.0, 1.02, 1.04, 1.06]
    )


def test_a_damaged_log_keeps_its_noise_off_the_terminal(tmp_path, capfd):
    """Before: 68 316 'bad header' lines on stderr, then the one-line error."""
    good = write_dataflash(
        tmp_path / "g.bin",
        {"ATT": (60, "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")},
        [("ATT", (1_000_000 + 20_000 * k, 0.0, 1.0, 0.0, 1.0, 0.0, 90.0)) for k in range(200)],
    ).read_bytes()
    rng = np.random.default_rng(3)
    damaged = bytearray(good)
    for i in rng.integers(200, len(good), 40):  # 40 bytes flipped inside the records
        damaged[i] ^= 0xFF
    (tmp_path / "d.bin").write_bytes(bytes(damaged) + bytes(rng.integers(0, 256, 3000, dtype=np.uint8)))
    s = read_fc_log(tmp_path / "d.bin")
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    assert len(s.attitude) > 100 and any("skipped" in p and "damaged places" in p for p in s.problems), s.problems
    (tmp_path / "junk.bin").write_bytes(bytes(rng.integers(0, 256, 20000, dtype=np.uint8)))
    with pytest.raises(ConfigError, match="junk.bin: no ATT, AHR2 or NKF1 messages"):
        read_fc_log(tmp_path / "junk.bin")
    assert capfd.readouterr() == ("", "")


def _px4_topics(n: int = 50) -> dict:
    """A PX4 flight's topics: attitude at 50 Hz rolling 0.5 deg per sample, a downward and a forward
    range sensor, local position with its height, barometer."""
    t_us = 10_000_000 + 20_000 * np.arange(n)
    roll = np.radians(0.5 * np.arange(n))
    pitch, yaw = np.radians(-3.0), np.radians(120.0)
    # q (w, x, y, z) of Euler 3-2-1 (roll, pitch, yaw), written out so the reader's conversion is checked independently
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll / 2),
        np.sin(roll / 2),
        np.cos(pitch / 2),
        np.sin(pitch / 2),
        np.cos(yaw / 2),
        np.sin(yaw / 2),
    )
    q = np.column_stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )
    ds_t = np.repeat(t_us[::5], 2)
    m = len(t_us[::10])
    return {
        "vehicle_attitude": ([("uint64_t", "timestamp"), ("float[4]", "q")], {"timestamp": t_us, "q": q}),
        "distance_sensor": (
            [
                ("uint64_t", "timestamp"),
                ("float", "min_distance"),
                ("float", "max_distance"),
                ("float", "current_distance"),
                ("int8_t", "signal_quality"),
                ("uint8_t", "orientation"),
            ],
            {
                "timestamp": ds_t,
                "min_distance": np.full(len(ds_t), 0.1),
                "max_distance": np.full(len(ds_t), 8.0),
                "current_distance": np.tile([3.0, 7.0], len(ds_t) // 2),
                "signal_quality": np.tile([100, 100], len(ds_t) // 2),
                "orientation": np.tile([25, 0], len(ds_t) // 2),
            },
        ),
        "vehicle_local_position": (
            [
                ("uint64_t", "timestamp"),
                ("float", "x"),
                ("float", "y"),
                ("float", "z"),
                ("bool", "xy_valid"),
                ("bool", "z_valid"),
            ],
            {
                "timestamp": t_us[::10],
                "x": np.arange(float(m)),
                "y": np.zeros(m),
                "z": np.full(m, -2.5),
                "xy_valid": np.ones(m),
                "z_valid": np.ones(m),
            },
        ),
        "vehicle_air_data": (
            [("uint64_t", "timestamp"), ("float", "baro_alt_meter")],
            {"timestamp": t_us[::10], "baro_alt_meter": np.full(m, 480.0)},
        ),
    }


def test_px4_ulog_attitude_range_and_local_height(tmp_path):
    """Before: refused ('expected a .tlog or a dataflash .bin'). Written by pyulog, read by pyulog."""
    s = read_fc_log(write_ulog(tmp_path / "px4.ulg", _px4_topics()))
    assert s.kind == "ulog" and s.problems == []
    assert np.allclose(s.attitude[:, 0], 10.0 + 0.02 * np.arange(50))
    assert np.allclose(np.degrees(s.attitude[:, 1]), 0.5 * np.arange(50), atol=1e-4)
    assert np.allclose(np.degrees(s.attitude[:, 2]), -3.0, atol=1e-4) and np.allclose(
        np.degrees(s.attitude[:, 3]), 120.0, atol=1e-4
    )
    assert np.allclose(s.range_m[:, 1], 3.0)  # the downward sensor only, not the forward one at 7 m
    assert np.allclose(s.height_m[:, 1], 2.5) and s.sources["height"] == "vehicle_local_position.z"
    assert np.allclose(s.local_ned_m[:, 1], np.arange(5.0))


def test_px4_ulog_without_local_position_takes_the_barometer_above_the_start(tmp_path):
    topics = _px4_topics()
    del topics["vehicle_local_position"]
    topics["vehicle_air_data"][1]["baro_alt_meter"] = 480.0 + np.arange(5.0)
    s = read_fc_log(write_ulog(tmp_path / "baro.ulg", topics))
    assert np.allclose(s.height_m[:, 1], np.arange(5.0)) and s.sources["height"] == "vehicle_air_data.baro_alt_meter"


def test_px4_ulog_that_is_not_one_or_has_no_attitude_is_one_line(tmp_path, capfd):
    (tmp_path / "junk.ulg").write_bytes(bytes(np.random.default_rng(5).integers(0, 256, 5000, dtype=np.uint8)))
    with pytest.raises(ConfigError, match=r"junk.ulg: not a readable PX4 ULog"):
        read_fc_log(tmp_path / "junk.ulg")
    topics = _px4_topics()
    del topics["vehicle_attitude"]
    with pytest.raises(ConfigError, match=r"noatt.ulg: no vehicle_attitude messages"):
        read_fc_log(write_ulog(tmp_path / "noatt.ulg", topics))
    assert capfd.readouterr() == ("", "")


def test_a_damaged_ulog_keeps_what_it_can_and_says_so(tmp_path, capfd):
    good = write_ulog(tmp_path / "g.ulg", _px4_topics(400)).read_bytes()
    damaged = bytearray(good)
    rng = np.random.default_rng(11)
    for i in rng.integers(len(good) // 2, len(good), 30):
        damaged[i] ^= 0xFF
    (tmp_path / "d.ulg").write_bytes(bytes(damaged))
    s = read_fc_log(tmp_path / "d.ulg")
    assert capfd.readouterr() == ("", "")
    assert len(s.attitude) > 150 and any("damaged" in p for p in s.problems), s.problems


def test_attitude_records_without_a_time_take_the_logs_other_clock(tmp_path):
    """ArduCopter 3.1's text logs: ATT has no time column, IMU has TimeMS. Before: the ATT records were all
    stamped 0, collapsed into one, and the log was refused as having no attitude ("found 1")."""
    lines = [
        "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns",
        "FMT, 9, 23, ATT, ccCcc, RollIn,Roll,PitchIn,Pitch,Yaw",
        "FMT, 1, 23, IMU, Iffffff, TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ",
    ]
    for k, r in enumerate(ROLL_DEG):
        lines += [f"IMU, {1000 + 20 * k}, 0, 0, 0, 0, 0, -9.8", f"ATT, 0, {r}, 0, 0.5, 90"]
    log = tmp_path / "ac31.log"
    log.write_text("\n".join(lines) + "\n")
    s = read_fc_log(log)
    assert np.allclose(s.attitude[:, 0], [1.0, 1.02, 1.04, 1.06]) and np.allclose(
        np.degrees(s.attitude[:, 1]), ROLL_DEG
    )
    assert any("carry no time of their own" in p and "(IMU)" in p for p in s.problems)
    (tmp_path / "none.log").write_text("\n".join([*lines[:2], *(f"ATT, 0, {r}, 0, 0.5, 90" for r in ROLL_DEG)]) + "\n")
    with pytest.raises(ConfigError, match="none.log: the ATT records carry no time .* cannot be placed in time"):
        read_fc_log(tmp_path / "none.log")


def test_a_log_the_reader_cannot_parse_is_refused_without_pythons_words(tmp_path):
    """A text log whose GPS line has an empty time field makes pymavlink's reader raise at the start.
    Before: "not a readable dataflash log (text): invalid literal for int() with base 10: ''"."""
    log = tmp_path / "old.log"
    log.write_text(
        "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns\n"
        "FMT, 1, 23, IMU, Iffffff, TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ\n"
        "FMT, 2, 23, GPS, BIHBcLLeeEe, Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs\n"
        "IMU, 1000, 0, 0, 0, 0, 0, -9.8\n"
        "GPS, 3, , 1800, 8, 1.2, -35.3, 149.1, 10, 600, 0, 0\n"
    )
    with pytest.raises(ConfigError) as e:
        read_fc_log(log)
    text = str(e.value)
    assert text.startswith(f"{log}: not a readable dataflash log (text): pymavlink's reader could not make sense")
    assert "invalid literal" not in text and "int()" not in text
