"""The files a replay leaves: trajectory (TUM), quality timeline (CSV and plot), summary (JSON), and,
against a reference (ground truth or the flight controller's own position), the errors and their plot.

Files in the output folder:
- ``estimate.tum``: what the flight controller received (VISION_POSITION_ESTIMATE at ``usec``);
- ``quality.csv`` and ``quality.png``: per estimate: state, quality, tracks, inliers, parallax, scale source,
  the gap between the ATTITUDE samples around the frame and the roll/pitch uncertainty it left;
- ``reference.tum`` and ``evaluation.png``: the reference at the estimates' times and the comparison;
- ``summary.json``: counts, speed, the evaluation, problems found in the input, notes (e.g. the time
  offset used and its confidence).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from mavvo.evaluation.metrics import Evaluation, PoseSeries, evaluate
from mavvo.evaluation.report import plot_evaluation, write_tum
from mavvo.offline.driver import QualityRow, ReplayInput, ReplayResult
from mavvo.types import StateReason

__all__ = ["reference_at", "write_replay_report"]

_STATE_COLOURS = {"tracking": "#d9f0d3", "degraded": "#fde0b2", "initialising": "#e0e0e0", "failed": "#f4c7c3"}


def reference_at(ref: PoseSeries, times_s: np.ndarray) -> tuple[np.ndarray, PoseSeries]:
    """The reference at ``times_s`` inside its time span: positions interpolated linearly, orientations
    from the nearest sample. Returns (indices of ``times_s`` kept, the series)."""
    t = ref.timestamps_s
    keep = np.flatnonzero((times_s >= t[0]) & (times_s <= t[-1])) if len(t) >= 2 else np.zeros(0, int)
    ts = times_s[keep]
    p = (
        np.column_stack([np.interp(ts, t, ref.positions_xyz_m[:, k]) for k in range(3)])
        if len(ts)
        else np.zeros((0, 3))
    )
    j = np.clip(np.searchsorted(t, ts), 1, max(len(t) - 1, 1))
    j = np.where(np.abs(ts - t[j - 1]) <= np.abs(t[j] - ts), j - 1, j) if len(ts) else j
    q = ref.orientations_quat_wxyz[j] if len(ts) else np.zeros((0, 4))
    return keep, PoseSeries(ts, p, q)


def _subset(s: PoseSeries, idx: np.ndarray) -> PoseSeries:
    return PoseSeries(s.timestamps_s[idx], s.positions_xyz_m[idx], s.orientations_quat_wxyz[idx])


def _finite(x: Any) -> Any:
    """JSON has no NaN: None instead (recursively)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def write_quality(out: Path, rows: list[QualityRow], title: str) -> None:
    """quality.csv and quality.png."""
    fields = [f.name for f in dataclasses.fields(QualityRow)]
    with (out / "quality.csv").open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(fields)
        for r in rows:
            w.writerow([getattr(r, k) for k in fields])
    if not rows:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = rows[0].t_exposure_s
    t = np.array([r.t_exposure_s - t0 for r in rows])
    fig, (ax, ax_att) = plt.subplots(2, 1, figsize=(11, 4.8), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    start = 0
    for i in range(1, len(rows) + 1):  # shade each run of one state
        if i == len(rows) or rows[i].state != rows[start].state:
            ax.axvspan(t[start], t[min(i, len(rows) - 1)], color=_STATE_COLOURS.get(rows[start].state, "#ffffff"), lw=0)
            start = i
    ax.plot(t, [r.quality for r in rows], color="tab:blue", lw=1.0, label="quality [%]")
    ax.set_ylim(-5, 105)
    sigma = [r.attitude_sigma_deg for r in rows]
    ax_att.plot(t, sigma, color="tab:purple", lw=1.0)
    ax_att.set_ylim(
        0.0, 1.3 * float(np.nanmax(sigma)) if np.isfinite(sigma).any() else 1.0
    )  # from zero: a flat line reads flat
    ax_att.set_ylabel("roll/pitch\nsigma [deg]", fontsize=8)
    ax_att.set_xlabel("time [s]")
    gaps = [r.attitude_gap_s for r in rows]
    ax_att.set_title(
        f"attitude pairing: samples up to {max(gaps):.2f} s apart (median {float(np.median(gaps)):.3f} s)", fontsize=8
    )
    ax.set_ylabel("quality [%]")
    ax2 = ax.twinx()
    ax2.plot(t, [r.inliers for r in rows], color="tab:green", lw=0.8, alpha=0.8, label="inliers")
    ax2.set_ylabel("inliers")
    resets = [t[i] for i in range(1, len(rows)) if rows[i].reset_counter != rows[i - 1].reset_counter]
    for x in resets:
        ax.axvline(x, color="tab:red", lw=0.8, ls="--")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in _STATE_COLOURS.values()]
    ax.legend(
        handles + ax.get_lines()[:1] + ax2.get_lines(),
        list(_STATE_COLOURS) + ["quality", "inliers"],
        loc="lower left",
        fontsize=7,
        ncol=6,
    )
    ax.set_title(f"{title}: quality timeline ({len(rows)} estimates, {len(resets)} resets: dashed)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "quality.png", dpi=90)
    plt.close(fig)


def _plot_path(path: Path, est: PoseSeries, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 5))
    ax.plot(est.positions_xyz_m[:, 1], est.positions_xyz_m[:, 0], "-", color="tab:orange", lw=1.2)
    ax.plot(est.positions_xyz_m[0, 1], est.positions_xyz_m[0, 0], "go")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.set_title(f"{title}: estimated path (no reference)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def attitude_pairing(rows: list[QualityRow]) -> dict[str, Any] | None:
    """How far apart the ATTITUDE samples around the frames were and the roll/pitch uncertainty that
    left; ``degraded``: estimates degraded for it (``attitude_interpolated``)."""
    if not rows:
        return None
    gap = np.array([r.attitude_gap_s for r in rows])
    sigma = np.array([r.attitude_sigma_deg for r in rows])
    sigma = sigma[np.isfinite(sigma)]
    return {
        "gap_s_median": round(float(np.median(gap)), 4),
        "gap_s_max": round(float(gap.max()), 4),
        "sigma_deg_median": round(float(np.median(sigma)), 3) if len(sigma) else None,
        "sigma_deg_p95": round(float(np.percentile(sigma, 95)), 3) if len(sigma) else None,
        "degraded": sum(1 for r in rows if r.reason == StateReason.ATTITUDE_INTERPOLATED),
    }


def write_replay_report(out_dir: str | Path, inp: ReplayInput, res: ReplayResult) -> dict[str, Any]:
    """Write the files (see the module docstring) and return the summary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    title = Path(inp.source).name or inp.kind
    est = res.estimates
    files = ["summary.json", "quality.csv"]
    if len(est):
        write_tum(out / "estimate.tum", est)
        files.append("estimate.tum")
    write_quality(out, res.quality, title)
    if res.quality:
        files.append("quality.png")
    evaluation: Evaluation | None = None
    if inp.reference is not None and len(est) >= 3:
        keep, ref = reference_at(inp.reference, est.timestamps_s)
        if len(keep) >= 3:
            matched = _subset(est, keep)
            evaluation, aligned = evaluate(matched, ref)
            write_tum(out / "reference.tum", ref)
            # As sent, where the reference is in the flight controller's frame (a data set's truth has its own).
            as_sent = None if inp.kind == "euroc" else matched
            plot_evaluation(
                out / "evaluation.png",
                aligned,
                ref,
                evaluation,
                title=f"{title} vs {inp.reference_label}",
                as_sent=as_sent,
            )
            files += ["reference.tum", "evaluation.png"]
    elif len(est) >= 2:
        _plot_path(out / "trajectory.png", est, title)
        files.append("trajectory.png")
    identical = None
    if inp.expected_vpe is not None:
        identical = res.vpe_payloads == inp.expected_vpe
    c = res.daemon.counters
    summary = {
        "source": inp.source,
        "kind": inp.kind,
        "frames": len(inp.frames),
        "frames_replayed": res.frames_replayed,
        "paired": c.get("paired", 0),
        "messages": len(inp.messages),
        "messages_lost": res.messages_lost,
        "estimates_received": len(est),
        "resets": sum(1 for a, b in zip(res.quality, res.quality[1:]) if a.reset_counter != b.reset_counter),
        "duration_s": round(res.duration_s, 3),
        "wall_s": round(res.wall_s, 3),
        "speed_x_real_time": round(res.duration_s / res.wall_s, 2) if res.wall_s > 0 else None,
        # The odometry alone (the worker thread's CPU in tracking, pose and filter), not the replay's
        # driver, link and sockets, which a batch row's CPU per frame counts too.
        "odometry_cpu_ms_per_frame": None
        if res.daemon.odometry_cpu_ms_per_frame is None
        else round(res.daemon.odometry_cpu_ms_per_frame, 2),
        "final_state": res.daemon.state,
        "complete": not res.stopped,
        "identical_to_recording": identical,
        "recorded_estimates": None if inp.expected_vpe is None else len(inp.expected_vpe),
        "reference": inp.reference_label or None,
        "evaluation": None if evaluation is None else evaluation.to_dict(),
        "attitude_pairing": attitude_pairing(res.quality),
        "notes": inp.notes,
        "problems": inp.problems,
        "warnings": inp.warnings,
        "statustexts": res.statustexts,
        "counters": c,
        "files": sorted(files),
    }
    summary = _finite(summary)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return summary
