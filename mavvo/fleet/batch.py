"""``mavvo batch``'s core: many logged flights under one or several settings, each pair one replay.

Flights are recordings, EuRoC folders or flight-controller logs (a log needs its video and camera
settings: give it through a manifest). Settings are ``--config`` files (the keys given replace the
flight's own, as ``mavvo replay --config`` does) and a grid of values per key whose cross product is
expanded. Each (flight, settings) pair is a :class:`BatchTask` with a stable key: its outcome is one row
of ``results.jsonl`` in the output folder, written as it comes, so a batch that stopped resumes where it
was. The tables (``results.csv``/``.json``, ``summary.csv``/``.json``) and ``batch.png`` are made from
that journal.

Row metrics (metres; None where there is nothing to measure): ``ate_rmse_m`` (SE(3)-aligned, against the
flight's reference), ``end_error_m`` and ``end_error_horizontal_m`` (the last estimate against the
reference at its time, no alignment: what the autopilot feels), ``resets``, ``failed_frames`` (frames
whose estimate was not sent because vision had failed), ``coverage`` (estimates per replayed frame),
``cpu_ms_per_frame`` (the worker process's CPU time over the replay per frame: driver, link and sockets
included), ``odometry_cpu_ms_per_frame`` (the odometry alone: the service's worker thread in tracking,
pose and filter).
"""

from __future__ import annotations

import csv
import glob
import hashlib
import itertools
import json
import logging
import math
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mavvo.errors import ConfigError
from mavvo.offline.recording import merge
from mavvo.service.settings import parse_config
from mavvo.service.yaml_loader import load_yaml

__all__ = [
    "Flight",
    "Settings",
    "BatchTask",
    "METRICS",
    "expand_flights",
    "expand_settings",
    "make_tasks",
    "replay_task",
    "Journal",
    "summarise",
    "best_settings",
    "write_tables",
]

JOURNAL = "results.jsonl"
# Metric -> whether larger is better.
METRICS = {
    "end_error_m": False,
    "end_error_horizontal_m": False,
    "ate_rmse_m": False,
    "resets": False,
    "failed_frames": False,
    "coverage": True,
    "cpu_ms_per_frame": False,
    "odometry_cpu_ms_per_frame": False,
}
ROW_FIELDS = (
    "key",
    "flight",
    "settings",
    "status",
    "reason",
    "frames",
    "frames_replayed",
    "estimates",
    *METRICS,
    "path_m",
    "wall_s",
    "estimates_sha256",
)


@dataclass(frozen=True)
class Flight:
    """One logged flight: ``source`` (a recording or EuRoC folder, or a log), and for a log its
    ``video``, ``config`` (camera and mounting), ``fps``, ``offset_s``; ``ground_truth`` a reference."""

    source: str
    video: str | None = None
    config: str | None = None
    fps: float | None = None
    offset_s: float | None = None
    ground_truth: str | None = None


@dataclass(frozen=True)
class Settings:
    """A named set of settings that replace a flight's own (nested, as in a config file)."""

    name: str
    overrides: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class BatchTask:
    flight: Flight
    settings: Settings

    @property
    def key(self) -> str:
        """Stable over runs: the flight and the settings' values, hashed."""
        text = json.dumps({"flight": asdict(self.flight), "settings": self.settings.overrides}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:16]


# ------------------------------------------------------------------ flights


def _manifest(path: Path) -> list[Flight]:
    """A YAML list of flights: each a path, or a mapping with ``source`` and the :class:`Flight` keys.
    Relative paths are relative to the manifest."""
    data = load_yaml(path) if path.suffix in (".yaml", ".yml") else None
    entries = data.get("flights") if isinstance(data, dict) else None
    if not isinstance(entries, list):
        raise ConfigError(f"{path}: expected a manifest: 'flights:' and a list of paths or {{source: PATH, ...}}")
    known = set(Flight.__dataclass_fields__)
    flights = []
    for i, entry in enumerate(entries):
        item = {"source": entry} if isinstance(entry, str) else entry
        if not isinstance(item, dict) or "source" not in item:
            raise ConfigError(f"{path}: flights[{i}]: expected a path or a mapping with 'source', got {entry!r}")
        unknown = sorted(set(item) - known)
        if unknown:
            raise ConfigError(f"{path}: flights[{i}]: unknown key {unknown[0]!r} (expected {', '.join(sorted(known))})")
        for k in ("source", "video", "config", "ground_truth"):
            if item.get(k) is not None:
                item[k] = str((path.parent / str(item[k])).resolve())
        flights.append(Flight(**item))
    return flights


def expand_flights(specs: Sequence[str]) -> list[Flight]:
    """Paths, globs (``flights/*``) and manifests (``.yaml`` with ``flights:``), in the order given,
    each flight once. ConfigError naming a spec that matches nothing."""
    out: list[Flight] = []
    for spec in specs:
        p = Path(spec)
        if p.is_file() and p.suffix in (".yaml", ".yml"):
            out += _manifest(p)
            continue
        matches = sorted(glob.glob(spec)) if glob.has_magic(spec) else ([spec] if p.exists() else [])
        if not matches:
            raise ConfigError(f"{spec}: no such flight (a recording or EuRoC folder, a log, a glob or a manifest)")
        out += [Flight(str(Path(m).resolve())) for m in matches]
    seen: set[Flight] = set()
    return [f for f in out if not (f in seen or seen.add(f))]


# ------------------------------------------------------------------ settings


def _nested(dotted: str, value: Any) -> dict[str, Any]:
    d: dict[str, Any] = value
    for part in reversed(dotted.split(".")):
        d = {part: d}
    return d


def _value_text(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def expand_settings(configs: Sequence[Path], grid: Path | None) -> list[Settings]:
    """``configs`` (each a settings set named after its file; none: the flights' own), each crossed
    with ``grid``'s cross product. The grid file maps dotted keys to lists of values::

        odometry.heading_correction_time_s: [5, 10, 20]
        odometry.frontend.fast_threshold: [10, 20]

    Every set is checked as a configuration is (unknown keys, values out of bounds) before any runs."""
    bases = [Settings(p.stem, load_yaml(p)) for p in configs] or [Settings("own", {})]
    combos: list[tuple[str, dict[str, Any]]] = [("", {})]
    if grid is not None:
        data = load_yaml(grid)
        if not data:
            raise ConfigError(
                f"{grid}: expected dotted keys with lists of values, e.g. 'odometry.frontend.fast_threshold: [10, 20]'"
            )
        axes = []
        for key, values in data.items():
            if not isinstance(values, list) or not values:
                raise ConfigError(f"{grid}: {key}: expected a non-empty list of values, got {values!r}")
            axes.append([(key, v) for v in values])
        combos = []
        for choice in itertools.product(*axes):
            over: dict[str, Any] = {}
            for key, v in choice:
                over = merge(over, _nested(key, v))
            combos.append((",".join(f"{k}={_value_text(v)}" for k, v in choice), over))
    out = []
    for base in bases:
        for name, over in combos:
            s = Settings(
                base.name if not name else (name if base.name == "own" else f"{base.name}:{name}"),
                merge(base.overrides, over),
            )
            parse_config(s.overrides, f"settings {s.name}")  # ConfigError naming the key
            out.append(s)
    return out


def make_tasks(flights: Iterable[Flight], settings: Iterable[Settings]) -> list[BatchTask]:
    """Every flight under every settings set, settings-major (a sweep fills in per setting)."""
    return [BatchTask(f, s) for s in settings for f in flights]


# ------------------------------------------------------------------ one task, on a worker


def replay_task(task: BatchTask) -> dict[str, Any]:
    """Replay one flight under one settings set (on a worker); the row's metrics. Raises on a flight
    that cannot be read (the engine makes that a failed row)."""
    import tempfile
    import time

    import numpy as np

    from mavvo.offline.driver import replay
    from mavvo.offline.report import reference_at
    from mavvo.offline.sources import open_replay_source

    # The service's own warnings about one flight ("no frame paired ...") would interleave from every
    # worker; the row says how the flight went.
    logging.getLogger("mavvo").setLevel(logging.ERROR)
    f, s = task.flight, task.settings
    with tempfile.TemporaryDirectory(prefix="mavvo-batch-") as tmp:
        config = None
        if f.config is not None or s.overrides:
            config = Path(tmp) / "settings.yaml"
            config.write_text(yaml.safe_dump(merge(load_yaml(f.config) if f.config else {}, s.overrides)))
        inp = open_replay_source(
            Path(f.source),
            config=config,
            video=None if f.video is None else Path(f.video),
            fps=f.fps,
            offset_s=f.offset_s,
            ground_truth=None if f.ground_truth is None else Path(f.ground_truth),
        )
    if inp.problems:
        raise ConfigError("; ".join(inp.problems))
    if not inp.frames or not inp.messages:
        raise ConfigError(f"{f.source}: nothing to replay ({len(inp.frames)} frames, {len(inp.messages)} messages)")
    cpu0, wall0 = time.process_time(), time.perf_counter()
    res = replay(inp)
    cpu_s, wall_s = time.process_time() - cpu0, time.perf_counter() - wall0
    est = res.estimates
    row: dict[str, Any] = {
        "frames": len(inp.frames),
        "frames_replayed": res.frames_replayed,
        "estimates": len(est),
        "resets": sum(1 for a, b in zip(res.quality, res.quality[1:]) if a.reset_counter != b.reset_counter),
        "failed_frames": int(res.daemon.counters.get("not_sent_failed", 0)),
        "coverage": len(est) / res.frames_replayed if res.frames_replayed else 0.0,
        "cpu_ms_per_frame": 1e3 * cpu_s / max(res.frames_replayed, 1),
        "odometry_cpu_ms_per_frame": res.daemon.odometry_cpu_ms_per_frame,
        "wall_s": wall_s,
        "estimates_sha256": hashlib.sha256(b"".join(res.vpe_payloads)).hexdigest(),
        "ate_rmse_m": None,
        "end_error_m": None,
        "end_error_horizontal_m": None,
        "path_m": None,
    }
    if inp.reference is not None and len(est) >= 3:
        from mavvo.evaluation.metrics import PoseSeries, evaluate

        keep, ref = reference_at(inp.reference, est.timestamps_s)
        if len(keep) >= 3:
            matched = PoseSeries(est.timestamps_s[keep], est.positions_xyz_m[keep], est.orientations_quat_wxyz[keep])
            ev, _ = evaluate(matched, ref)
            d = matched.positions_xyz_m[-1] - ref.positions_xyz_m[-1]
            row.update(
                ate_rmse_m=ev.ate_se3_m["rmse"],
                end_error_m=float(np.linalg.norm(d)),
                end_error_horizontal_m=float(np.linalg.norm(d[:2])),
                path_m=ev.path_length_m,
            )
    return row


# ------------------------------------------------------------------ results


class Journal:
    """``results.jsonl`` in the output folder: one row per finished task, appended as it comes."""

    def __init__(self, out_dir: Path) -> None:
        self.path = out_dir / JOURNAL
        out_dir.mkdir(parents=True, exist_ok=True)

    def rows(self) -> list[dict[str, Any]]:
        """The rows so far (the last one of a key wins; a line cut short by a crash is skipped)."""
        if not self.path.exists():
            return []
        rows: dict[str, dict[str, Any]] = {}
        for line in self.path.read_text(encoding="utf-8").splitlines():
            try:
                row = json.loads(line)
            except ValueError:
                continue
            if isinstance(row, dict) and "key" in row:
                rows[row["key"]] = row
        return list(rows.values())

    def append(self, row: dict[str, Any]) -> None:
        with self.path.open("a", encoding="utf-8") as f:
            f.write(json.dumps(row) + "\n")


def task_row(task: BatchTask, result: dict[str, Any] | None, error: str | None) -> dict[str, Any]:
    """The journal's row for one outcome."""
    row = {k: None for k in ROW_FIELDS}
    row.update(key=task.key, flight=task.flight.source, settings=task.settings.name)
    if error is None and result is not None:
        row.update(result, status="ok", reason="")
    else:
        row.update(status="failed", reason=error or "no result")
    return row


def _number(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def summarise(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per settings set: flights ok and failed, and each metric's median and worst over its flights."""
    out = []
    for name in dict.fromkeys(r["settings"] for r in rows):
        mine = [r for r in rows if r["settings"] == name]
        ok = [r for r in mine if r["status"] == "ok"]
        s: dict[str, Any] = {"settings": name, "flights_ok": len(ok), "flights_failed": len(mine) - len(ok)}
        for metric, larger_better in METRICS.items():
            values = [v for v in (_number(r.get(metric)) for r in ok) if v is not None]
            s[f"{metric}_median"] = statistics.median(values) if values else None
            s[f"{metric}_worst"] = (min(values) if larger_better else max(values)) if values else None
        out.append(s)
    return out


def best_settings(summary: Sequence[dict[str, Any]], metric: str) -> dict[str, Any] | None:
    """The settings set with the best median of ``metric`` (ties: the better worst; failures count
    against: a set that failed on a flight ranks after every set that did not)."""
    if metric not in METRICS:
        raise ConfigError(f"--metric: expected one of {', '.join(METRICS)}, got {metric!r}")
    sign = -1.0 if METRICS[metric] else 1.0
    ranked = [s for s in summary if s[f"{metric}_median"] is not None]
    if not ranked:
        return None
    return min(ranked, key=lambda s: (s["flights_failed"], sign * s[f"{metric}_median"], sign * s[f"{metric}_worst"]))


def write_tables(out_dir: Path, rows: Sequence[dict[str, Any]], metric: str) -> dict[str, Any]:
    """results.csv/.json, summary.csv/.json (with the best settings) and batch.png; returns the summary."""
    rows = sorted(rows, key=lambda r: (r["settings"], r["flight"]))
    (out_dir / "results.json").write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
    _csv(out_dir / "results.csv", rows, ROW_FIELDS)
    per = summarise(rows)
    best = best_settings(per, metric)
    _csv(out_dir / "summary.csv", per, list(per[0]) if per else ["settings"])
    summary = {"metric": metric, "best": best, "settings": per}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
    if any(r["status"] == "ok" for r in rows):
        _plot(out_dir / "batch.png", rows, metric)
    return summary


def _csv(path: Path, rows: Sequence[dict[str, Any]], fields: Sequence[str]) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=list(fields), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def _plot(path: Path, rows: Sequence[dict[str, Any]], metric: str) -> None:
    """``metric`` per settings set: one point per flight, the median as a bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["settings"] for r in rows))
    flights = list(dict.fromkeys(r["flight"] for r in rows))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.6 * len(names) + 3), 4.5))
    for flight in flights:
        xs, ys = [], []
        for i, name in enumerate(names):
            v = next(
                (
                    _number(r.get(metric))
                    for r in rows
                    if r["settings"] == name and r["flight"] == flight and r["status"] == "ok"
                ),
                None,
            )
            if v is not None:
                xs.append(i)
                ys.append(v)
        ax.plot(xs, ys, "o-", alpha=0.6, lw=0.8, label=Path(flight).name if len(flights) <= 10 else None)
    for i, name in enumerate(names):
        values = [
            v
            for r in rows
            if r["settings"] == name and r["status"] == "ok" and (v := _number(r.get(metric))) is not None
        ]
        if values:
            ax.hlines(statistics.median(values), i - 0.3, i + 0.3, colors="k", lw=2)
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(metric)
    ax.set_title(f"{metric} per settings (points: flights; bars: medians)")
    if len(flights) <= 10:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
