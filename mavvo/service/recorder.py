"""Recording a flight on the drone, so that ``mavvo replay`` can run it again exactly.

A recording is a folder (``record.dir``/YYYYmmdd-HHMMSS) holding:

- ``config.yaml``: the settings in effect (every key);
- ``mavlink-NNN.tlog``: every MAVLink message the link read or wrote, in pymavlink's .tlog format,
  stamped with the host-clock microsecond the link gave it plus ``unix_minus_host_us`` (meta.json), so
  ground-station tools see wall-clock times and replay recovers the exact host stamps. Messages from
  component 197 are mavvo's own; everything else came in;
- ``frames-NNN.csv`` and ``frames/``: each frame the worker took, as a lossless PNG (or a JPEG at
  ``jpeg_quality``), with its exposure time, the flight-controller state version it was paired at
  and the pairing it got (see :class:`mavvo.service.timing.Pairing`); floats are written exactly;
- ``meta.json``: format version, clocks, what was written and dropped, why recording stopped.

Recording never holds the service up: the link and the worker hand items to bounded queues and a
writer thread does the disk work; when a queue is full the item is dropped and counted. On a simulated
(lockstep) clock the producers wait for room instead, holding the simulation back: nothing is lost. Recording
stops (counted, logged, reported through ``on_stop``) when the recording reaches ``max_total_mb``, the
disk's free space falls below ``min_free_mb``, or a write fails (disk full, medium gone); what was
written stays readable, and the service goes on. The .tlog and frame index start a new segment every
``rotate_mb`` and on :meth:`Recorder.reopen` (SIGHUP). On close, the writer drains what is queued
(bounded) and closes every file. The folder is created 0700 and every file 0600: a flight's images and
messages are the operator's.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import queue
import shutil
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Callable, Literal

import cv2

from mavvo import __version__
from mavvo.errors import ConfigError, RecordingError
from mavvo.options import bounded
from mavvo.service.link import COMPONENT_ID
from mavvo.service.timing import Clock, MonotonicClock, Pairing
from mavvo.service.tlog import write_record
from mavvo.types import Frame

__all__ = ["RecordOptions", "Recorder", "FORMAT_VERSION", "FRAME_COLUMNS"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
FRAME_COLUMNS = (
    "seq",
    "t_exposure_s",
    "t_paired_s",
    "fc_version",
    "status",
    "roll_rad",
    "pitch_rad",
    "yaw_rad",
    "range_m",
    "height_m",
    "file",
)
_MB = 1 << 20
_FREE_CHECK_S = 1.0
_CLOSE_DRAIN_S = 5.0


_LOCKSTEP_PUT_TIMEOUT_S = 30.0  # real seconds a lockstep producer waits for the disk at most


@dataclass(frozen=True)
class RecordOptions:
    """Recording the flight for replay (mavvo run --record DIR sets dir)."""

    dir: str = bounded("", "record each run into a new folder under this directory (empty: no recording)")
    frames: Literal["png", "jpg"] = bounded(
        "png", "png: lossless, replays bit for bit; jpg: about 5x smaller at jpeg_quality"
    )
    jpeg_quality: int = bounded(95, "JPEG quality of jpg frames", ge=50, le=100)
    max_total_mb: float = bounded(4096.0, "stop recording when the recording reaches this size", gt=0, le=1e7)
    min_free_mb: float = bounded(512.0, "stop recording when the disk has less free space than this", ge=0, le=1e7)
    rotate_mb: float = bounded(256.0, "start a new .tlog and frame index after this many MB", gt=0, le=1e6)
    queue_frames: int = bounded(
        16, "frames waiting for the disk; beyond, new frames are dropped and counted", ge=1, le=4096
    )
    queue_messages: int = bounded(
        8192, "MAVLink messages waiting for the disk; beyond, dropped and counted", ge=1, le=1000000
    )


def _float(v: float | None) -> str:
    return "" if v is None else repr(float(v))


class Recorder:
    """Writes one recording (see the module docstring). Thread-safe producers: :meth:`mavlink` (the
    link's tap) and :meth:`frame` (the worker); :meth:`close` once at the end.

    Counters: ``messages``, ``frames``, ``bytes``, ``dropped_messages``, ``dropped_frames`` (queue full
    or recording stopped), ``write_errors``, ``segments``.
    """

    def __init__(
        self, options: RecordOptions, config_yaml: str, clock: Clock, on_stop: Callable[[str], None] | None = None
    ) -> None:
        if not options.dir:
            raise ConfigError("record.dir: expected a directory to record into, got an empty string")
        self.options = options
        self.clock = clock
        self.on_stop = on_stop
        self._reopen = threading.Event()
        self._wall = MonotonicClock()
        self.counters: Counter[str] = Counter()
        self.path = self._new_folder(Path(options.dir))
        self.stopped_reason = ""
        self._unix_minus_host_us = round((time.time() - clock.now_s()) * 1e6)
        self._frames_q: queue.Queue[tuple[Frame, Pairing, float]] = queue.Queue(options.queue_frames)
        self._mav_q: queue.Queue[tuple[int, bytes]] = queue.Queue(options.queue_messages)
        self._closing = threading.Event()
        self._tlog: IO[bytes] | None = None
        self._csv_file: IO[str] | None = None
        self._csv: Any = None
        self._segment = -1
        self._segment_bytes = 0
        self._next_free_check_s = 0.0
        try:
            (self.path / "frames").mkdir(mode=0o700)
            _write_private(self.path / "config.yaml", config_yaml.encode("utf-8"))
            self._write_meta()
            self._rotate()
        except OSError as e:
            self._close_segment()
            raise RecordingError(
                f"record.dir {options.dir}: cannot write the recording {self.path}: {e.strerror or e}"
            ) from e
        self._thread = threading.Thread(target=self._writer, name="mavvo-recorder", daemon=True)
        self._thread.start()
        log.info("recording into %s", self.path)

    @staticmethod
    def _new_folder(parent: Path) -> Path:
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        try:
            parent.mkdir(parents=True, exist_ok=True, mode=0o700)
            for n in range(1000):
                p = parent / (stamp if n == 0 else f"{stamp}-{n}")
                try:
                    p.mkdir(mode=0o700)
                    return p
                except FileExistsError:
                    continue
        except OSError as e:
            raise RecordingError(f"record.dir {parent}: cannot create a recording folder: {e.strerror or e}") from e
        raise RecordingError(f"record.dir {parent}: too many recordings started in the same second")

    # ------------------------------------------------------------------ producers (never block)

    def mavlink(self, t_host_us: int, frame: bytes) -> None:
        """The link's tap: one message with the host stamp the link gave it."""
        self._offer(self._mav_q, (t_host_us, frame), "dropped_messages")

    def frame(self, frame: Frame, pairing: Pairing, t_paired_s: float) -> None:
        """A frame the worker took, with the pairing it got at host time ``t_paired_s``."""
        self._offer(self._frames_q, (frame, pairing, t_paired_s), "dropped_frames")

    def _offer(self, q: queue.Queue[Any], item: Any, drop_counter: str) -> None:
        if self.stopped_reason or self._closing.is_set():
            self.counters[drop_counter] += 1
            return
        try:
            if self.clock.realtime:
                q.put_nowait(item)  # in flight the service never waits for the disk
            else:
                # Lockstep (a simulated clock): waiting holds the simulation back instead of losing the
                # item, so a recording of a simulated flight is whole however slow the disk or busy the
                # machine. Bounded, should the writer be stuck: then dropped and counted as in flight.
                q.put(item, timeout=_LOCKSTEP_PUT_TIMEOUT_S)
        except queue.Full:
            self.counters[drop_counter] += 1

    # ------------------------------------------------------------------ the writer thread

    def reopen(self) -> None:
        """Close the current files and continue in new ones (SIGHUP); thread-safe, acted on by the writer."""
        self._reopen.set()

    def _writer(self) -> None:
        try:
            self._write_loop()
        except OSError as e:  # the disk failed under us: what is written stays, vision goes on
            self.counters["write_errors"] += 1
            self._stop(f"a write failed: {e.strerror or e}")

    def _write_loop(self) -> None:
        while True:
            if self._reopen.is_set():
                self._reopen.clear()
                if not self.stopped_reason:
                    self._rotate()
                    log.info("recording: files reopened (segment %d)", self._segment)
            self._drain_messages()
            try:
                item = self._frames_q.get(timeout=0.05)
            except queue.Empty:
                if self._closing.is_set() and self._mav_q.empty():
                    return
                continue
            self._write_frame(*item)

    def _drain_messages(self) -> None:
        while True:
            try:
                t_us, frame = self._mav_q.get_nowait()
            except queue.Empty:
                return
            if self._writable() and self._tlog is not None:
                self._account(write_record(self._tlog, t_us + self._unix_minus_host_us, frame))
                self.counters["messages"] += 1
            else:
                self.counters["dropped_messages"] += 1

    def _write_frame(self, frame: Frame, p: Pairing, t_paired_s: float) -> None:
        if not self._writable():
            self.counters["dropped_frames"] += 1
            return
        name = f"{frame.seq:09d}.{self.options.frames}"
        params = (
            [cv2.IMWRITE_PNG_COMPRESSION, 1]
            if self.options.frames == "png"
            else [cv2.IMWRITE_JPEG_QUALITY, self.options.jpeg_quality]
        )
        try:
            ok, buf = cv2.imencode(f".{self.options.frames}", frame.image, params)
            if not ok:
                raise ValueError("the encoder refused the image")
            _write_private(self.path / "frames" / name, buf.tobytes())
        except (ValueError, cv2.error) as e:
            self.counters["write_errors"] += 1
            if self.counters["write_errors"] <= 3:
                log.warning("recording: frame %d not written: %s", frame.seq, e)
            return
        self._csv.writerow(
            [
                frame.seq,
                repr(frame.t_exposure_s),
                repr(t_paired_s),
                p.fc_version,
                p.status,
                _float(p.roll_rad),
                _float(p.pitch_rad),
                _float(p.yaw_rad),
                _float(p.range_m),
                _float(p.height_m),
                name,
            ]
        )
        self.counters["frames"] += 1
        self._account(len(buf))

    def _account(self, n: int) -> None:
        self.counters["bytes"] += n
        self._segment_bytes += n
        if self._segment_bytes >= self.options.rotate_mb * _MB:
            self._rotate()

    def _writable(self) -> bool:
        if self.stopped_reason:
            return False
        if self.counters["bytes"] >= self.options.max_total_mb * _MB:
            self._stop(f"the recording reached record.max_total_mb = {self.options.max_total_mb:g}")
            return False
        now = self._wall.now_s()  # real time: the disk fills in real time, also in a simulation
        if now >= self._next_free_check_s:
            self._next_free_check_s = now + _FREE_CHECK_S
            try:
                free_mb = shutil.disk_usage(self.path).free / _MB
            except OSError as e:
                self._stop(f"cannot check the disk: {e.strerror or e}")
                return False
            if free_mb < self.options.min_free_mb:
                self._stop(
                    f"{free_mb:.0f} MB free on the disk, below record.min_free_mb = {self.options.min_free_mb:g}"
                )
                return False
        return True

    def _stop(self, reason: str) -> None:
        self.stopped_reason = reason
        log.warning("recording stopped: %s (%s kept)", reason, self.path)
        try:
            self._close_segment()
        except OSError as e:  # closing flushes; on a full disk that may fail too: the file keeps what it had
            log.warning("recording: closing %s: %s", self.path, e.strerror or e)
        if self.on_stop is not None:
            self.on_stop(reason)

    def _rotate(self) -> None:
        self._close_segment()
        self._segment += 1
        self.counters["segments"] += 1
        self._segment_bytes = 0
        self._tlog = _open_private(self.path / f"mavlink-{self._segment:03d}.tlog", "wb")
        self._csv_file = _open_private(self.path / f"frames-{self._segment:03d}.csv", "w")
        self._csv = csv.writer(self._csv_file)
        self._csv.writerow(FRAME_COLUMNS)

    def _close_segment(self) -> None:
        files, self._tlog, self._csv_file = (self._tlog, self._csv_file), None, None
        for f in files:
            if f is not None:
                f.close()

    # ------------------------------------------------------------------ the end

    def close(self, drain: bool = True) -> None:
        """Write what is queued (at most a few seconds; nothing with ``drain`` False), close the files,
        write meta.json. Never raises: a disk error here is logged."""
        self._closing.set()
        self._thread.join(_CLOSE_DRAIN_S if drain else 0.0)
        try:
            if self._thread.is_alive():
                log.warning("recording: the disk did not keep up; %s closed with items still queued", self.path)
            else:
                self._close_segment()
            self._write_meta()
        except OSError as e:
            log.warning("recording: closing %s: %s", self.path, e.strerror or e)
        log.info(
            "recording closed: %s (%d frames, %d messages, %.1f MB)",
            self.path,
            self.counters["frames"],
            self.counters["messages"],
            self.counters["bytes"] / _MB,
        )

    def _write_meta(self) -> None:
        meta = {
            "format": "mavvo-recording",
            "version": FORMAT_VERSION,
            "mavvo": __version__,
            "unix_minus_host_us": self._unix_minus_host_us,
            "mavvo_component_id": COMPONENT_ID,
            "frames_format": self.options.frames,
            "complete": self._closing.is_set() and not self.stopped_reason,
            "stopped_reason": self.stopped_reason,
            "counters": dict(self.counters),
        }
        _write_private(self.path / "meta.json", (json.dumps(meta, indent=2) + "\n").encode("utf-8"))


def _open_private(path: Path, mode: Literal["wb", "w"]) -> IO[Any]:
    """``path`` opened for writing, created 0600 (owner only)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    if mode == "wb":
        return os.fdopen(fd, "wb")
    return os.fdopen(fd, "w", newline="", encoding="utf-8")


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path``, created 0600."""
    with _open_private(path, "wb") as f:
        f.write(data)
