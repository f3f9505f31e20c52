"""Which autopilot on the link is the flight controller: the configured system id at its first
HEARTBEAT, else the first autopilot whose HEARTBEAT and ATTITUDE have both come for ``fc_confirm_s``.
Any other after that is reported (logged once, counted as ``other_autopilots``), never followed."""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass

from mavvo.service.link_options import LinkOptions

__all__ = ["AutopilotChoice"]

log = logging.getLogger(__name__)

_MAX_KNOWN = 16  # a flood of forged ids must not grow the candidates or the warnings without bound


@dataclass
class _Candidate:
    """An autopilot heard before one was chosen: (first HEARTBEAT, HEARTBEATs, ATTITUDEs, MAV_AUTOPILOT)."""

    first_heartbeat_s: float
    autopilot: int
    heartbeats: int = 1
    attitudes: int = 0


class AutopilotChoice:
    """The choice, made from what the link hears (link thread only); ``counters`` is the link's."""

    def __init__(self, options: LinkOptions, counters: Counter[str]) -> None:
        self.options, self.counters = options, counters
        self.system_id: int | None = options.fc_system_id or None
        self.component_id: int | None = None  # set once the flight controller is chosen
        self.autopilot: int | None = None  # the chosen one's HEARTBEAT autopilot (MAV_AUTOPILOT)
        self.candidates: dict[tuple[int, int], _Candidate] = {}
        self._others_told: set[tuple[int, int]] = set()

    def is_chosen(self, sys_id: int, comp_id: int) -> bool:
        return (sys_id, comp_id) == (self.system_id, self.component_id)

    def heartbeat(self, sys_id: int, comp_id: int, autopilot: int, now: float) -> bool:
        """An autopilot's HEARTBEAT; whether it chose the flight controller just now."""
        key = (sys_id, comp_id)
        if self.component_id is not None:
            if not self.is_chosen(sys_id, comp_id):
                self.counters["other_autopilots"] += 1
                if key not in self._others_told and len(self._others_told) < _MAX_KNOWN:
                    self._others_told.add(key)
                    log.warning(
                        "another autopilot on the link (system %d component %d): ignored; following system %d component %d",
                        sys_id,
                        comp_id,
                        self.system_id,
                        self.component_id,
                    )
            return False
        if self.options.fc_system_id and sys_id != self.options.fc_system_id:
            self.counters["other_autopilots"] += 1
            return False
        c = self.candidates.get(key)
        if c is None:
            if len(self.candidates) >= _MAX_KNOWN:
                return False
            c = self.candidates[key] = _Candidate(now, autopilot)
        else:
            c.heartbeats += 1
        if self.options.fc_system_id:
            return self._choose(sys_id, comp_id, autopilot)
        return self._confirm_if_consistent(key, c, now)

    def attitude(self, sys_id: int, comp_id: int, now: float) -> bool:
        """An ATTITUDE from an autopilot not (yet) chosen; whether it chose the flight controller just now."""
        c = self.candidates.get((sys_id, comp_id))
        if c is None:
            return False
        c.attitudes += 1
        return self._confirm_if_consistent((sys_id, comp_id), c, now)

    def _confirm_if_consistent(self, key: tuple[int, int], c: _Candidate, now: float) -> bool:
        """Chosen once its HEARTBEAT (twice) and ATTITUDE have come for ``fc_confirm_s``."""
        if c.heartbeats >= 2 and c.attitudes >= 3 and now - c.first_heartbeat_s >= self.options.fc_confirm_s:
            return self._choose(*key, c.autopilot)
        return False

    def _choose(self, sys_id: int, comp_id: int, autopilot: int) -> bool:
        self.system_id, self.component_id, self.autopilot = sys_id, comp_id, autopilot
        self.candidates.clear()
        log.info("flight controller: system %d component %d (autopilot type %d)", sys_id, comp_id, autopilot)
        return True
