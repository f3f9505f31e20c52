"""Shared helpers and fixtures: waiting for an event, free loopback ports, a plain pymavlink client."""

from __future__ import annotations

import os
import socket
import time

import matplotlib
import pytest

# matplotlib before any test loads GStreamer: with the distribution's PyGObject and GStreamer loaded
# first, importing matplotlib's mathtext tables crashed the interpreter (SIGSEGV, pyenv's Python 3.11 with
# Debian's gi), which ended the whole test run; in this order both load.
matplotlib.use("Agg")
import matplotlib.pyplot  # noqa: E402, F401


def wait_for(done, timeout_s: float = 60.0) -> bool:
    """Until ``done()`` holds, at most ``timeout_s`` of real time (generous: the machine may be loaded);
    whether it holds."""
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port on 127.0.0.1 that nothing is bound to right now."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def mavutil():
    """pymavlink's mavutil in MAVLink 2 with the ardupilotmega dialect, as a ground-station script uses it."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil as mu

    mu.set_dialect("ardupilotmega")
    return mu
