"""The service's settings file and the command line's exit codes for it."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mavvo.cli import main
from mavvo.errors import ConfigError
from mavvo.service.settings import ServiceConfig, default_yaml, load_config

ROOT = Path(__file__).resolve().parents[1]


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "mavvo.yaml"
    p.write_text(text, encoding="utf-8")
    return p


def test_default_yaml_lists_every_key_and_is_current():
    assert (ROOT / "config" / "default.yaml").read_text(encoding="utf-8") == default_yaml(), (
        'run: python -c \'from mavvo.service.settings import default_yaml; open("config/default.yaml","w").write(default_yaml())\''
    )
    assert load_config(ROOT / "config" / "default.yaml") == ServiceConfig()
    text = default_yaml()
    for section in ("camera", "mounting", "link", "timing", "output", "service", "odometry"):
        for f in dataclasses.fields(getattr(ServiceConfig(), section)):
            assert f"  {f.name}:" in text, f"{section}.{f.name} missing from default.yaml"


def test_sim_yaml_loads():
    cfg = load_config(ROOT / "config" / "sim.yaml")
    assert cfg.camera.source.startswith("sim:") and cfg.link.url.startswith("udpout:127.0.0.1:")


@pytest.mark.parametrize(
    "text, message",
    [
        ("camera: {widht_px: 640}", "mavvo.yaml: camera.widht_px: unknown key; expected one of"),
        ("camera: {width_px: wide}", "camera.width_px: expected an integer, got 'wide'"),
        ("odometry: {ransac: {max_err_px: -1}}", "odometry.ransac.max_err_px: expected a number > 0, got -1"),
        ("output: {max_rate_hz: 80}", "output.max_rate_hz: expected a number <= 50, got 80"),
        ("output: {odometry: yes please}", "output.odometry: expected true or false, got 'yes please'"),
        ("odometry: {scale: {source: lidar}}", "odometry.scale.source: expected one of 'rangefinder'"),
        (
            "mounting: {R_body_cam: [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}",
            "mounting: R_body_cam: expected a rotation matrix",
        ),
        ("mounting: {R_body_cam: [[1, 0, 0], [0, 1, 0]]}", "mounting.R_body_cam: expected a list of 3 values"),
        ("link: {url: COM3}", "link.url: expected /dev/DEVICE:BAUD, udpin:HOST:PORT"),
        ("link: {url: 'udpout:127.0.0.1:99999'}", "link.url: expected udpout:HOST:PORT with a port 1-65535"),
        ("camera: {model: fisheye, distortion: [0.1]}", "camera:"),
        ("- just a list", "expected a mapping of keys at the top level, got list"),
        # Mistakes across keys, with what to set.
        (
            "link: {attitude_rate_hz: 10}\ncamera: {rate_hz: 20}",
            "link.attitude_rate_hz (10) is below camera.rate_hz (20)",
        ),
        (
            "link: {attitude_rate_hz: 20}\ntiming: {max_attitude_gap_s: 0.04}",
            "timing.max_attitude_gap_s (0.04) is shorter than the ATTITUDE period (0.05 s",
        ),
        ("camera: {cx_px: 900}", "camera: cx_px, cy_px: expected the principal point inside the 640x480 image"),
        ("camera: {fx_px: 20}", "camera.fx_px (20) gives a 172.8 deg horizontal field of view on a 640 px wide image"),
        ("camera: {source: [", "not valid YAML"),
        ("link: {url: 'udpout:127.0.0.1:9'}\nlink: {url: 'udpout:127.0.0.1:10'}", "duplicate key 'link'"),
        ("a: &x [1, 2]\nb: [*x, *x]", "aliases (*name) are not allowed"),
    ],
)
def test_each_kind_of_bad_value_names_the_key(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert message in str(e.value) and str(path) in str(e.value)


def test_check_config_exit_codes(tmp_path, capsys):
    assert main(["check-config", str(ROOT / "config" / "default.yaml")]) == 0
    assert ": ok" in capsys.readouterr().out
    assert main(["check-config", str(write(tmp_path, "link: {attitude_rate_hz: 0}"))]) == 2
    err = capsys.readouterr().err
    assert "link.attitude_rate_hz: expected a number > 0, got 0" in err and err.count("\n") == 1
    assert main(["check-config", str(tmp_path / "nowhere.yaml")]) == 2
    assert "nowhere.yaml: cannot read" in capsys.readouterr().err
    # An empty file is valid but says so (issue 49: it passed silently).
    for text in ("", "# all defaults\n"):
        assert main(["check-config", str(write(tmp_path, text))]) == 0
        assert "it sets nothing, so every setting is its default" in capsys.readouterr().out
    assert main(["check-config", str(write(tmp_path, "link: {attitude_rate_hz: 20}"))]) == 0
    assert "sets nothing" not in capsys.readouterr().out


def test_run_exit_codes(tmp_path, capsys):
    assert main(["run", "--config", str(write(tmp_path, "service: {shutdown_drain_s: -1}"))]) == 2
    assert "service.shutdown_drain_s" in capsys.readouterr().err
    missing = tmp_path / "no_such_video.mp4"
    cfg = write(tmp_path, f"camera: {{source: '{missing}'}}\nlink: {{url: 'udpout:127.0.0.1:9'}}\n")
    assert main(["run", "--config", str(cfg)]) == 1
    err = capsys.readouterr().err
    assert "camera.source" in err and "no_such_video.mp4" in err and "Traceback" not in err
    key = tmp_path / "key"
    key.write_text("0" * 64)
    os.chmod(key, 0o644)
    cfg = write(
        tmp_path, f"camera: {{source: 'sim:hover'}}\nlink: {{url: 'udpout:127.0.0.1:9', signing_key_file: '{key}'}}\n"
    )
    assert main(["run", "--config", str(cfg)]) == 2
    assert "expected mode 0600 or stricter" in capsys.readouterr().err
    # check-config refuses what run refuses (it passed a world-readable or missing key before)
    assert main(["check-config", str(cfg)]) == 2
    assert "expected mode 0600 or stricter" in capsys.readouterr().err
    key.unlink()
    assert main(["check-config", str(cfg)]) == 2
    assert "link.signing_key_file" in capsys.readouterr().err


def test_version_and_help_exit_zero():
    out = subprocess.run([sys.executable, "-m", "mavvo", "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith("mavvo ")
    for cmd in (
        ["--help"],
        ["run", "--help"],
        ["sim", "--help"],
        ["check-config", "--help"],
        ["calibrate", "--help"],
        ["monitor", "--help"],
    ):
        with pytest.raises(SystemExit) as e:
            main(cmd)
        assert e.value.code == 0
    with pytest.raises(SystemExit) as e:
        main(["run"])  # --config is required
    assert e.value.code == 2


def test_a_settings_file_must_be_utf8_and_of_a_sane_size(tmp_path):
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes("camera: {source: '/dev/vid\xe9o0'}\n".encode("latin-1"))
    with pytest.raises(ConfigError, match="latin1.yaml: expected UTF-8 text, got byte 0xe9 at offset 26"):
        load_config(bad)
    big = tmp_path / "big.yaml"
    big.write_bytes(b"#" * (10 * 1024 * 1024 + 1))
    with pytest.raises(ConfigError, match="big.yaml: expected a settings file of at most 10 MiB"):
        load_config(big)
