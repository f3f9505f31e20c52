"""``mavvo preflight`` against the simulated flight controller's parameter table (ArduPilot and PX4
flavours): wrong parameters are named with a non-zero exit, ``--fix`` makes it pass, an armed vehicle
is never written to."""

from __future__ import annotations

import subprocess
import sys
import threading
from dataclasses import replace

import pytest

from mavvo.cli import main
from mavvo.service.preflight import Verdict, checks
from mavvo.service.settings import MountingOptions, ServiceConfig
from mavvo.sim.flight_controller.spec import VISION_READY_PARAMS
from mavvo.sim.scenarios.flight import Simulation
from mavvo.sim.scenarios.loader import load_scenario
from tests.conftest import free_port


class FcOnly:
    """The simulated flight controller of the hover scenario, in real time, listening on a UDP port."""

    def __init__(self, **fc) -> None:
        sc = load_scenario("hover")
        sc = replace(sc, flight_controller=replace(sc.flight_controller, **fc))
        self.port = free_port()
        self.sim = Simulation(sc, f"udpin:127.0.0.1:{self.port}", realtime=True)
        self.stop = threading.Event()
        self.thread = threading.Thread(
            target=self.sim.serve, args=(self.stop,), kwargs={"until_s": float("inf")}, daemon=True
        )
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(10)
        self.sim.close()


@pytest.fixture
def fc_only():
    made = []

    def make(**fc):
        made.append(FcOnly(**fc))
        return made[-1]

    yield make
    for f in made:
        f.close()


def test_checks_name_what_is_wrong_and_what_to_set():
    ready = VISION_READY_PARAMS["ardupilot"]
    cfg = ServiceConfig()
    assert all(c.verdict is Verdict.OK for c in checks("ardupilot", ready, cfg, advised_delay_ms=30.0, has_origin=True))
    wrong = {**ready, "VISO_TYPE": 0, "EK3_SRC1_POSXY": 3, "VISO_DELAY_MS": 100}
    moved = replace(cfg, mounting=MountingOptions(lever_arm_m=(0.1, 0.0, 0.05)))
    by_name = {c.name: c for c in checks("ardupilot", wrong, moved, advised_delay_ms=45.0, has_origin=False)}
    assert by_name["VISO_TYPE"].verdict is Verdict.BLOCK and by_name["VISO_TYPE"].set_to == 1
    assert by_name["EK3_SRC1_POSXY"].set_to == 6 and by_name["EKF origin"].verdict is Verdict.BLOCK
    assert by_name["VISO_DELAY_MS"].verdict is Verdict.WARN and by_name["VISO_DELAY_MS"].set_to == 45
    assert by_name["VISO_POS_X"].set_to == pytest.approx(0.1) and by_name["VISO_POS_Y"].verdict is Verdict.OK
    # No latency measured yet: 0 ms (the parameter's default) cannot be right; a plausible value passes.
    unmeasured = {c.name: c for c in checks("ardupilot", {**ready, "VISO_DELAY_MS": 0}, cfg)}["VISO_DELAY_MS"]
    assert unmeasured.verdict is Verdict.WARN and "as if taken when it arrives" in unmeasured.advice
    assert {c.name: c for c in checks("ardupilot", ready, cfg)}["VISO_DELAY_MS"].verdict is Verdict.OK
    # No GPS: GPS sources for velocity or yaw block (before: warnings, and --fix left them).
    gps = {**ready, "EK3_SRC1_VELXY": 3, "EK3_SRC1_YAW": 2}
    no_gps = {c.name: c for c in checks("ardupilot", gps, cfg)}
    assert no_gps["EK3_SRC1_VELXY"].verdict is Verdict.BLOCK and no_gps["EK3_SRC1_VELXY"].set_to == 6
    assert no_gps["EK3_SRC1_YAW"].verdict is Verdict.BLOCK and no_gps["EK3_SRC1_YAW"].set_to == 1
    with_gps = {c.name: c for c in checks("ardupilot", {**gps, "GPS1_TYPE": 1}, cfg)}
    assert with_gps["EK3_SRC1_VELXY"].verdict is with_gps["EK3_SRC1_YAW"].verdict is Verdict.WARN
    before_4_6 = {k: v for k, v in gps.items() if k != "GPS1_TYPE"} | {"GPS_TYPE": 0}
    old_name = {c.name: c for c in checks("ardupilot", before_4_6, cfg)}
    assert old_name["EK3_SRC1_YAW"].verdict is Verdict.BLOCK  # GPS_TYPE before ArduPilot 4.6
    # The heading policy decides the yaw source --fix sets: mavvo's own heading wants the EKF on it.
    own = replace(cfg, odometry=replace(cfg.odometry, heading_source="vision"))
    by_policy = {c.name: c for c in checks("ardupilot", ready, own)}["EK3_SRC1_YAW"]
    assert by_policy.verdict is Verdict.WARN and by_policy.set_to == 6
    ekf = {c.name: c for c in checks("ardupilot", ready, cfg, ekf_flags=0x1 | 0x80)}["EKF status"]
    assert ekf.verdict is Verdict.WARN and "no horizontal position" in ekf.advice
    px4 = {c.name: c for c in checks("px4", {**VISION_READY_PARAMS["px4"], "EKF2_EV_CTRL": 2}, cfg)}
    assert (
        px4["EKF2_EV_CTRL"].verdict is Verdict.BLOCK and px4["EKF2_EV_CTRL"].set_to == 3
    )  # bit 0 added, the rest kept


def test_preflight_names_each_wrong_parameter_and_fix_makes_it_pass(fc_only, capsys):
    fc = fc_only(
        armed=False,
        params=(("VISO_TYPE", 0.0), ("EK3_SRC1_POSXY", 3.0), ("VISO_POS_Z", 0.2), ("EK3_SRC1_YAW", 3.0)),
    )
    url = f"udpout:127.0.0.1:{fc.port}"
    assert main(["preflight", "--mavlink", url, "--latency-ms", "30"]) == 1
    out = capsys.readouterr().out
    assert "flight controller: ardupilot" in out
    assert any(line.startswith("EKF status") and " ok " in line for line in out.splitlines()), out
    for name in ("VISO_TYPE", "EK3_SRC1_POSXY", "VISO_POS_Z", "EK3_SRC1_YAW"):
        assert any(line.startswith(name) and ("BLOCK" in line or "WARN" in line) for line in out.splitlines()), (
            name,
            out,
        )
    assert "would set: VISO_TYPE = 1, EK3_SRC1_POSXY = 6, EK3_SRC1_YAW = 1, VISO_POS_Z = 0" in out
    assert main(["preflight", "--mavlink", url, "--latency-ms", "30", "--fix"]) == 0
    out = capsys.readouterr().out
    assert "set VISO_TYPE = 1: confirmed" in out and "reboots" in out
    assert (
        fc.sim.fc.params["VISO_TYPE"] == 1
        and fc.sim.fc.params["EK3_SRC1_POSXY"] == 6
        and fc.sim.fc.params["VISO_POS_Z"] == 0
        and fc.sim.fc.params["EK3_SRC1_YAW"] == 1
    )
    assert main(["preflight", "--mavlink", url, "--latency-ms", "30"]) == 0


def test_preflight_never_writes_to_an_armed_vehicle_and_checks_px4(fc_only, capsys):
    fc = fc_only(armed=True, params=(("VISO_TYPE", 0.0),))
    assert main(["preflight", "--mavlink", f"udpout:127.0.0.1:{fc.port}", "--fix"]) == 1
    assert "armed" in capsys.readouterr().err and fc.sim.fc.params["VISO_TYPE"] == 0
    px4 = fc_only(autopilot="px4", armed=False, params=(("EKF2_EV_CTRL", 0.0),))
    assert main(["preflight", "--mavlink", f"udpout:127.0.0.1:{px4.port}"]) == 1
    assert "flight controller: px4" in capsys.readouterr().out


def test_no_flight_controller_is_a_clear_error():
    out = subprocess.run(
        [sys.executable, "-m", "mavvo", "preflight", "--mavlink", f"udpout:127.0.0.1:{free_port()}", "--timeout", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert (
        out.returncode == 1 and "no flight controller HEARTBEAT in 1 s" in out.stderr and "Traceback" not in out.stderr
    )
