"""Writers of small flight-controller logs for the tests: a PX4 ULog through pyulog and an ArduPilot
dataflash ``.bin`` through pymavlink's format table. Test tooling, not part of the package: the ULog
writer sets pyulog's private attributes (pyulog writes only logs it has read)."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from mavvo.service.mavlink import dfreader


def write_ulog(path: str | Path, topics: dict[str, tuple[list[tuple[str, str]], dict[str, Any]]]) -> Path:
    """A PX4 ULog written by pyulog: ``topics`` maps a topic to its fields ``[(type, name)]`` (ULog
    types: ``uint64_t``, ``float``, ``float[4]``, ...; ``timestamp`` first, microseconds) and its
    columns ``{name: values}`` (an array field as an (N, k) array). Test logs."""
    from pyulog import ULog

    log = ULog(None)
    formats = {
        name: ULog.MessageFormat((name + ":" + "".join(f"{t} {n};" for t, n in fields)).encode(), None)
        for name, (fields, _) in topics.items()
    }
    log._message_formats = formats
    data = []
    for msg_id, (name, (_, cols)) in enumerate(topics.items()):
        added = ULog._MessageAddLogged(struct.pack("<BH", 0, msg_id) + name.encode(), None, formats)
        rec = np.zeros(len(cols["timestamp"]), dtype=added.dtype)
        for f in added.field_data:
            base, _, index = f.field_name.partition("[")
            rec[f.field_name] = np.asarray(cols[base])[:, int(index[:-1])] if index else cols[base]
        added.buffer = bytearray(rec.tobytes())
        data.append(ULog.Data(added))
    log._data_list = data
    log._start_timestamp = int(min(c["timestamp"][0] for _, c in topics.values()))
    log._last_timestamp = int(max(c["timestamp"][-1] for _, c in topics.values()))
    log.write_ulog(str(path))
    return Path(path)


# ---------------------------------------------------------------------- writing dataflash (test logs)

_FMT_ID = 128
_FMT_BODY = "BB4s16s64s"


def write_dataflash(
    path: str | Path, formats: dict[str, tuple[int, str, str]], records: Iterable[tuple[str, tuple[Any, ...]]]
) -> Path:
    """A dataflash .bin: ``formats`` maps a name to (id, format characters, comma-separated columns),
    ``records`` are (name, values) in order. Formats use pymavlink's DFReader type characters."""
    FORMAT_TO_STRUCT = dfreader().FORMAT_TO_STRUCT

    p = Path(path)
    structs = {}
    scales = {}
    with p.open("wb") as f:
        fmt_struct = struct.Struct("<" + _FMT_BODY)
        f.write(
            bytes([0xA3, 0x95, _FMT_ID])
            + fmt_struct.pack(_FMT_ID, 3 + fmt_struct.size, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")
        )
        for name, (msg_id, chars, columns) in formats.items():
            st = struct.Struct("<" + "".join(FORMAT_TO_STRUCT[c][0] for c in chars))
            structs[name], scales[name] = (msg_id, st), [FORMAT_TO_STRUCT[c][1] for c in chars]
            f.write(
                bytes([0xA3, 0x95, _FMT_ID])
                + fmt_struct.pack(msg_id, 3 + st.size, name.encode(), chars.encode(), columns.encode())
            )
        for name, values in records:
            msg_id, st = structs[name]
            packed = [v if s is None else int(round(v / s)) for v, s in zip(values, scales[name])]
            packed = [v.encode() if isinstance(v, str) else v for v in packed]
            f.write(bytes([0xA3, 0x95, msg_id]) + st.pack(*packed))
    return p
