"""Reading a mavvo recording (:mod:`mavvo.service.recorder`) into a replay input.

Problems a replay can live with (a recording stopped early, frames or messages dropped in flight, a
missing frame file) go into ``ReplayInput.problems``: the replay runs what is there, the report says
what was wrong and the exit is non-zero. A folder that is not a recording, or unreadable metadata, is
a ConfigError at once.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from mavvo.errors import ConfigError
from mavvo.evaluation.report import GROUND_TRUTH_FILE, read_tum
from mavvo.offline.driver import ReplayFrame, ReplayInput, image_loader
from mavvo.service.recorder import FORMAT_VERSION, FRAME_COLUMNS
from mavvo.service.settings import parse_config
from mavvo.service.tlog import message_id, payload, read_tlog, source_component
from mavvo.service.yaml_loader import load_yaml

__all__ = ["is_recording", "load_recording", "merge"]


def is_recording(path: Path) -> bool:
    return (path / "meta.json").is_file() and (path / "config.yaml").is_file()


def merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``base`` with the keys of ``override`` replacing its own, section by section."""
    out = dict(base)
    for k, v in override.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _indexed_frames(p: Path, index: Path, problems: list[str]) -> list[ReplayFrame]:
    """The frames one index (frames-*.csv) of recording ``p`` lists, up to a malformed row or a missing
    file (named in ``problems``)."""
    frames: list[ReplayFrame] = []
    with index.open(newline="", encoding="utf-8") as f:
        rows = csv.reader(f)
        header = next(rows, None)
        if header is None or tuple(header) != FRAME_COLUMNS:
            problems.append(f"{index}: expected the header {','.join(FRAME_COLUMNS)}, got {header}")
            return frames
        for n, row in enumerate(rows, 2):
            try:
                rec = dict(zip(FRAME_COLUMNS, row, strict=True))
                t_paired = float(rec["t_paired_s"])
                fr = ReplayFrame(
                    int(rec["seq"]),
                    float(rec["t_exposure_s"]),
                    t_paired,
                    int(rec["fc_version"]),
                    image_loader(p / "frames" / rec["file"]),
                )
            except ValueError as e:
                problems.append(f"{index}:{n}: malformed row ({e}); stopped reading this index")
                break
            if not (p / "frames" / rec["file"]).is_file():
                problems.append(
                    f"{index}:{n}: frame file frames/{rec['file']} is missing; the frames after it are not replayed"
                )
                break
            frames.append(fr)
    return frames


def load_recording(path: str | Path, overrides: dict[str, Any] | None = None) -> ReplayInput:
    """The recording in folder ``path``; ``overrides``: settings replacing the recorded ones (tuning)."""
    p = Path(path)
    if not is_recording(p):
        found = sorted(q.name for q in p.iterdir() if q.is_dir() and is_recording(q)) if p.is_dir() else []
        hint = f"; it holds recordings: {', '.join(found)}" if found else ""
        raise ConfigError(f"{p}: expected a mavvo recording (a folder with meta.json and config.yaml){hint}")
    try:
        meta = json.loads((p / "meta.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise ConfigError(f"{p / 'meta.json'}: cannot read: {e}") from e
    if meta.get("format") != "mavvo-recording" or meta.get("version") != FORMAT_VERSION:
        raise ConfigError(
            f"{p / 'meta.json'}: expected format mavvo-recording version {FORMAT_VERSION}, got {meta.get('format')!r} version {meta.get('version')!r}"
        )
    config_data = load_yaml(p / "config.yaml")
    config = parse_config(merge(config_data, overrides or {}), str(p / "config.yaml"))
    problems: list[str] = []
    counters = meta.get("counters", {})
    if not meta.get("complete", False):
        problems.append(
            f"{p}: the recording was not closed cleanly ({meta.get('stopped_reason') or 'the service did not stop normally'}): it ends early"
        )
    for key in ("dropped_frames", "dropped_messages"):
        if counters.get(key):
            problems.append(
                f"{p}: {counters[key]} {key.split('_')[1]} were dropped while recording: the replay differs from the flight"
            )

    unix_minus_host_us = int(meta["unix_minus_host_us"])
    mavvo_component = int(meta.get("mavvo_component_id", 197))
    inbound: list[tuple[int, bytes]] = []
    vpe: list[bytes] = []
    for tlog in sorted(p.glob("mavlink-*.tlog")):
        try:
            for t_us, frame in read_tlog(tlog):
                if source_component(frame) == mavvo_component:
                    if message_id(frame) == 102:  # VISION_POSITION_ESTIMATE
                        vpe.append(payload(frame))
                else:
                    inbound.append((t_us - unix_minus_host_us, frame))
        except ConfigError as e:
            problems.append(str(e))
    if not inbound:
        problems.append(f"{p}: no message from the flight controller in the recording")

    frames = [fr for index in sorted(p.glob("frames-*.csv")) for fr in _indexed_frames(p, index, problems)]
    if not frames:
        problems.append(f"{p}: no frames in the recording")
    reference, label = None, ""
    gt = p / GROUND_TRUTH_FILE
    if gt.is_file():
        reference, label = read_tum(gt), "ground truth"
    return ReplayInput(
        "recording",
        str(p),
        config,
        inbound,
        frames,
        reference,
        label,
        vpe,
        notes={"frames_format": meta.get("frames_format"), "mavvo_recorded": meta.get("mavvo")},
        problems=problems,
    )
