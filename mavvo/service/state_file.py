"""What the service keeps across restarts (``service.state_file``): the last ``reset_counter`` sent, so
that a restarted service never repeats one the flight controller has seen (it would take the new pose
for a continuation of the old and jump)."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

from mavvo.service.timing import Clock

__all__ = ["ResetCounterFile"]

log = logging.getLogger(__name__)


class ResetCounterFile:
    """``service.state_file`` (empty: none kept) and the counter kept in it.

    Args:
        path: the file; "" keeps nothing.
        clock: the host clock, for a counter that differs between starts where no file is kept.
        on_error: called with an OSError when the file cannot be written (the service flies on).
    """

    def __init__(self, path: str, clock: Clock, on_error: Callable[[OSError], None]) -> None:
        self.path, self.clock, self.on_error = path, clock, on_error

    def first(self) -> int:
        """A ``reset_counter`` the flight controller has not seen from this service: one past the
        last one kept (written back at once), else derived from the clock."""
        if self.path:
            try:
                last = int(json.loads(Path(self.path).read_text(encoding="utf-8"))["reset_counter"])
            except FileNotFoundError:
                last = -1
            except (OSError, ValueError, KeyError, TypeError) as e:
                log.warning(
                    "service.state_file %s: cannot read the last reset_counter (%s); starting from the clock",
                    self.path,
                    e,
                )
                last = int(self.clock.now_s() * 10)
            first = (last + 1) % 256
            self.save(first)
            return first
        # No state file: a real clock's tenths of a second since the host's boot differ between two
        # starts of the service; a simulated one starts at 0, so runs repeat.
        return int(self.clock.now_s() * 10) % 256 if self.clock.realtime else 0

    def save(self, counter: int) -> None:
        """Keep ``counter`` (atomically: a crash leaves the old file or the new one). Nothing without a path."""
        if not self.path:
            return
        path = Path(self.path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text(json.dumps({"reset_counter": counter}) + "\n", encoding="utf-8")
            tmp.replace(path)
        except OSError as e:
            self.on_error(e)
