"""``mavvo monitor``: what the service sends, read back into a live view; end to end against a running
``mavvo sim`` whose flight controller forwards to the monitor's port."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mavvo.cli import main
from mavvo.service.mavlink import mavutil
from mavvo.service.monitor import Monitor, render
from tests.conftest import free_port


def _decoded(mav, msg):
    """A message as a receiver sees it: packed to bytes by one side, parsed by the other."""
    parser = mavutil().mavlink.MAVLink(None)
    return parser.parse_char(bytes(msg.pack(mav)))


def test_the_view_follows_what_mavvo_sends():
    m = mavutil().mavlink
    vo = m.MAVLink(None, srcSystem=1, srcComponent=197)
    fc = m.MAVLink(None, srcSystem=1, srcComponent=1)
    mon = Monitor()
    assert not mon.snapshot(0.0).heard and "nothing heard" in render(mon.snapshot(0.0), "udpin:0.0.0.0:14550")
    mon.add(_decoded(vo, m.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3)), 1.0)
    for name, value in (
        ("VO_QUAL", 87.0),
        ("VO_INLIER", 143.0),
        ("VO_STATE", 1.0),
        ("VO_LAT_MS", 42.0),
        ("VO_DRIFT", 0.31),
    ):
        mon.add(_decoded(vo, m.MAVLink_named_value_float_message(1000, name.encode(), value)), 1.1)
    mon.add(_decoded(vo, m.MAVLink_statustext_message(6, b"mavvo: tracking")), 1.2)
    for k in range(20):  # 10 per second, one reset among them
        mon.add(
            _decoded(
                vo, m.MAVLink_vision_position_estimate_message(k, 0, 0, 0, 0, 0, 0, [0.0] * 21, 3 if k < 12 else 4)
            ),
            0.3 + 0.1 * k,
        )
    mon.add(_decoded(fc, m.MAVLink_named_value_float_message(1000, b"VO_QUAL", 1.0)), 2.0)  # not mavvo's: ignored
    s = mon.snapshot(2.3)
    assert (s.state, s.system_status, s.quality, s.inliers, s.latency_ms, s.drift_m) == (
        "tracking",
        "active",
        87.0,
        143.0,
        42.0,
        pytest.approx(0.31),
    )
    assert s.resets == 1 and s.estimates_per_s == pytest.approx(10.0) and s.texts == ((1.2, "mavvo: tracking"),)
    text = render(s, "udpin:0.0.0.0:14550")
    assert "tracking" in text and "inliers 143" in text and "resets 1" in text and "mavvo: tracking" in text
    assert "drift 0.31 m (1 sigma since the origin)" in text
    assert len(mon.timeline) == 1 and mon.timeline[0].quality == 87.0
    assert "SILENT" in render(mon.snapshot(10.0), "x")


def test_mavvo_monitor_shows_a_running_sim(tmp_path):
    port = free_port()
    monitor = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mavvo",
            "monitor",
            "--mavlink",
            f"udpin:127.0.0.1:{port}",
            "--duration",
            "13",
            "--plot",
            str(tmp_path / "t.png"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        sim = subprocess.run(
            [
                sys.executable,
                "-m",
                "mavvo",
                "sim",
                "--scenario",
                "hover",
                "--realtime",
                "--duration",
                "7",
                "--forward",
                f"udpout:127.0.0.1:{port}",
                "--out",
                str(tmp_path / "out"),
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert sim.returncode == 0, sim.stderr
        out, err = monitor.communicate(timeout=120)
    finally:
        if monitor.poll() is None:
            monitor.kill()
    assert monitor.returncode == 0, err
    final = out[out.rindex("mavvo monitor on") :]
    assert "state        tracking" in final and "quality" in final and "mavvo: tracking" in final, out
    assert (tmp_path / "t.png").stat().st_size > 10_000


def test_a_port_another_process_holds_is_refused_before_listening(capsys):
    """Before: pymavlink bound it too (SO_REUSEADDR), and the two processes split the datagrams in silence."""
    import socket

    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("127.0.0.1", 0))
    port = holder.getsockname()[1]
    try:
        assert main(["monitor", "--mavlink", f"udpin:127.0.0.1:{port}", "--duration", "1"]) == 1
    finally:
        holder.close()
    err = capsys.readouterr().err
    assert f"cannot listen on 127.0.0.1:{port}" in err and "another process has the port?" in err
