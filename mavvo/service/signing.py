"""Checking MAVLink 2 signatures so that a forged or replayed frame changes nothing.

pymavlink's check records a frame's timestamp before it checks the signature: one unsigned-in-truth
frame with a huge timestamp then makes every genuine frame "old" (a denial of service without the
key). :class:`SignatureCheck` replaces that check on a connection's parser:

1. the signature first (SHA-256 of key + frame, first 6 bytes, compared in constant time): a frame
   that fails it changes no state;
2. then the timestamp, per stream (link id, system, component), as the MAVLink signing spec says: it
   must grow; a stream not seen before is accepted only if its timestamp is at most one minute behind
   the newest accepted one (the spec's rule) and, when the same system and component already sent on
   another link id, not older than that stream's newest by more than ``_OTHER_LINK_SLACK``: so a genuine
   frame recorded on one link and replayed as another cannot fake a flight-controller reboot.

Timestamps are in the spec's unit: 10 microseconds since 2015-01-01.
"""

from __future__ import annotations

import hashlib
import hmac
from collections import Counter
from typing import Any

__all__ = ["SignatureCheck", "install"]

_NEW_STREAM_MAX_AGE = 60 * 100_000  # one minute, in 10 us units (the spec's rule for a new stream)
_OTHER_LINK_SLACK = 100_000  # 1 s: a second link of the same sender runs on the same clock


class SignatureCheck:
    """A replacement for pymavlink's ``MAVLink.check_signature`` (see the module docstring).

    Args:
        signing: the parser's signing state (pymavlink ``MAVLinkSigning``: ``secret_key``,
            ``timestamp``, ``stream_timestamps``); updated only by frames that pass.
        counters: gets ``signature_bad`` and ``signature_replayed``.
    """

    def __init__(self, signing: Any, counters: Counter[str]) -> None:
        self.signing = signing
        self.counters = counters

    def __call__(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        key = self.signing.secret_key
        expected = hashlib.sha256(bytes(key) + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(expected, bytes(msgbuf[-6:])):
            self.counters["signature_bad"] += 1
            return False
        link_id = msgbuf[-13]
        timestamp = int.from_bytes(bytes(msgbuf[-12:-6]), "little")
        streams: dict[tuple[int, int, int], int] = self.signing.stream_timestamps
        last = streams.get((link_id, src_system, src_component))
        if last is not None:
            ok = timestamp > last
        else:
            same_sender = [t for (_, s, c), t in streams.items() if (s, c) == (src_system, src_component)]
            ok = timestamp + _NEW_STREAM_MAX_AGE >= self.signing.timestamp and (
                not same_sender or timestamp + _OTHER_LINK_SLACK >= max(same_sender)
            )
        if not ok:
            self.counters["signature_replayed"] += 1
            return False
        streams[(link_id, src_system, src_component)] = timestamp
        self.signing.timestamp = max(self.signing.timestamp, timestamp)
        return True


def install(mav: Any, counters: Counter[str]) -> None:
    """Make ``mav`` (a pymavlink ``MAVLink`` parser with signing set up) check with :class:`SignatureCheck`."""
    mav.check_signature = SignatureCheck(mav.signing, counters)
