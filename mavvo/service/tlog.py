"""The .tlog file format (pymavlink's, what ground stations write), without decoding the messages.

A .tlog is a sequence of records: a big-endian uint64 timestamp in microseconds (Unix time by
convention) and one MAVLink frame as it went over the wire. Frames are split by their headers:

- MAVLink 2: ``0xFD``, payload length, incompatibility flags (bit 0: signed, 13 more bytes), then
  7 more header bytes, the payload and a 2-byte checksum;
- MAVLink 1: ``0xFE``, payload length, 4 more header bytes, the payload and a 2-byte checksum.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO, Iterator

from mavvo.errors import ConfigError

__all__ = ["write_record", "frame_length", "read_tlog", "source_component", "message_id", "payload"]

_STAMP = struct.Struct(">Q")


def write_record(f: BinaryIO, t_us: int, frame: bytes) -> int:
    """Append one record; returns the bytes written."""
    f.write(_STAMP.pack(t_us))
    f.write(frame)
    return _STAMP.size + len(frame)


def frame_length(head: bytes) -> int | None:
    """The length of the MAVLink frame that starts ``head`` (at least 3 bytes), or None when ``head``
    does not start a frame."""
    if len(head) < 3:
        return None
    if head[0] == 0xFD:
        return 12 + head[1] + (13 if head[2] & 0x01 else 0)
    if head[0] == 0xFE:
        return 8 + head[1]
    return None


def read_tlog(path: str | Path) -> Iterator[tuple[int, bytes]]:
    """(timestamp_us, frame) for each record of ``path``; ConfigError naming the file and the byte
    offset when the file cannot be read, is not a .tlog, or ends inside a record (the records before
    have been yielded by then)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read: {e.strerror or e}") from e
    i = 0
    while i < len(data):
        if len(data) - i < _STAMP.size + 3:
            raise ConfigError(f"{p}: truncated: {len(data) - i} stray bytes at offset {i} (the log was cut off)")
        (t_us,) = _STAMP.unpack_from(data, i)
        n = frame_length(data[i + 8 : i + 11])
        if n is None:
            raise ConfigError(f"{p}: not a .tlog: no MAVLink frame at offset {i + 8} (byte 0x{data[i + 8]:02x})")
        if i + 8 + n > len(data):
            raise ConfigError(
                f"{p}: truncated: the record at offset {i} needs {n} bytes, {len(data) - i - 8} left (the log was cut off)"
            )
        yield t_us, data[i + 8 : i + 8 + n]
        i += 8 + n


def source_component(frame: bytes) -> int:
    """The sender's component id of a MAVLink 1 or 2 frame."""
    return frame[6] if frame[0] == 0xFD else frame[4]


def message_id(frame: bytes) -> int:
    """The message id of a MAVLink 1 or 2 frame."""
    return frame[7] | frame[8] << 8 | frame[9] << 16 if frame[0] == 0xFD else frame[5]


def payload(frame: bytes) -> bytes:
    """The payload of a MAVLink 1 or 2 frame as sent (MAVLink 2 trims trailing zero bytes): what two
    equal messages share whatever their sequence numbers and signatures."""
    start = 10 if frame[0] == 0xFD else 6
    return frame[start : start + frame[1]]
