"""systemd notifications (``sd_notify``): READY, WATCHDOG, STOPPING and STATUS over ``$NOTIFY_SOCKET``.

Nothing happens when the variable is unset (not started by systemd with ``Type=notify``).
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


def notify(state: str) -> bool:
    """Send ``state`` (e.g. ``READY=1``) to systemd; True if it was sent."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):
        addr = "\0" + addr[1:]  # abstract namespace
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.connect(addr)
            s.sendall(state.encode("utf-8"))
        return True
    except OSError as e:
        log.warning("systemd notification %r failed: %s", state, e)
        return False


def watchdog_interval_s() -> float | None:
    """Half the watchdog period systemd asks for (``$WATCHDOG_USEC``), or None without a watchdog."""
    usec = os.environ.get("WATCHDOG_USEC", "")
    pid = os.environ.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) <= 0 or (pid.isdigit() and int(pid) != os.getpid()):
        return None
    return int(usec) * 1e-6 / 2.0
