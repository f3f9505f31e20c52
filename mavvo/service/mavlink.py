"""pymavlink, loaded once in MAVLink 2 with the ardupilotmega dialect: the only module that imports it.

VISION_POSITION_ESTIMATE's ``covariance`` and ``reset_counter`` exist only in MAVLink 2; pymavlink
picks its wire version from ``MAVLINK20`` when its dialect is first loaded. A program that imported
pymavlink before mavvo has the MAVLink 1 dialect loaded, so :func:`mavutil` checks
``WIRE_PROTOCOL_VERSION`` and reloads the dialect when it is not ``2.0``, whoever came first.
"""

from __future__ import annotations

import os
from types import ModuleType

from mavvo.errors import LinkError

__all__ = ["SOCKET_SCHEMES", "dfreader", "mavutil"]

# The socket forms of a pymavlink connection string; anything else is a serial device.
SOCKET_SCHEMES = ("udpin:", "udpout:", "tcp:", "tcpin:")
_DIALECT = "ardupilotmega"


def mavutil() -> ModuleType:
    """pymavlink's ``mavutil`` set to MAVLink 2 and the ardupilotmega dialect; LinkError if it cannot be."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil as mu

    if getattr(mu.mavlink, "WIRE_PROTOCOL_VERSION", "") != "2.0" or mu.current_dialect != _DIALECT:
        mu.set_dialect(_DIALECT)
    if getattr(mu.mavlink, "WIRE_PROTOCOL_VERSION", "") != "2.0":
        raise LinkError(f"pymavlink did not load MAVLink 2 (WIRE_PROTOCOL_VERSION {mu.mavlink.WIRE_PROTOCOL_VERSION})")
    return mu


def dfreader() -> ModuleType:
    """pymavlink's ``DFReader`` (ArduPilot dataflash logs)."""
    from pymavlink import DFReader

    return DFReader
