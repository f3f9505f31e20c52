"""Flight-controller logs of every age: dataflash with TimeUS, with TimeMS (older firmware), with AHR2
or NKF1 instead of ATT, the text format, and a damaged file whose parser noise stays off the terminal.
The binary logs are written in pymavlink's own format description; the text log as ArduPilot's
LogAnalyzer examples are."""

from __future__ import annotations

import numpy as np
import pytest

from mavvo.errors import ConfigError
from sim.replay.fc_logs import read_fc_log, write_dataflash

ROLL_DEG = [1.0, 2.0, 3.0, 4.0]


def test_current_firmware_time_us_and_att(tmp_path):
    log = write_dataflash(tmp_path / "a.bin", {"ATT": (60, "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")},
                          [("ATT", (1_000_000 + 20_000 * k, 0.0, r, 0.0, -r, 0.0, 90.0)) for k, r in enumerate(ROLL_DEG)])
    s = read_fc_log(log)
    assert np.allclose(s.attitude[:, 0], [1.0, 1.02, 1.04, 1.06]) and np.allclose(np.degrees(s.attitude[:, 1]), ROLL_DEG)
    assert s.problems == []


def test_older_firmware_time_ms(tmp_path):
    """Before: AttributeError: TimeUS, exit 1."""
    log = write_dataflash(tmp_path / "old.bin", {"ATT": (60, "Iccccc", "TimeMS,RollIn,Roll,PitchIn,Pitch,Yaw")},
                          [("ATT", (5_000 + 20 * k, 0.0, r, 0.0, -r, 90.0)) for k, r in enumerate(ROLL_DEG)])
    s = read_fc_log(log)
    assert np.allclose(s.attitude[:, 0], [5.0, 5.02, 5.04, 5.06]) and np.allclose(np.degrees(s.attitude[:, 1]), ROLL_DEG, atol=0.01)


def test_ahr2_when_there_is_no_att(tmp_path):
    log = write_dataflash(tmp_path / "ahr2.bin", {"AHR2": (61, "Qccf", "TimeUS,Roll,Pitch,Yaw")},
                          [("AHR2", (2_000_000 + 100_000 * k, r, 0.5, 45.0)) for k, r in enumerate(ROLL_DEG)])
    s = read_fc_log(log)
    assert np.allclose(np.degrees(s.attitude[:, 1]), ROLL_DEG, atol=0.01)
    assert any("roll/pitch from AHR2" in p for p in s.problems)


def test_text_dataflash_log(tmp_path):
    """Before: parsed as binary, 179 000 'bad header' lines on stderr, then 'no ATT messages'."""
    lines = ["FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns",
             "FMT, 60, 31, ATT, Qffffff, TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"]
    lines += [f"ATT, {1_000_000 + 20_000 * k}, 0.0, {r}, 0.0, {-r}, 0.0, 90.0" for k, r in enumerate(ROLL_DEG)]
    log = tmp_path / "flight.log"
    log.write_text("\n".join(lines) + "\n")
    s = read_fc_log(log)
    assert np.allclose(np.degrees(s.attitude[:, 1]), ROLL_DEG) and np.allclose(s.attitude[:, 0], [1.0, 1.02, 1.04, 1.06])


def test_a_damaged_log_keeps_its_noise_off_the_terminal(tmp_path, capfd):
    """Before: 68 316 'bad header' lines on stderr, then the one-line error."""
    good = write_dataflash(tmp_path / "g.bin", {"ATT": (60, "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")},
                           [("ATT", (1_000_000 + 20_000 * k, 0.0, 1.0, 0.0, 1.0, 0.0, 90.0)) for k in range(200)]).read_bytes()
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
