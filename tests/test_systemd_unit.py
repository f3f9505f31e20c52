"""The unit file asks systemd for what the service needs, and its commands are ones mavvo accepts."""

from __future__ import annotations

import configparser
import shlex
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
    assert s["ProtectSystem"] == "strict" and "/var/log/mavvo" in s["ReadWritePaths"]
    assert s["RestartPreventExitStatus"] == "2"  # a configuration error does not fix itself
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_unit_commands_parse(unit):
    for key in ("ExecStart", "ExecStartPre"):
        argv = shlex.split(unit["Service"][key])
        assert argv[0].endswith("/mavvo")
        args = _parser().parse_args(argv[1:])
        assert args.command in ("run", "check-config")
    args = _parser().parse_args(shlex.split(unit["Service"]["ExecStart"])[1:])
    assert str(args.config) == "/etc/mavvo/mavvo.yaml"
