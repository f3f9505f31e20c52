"""The unit file asks systemd for what the service needs, and its commands are ones mavvo accepts."""

from __future__ import annotations

import configparser
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mavvo.cli import _parser

UNIT = Path(__file__).resolve().parents[1] / "systemd" / "mavvo.service"


@pytest.fixture(scope="module")
def unit():
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # systemd keys are case-sensitive
    cp.read(UNIT)
    return cp


def test_unit_hardening_and_supervision(unit):
    s = unit["Service"]
    assert s["Type"] == "notify" and float(s["WatchdogSec"]) > 0 and s["Restart"] == "on-failure"
    assert s["User"] == "mavvo" and set(s["SupplementaryGroups"].split()) == {"dialout", "video"}
    for key in ("NoNewPrivileges", "ProtectHome", "PrivateTmp"):
        assert s[key] == "yes", key
    assert s["ProtectSystem"] == "strict" and s["LogsDirectory"] == "mavvo" and s["StateDirectory"] == "mavvo"
    assert s["UMask"] == "0077" and s["CapabilityBoundingSet"] == "" and s["LockPersonality"] == "yes"
    assert s["RestartPreventExitStatus"] == "2"  # a configuration error does not fix itself
    # The compiled kernels' cache lives where the service may write: the cache directory systemd makes for it.
    assert s["CacheDirectory"] == "mavvo" and "NUMBA_CACHE_DIR=/var/cache/mavvo/numba" in s["Environment"]
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_unit_commands_parse(unit):
    for key in ("ExecStart", "ExecStartPre"):
        argv = shlex.split(unit["Service"][key])
        assert argv[0].endswith("/mavvo")
        args = _parser().parse_args(argv[1:])
        assert args.command in ("run", "check-config")
    args = _parser().parse_args(shlex.split(unit["Service"]["ExecStart"])[1:])
    assert str(args.config) == "/etc/mavvo/mavvo.yaml"


def _runnable_copy(tmp_path: Path) -> Path:
    """The unit with its commands pointing at an executable that exists here (verify checks them)."""
    exe = tmp_path / "mavvo"
    exe.write_text(f"#!{sys.executable}\n")
    exe.chmod(0o755)
    unit = tmp_path / "mavvo.service"
    unit.write_text(UNIT.read_text().replace("/opt/mavvo/.venv/bin/mavvo", str(exe)))
    return unit


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_systemd_analyze_verifies_the_unit_and_rates_it_ok(tmp_path):
    unit = _runnable_copy(tmp_path)
    verify = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr
    assert "mavvo.service" not in verify.stderr, verify.stderr  # no complaint about the unit itself
    security = subprocess.run(
        ["systemd-analyze", "security", "--offline=true", str(unit)], capture_output=True, text=True, timeout=120
    )
    m = re.search(r"Overall exposure level for mavvo.service: ([0-9.]+) (\w+)", security.stdout)
    assert m is not None, security.stdout + security.stderr
    assert float(m.group(1)) <= 3.0 and m.group(2) == "OK", security.stdout
