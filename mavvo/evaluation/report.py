"""Files of an evaluation: trajectories in TUM format, a JSON summary and a PNG plot.

TUM format (read by evo and most SLAM tools): one pose per line, ``timestamp tx ty tz qx qy qz qw``,
seconds, metres, the quaternion giving R_world_body; ``#`` starts a comment.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterable, Literal

import numpy as np

from mavvo.errors import ConfigError
from mavvo.evaluation.metrics import Evaluation, PoseSeries, evaluate
from mavvo.geometry.frames import R_from_euler321

GROUND_TRUTH_FILE = "ground_truth.tum"  # a simulated flight's truth, written beside its recording


def write_tum(path: str | Path, series: PoseSeries) -> Path:
    """Write ``series`` as a TUM trajectory file."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    q = series.orientations_quat_wxyz
    rows = np.column_stack([series.timestamps_s, series.positions_xyz_m, q[:, 1:], q[:, :1]])
    np.savetxt(p, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw", comments="# ")
    return p


def read_tum(path: str | Path) -> PoseSeries:
    """Read a TUM trajectory file; ConfigError naming the file and line on malformed input."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read: {e.strerror or e}") from e
    rows = []
    for n, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            vals = []
        if len(vals) != 8 or not all(math.isfinite(v) for v in vals):
            raise ConfigError(f"{p}:{n}: expected 8 finite numbers 'timestamp tx ty tz qx qy qz qw', got {line!r}")
        rows.append(vals)
    a = np.array(rows, dtype=float).reshape(-1, 8)
    order = np.argsort(a[:, 0], kind="stable")
    a = a[order]
    return PoseSeries(a[:, 0], a[:, 1:4], np.column_stack([a[:, 7], a[:, 4:7]]))


def vision_estimates(
    received: Iterable[Any], time_source: Literal["usec", "arrival"] = "usec", usec_offset_s: float = 0.0
) -> PoseSeries:
    """The VISION_POSITION_ESTIMATEs among ``received`` (mavvo.sim.flight_controller.autopilot.Received) as a series.

    ``usec``: the message's own timestamp plus ``usec_offset_s``, read as simulation time (offset 0:
    the clock the simulator gives the daemon; a client on its own clock: the offset its TIMESYNC
    requests show); ``arrival``: when the flight controller received it (the error then includes the
    client's latency). Non-finite estimates are skipped.
    """
    t, p, R = [], [], []
    for r in received:
        if r.type != "VISION_POSITION_ESTIMATE":
            continue
        m = r.msg
        vals = (m.x, m.y, m.z, m.roll, m.pitch, m.yaw)
        if not all(math.isfinite(v) for v in vals):
            continue
        t.append(m.usec * 1e-6 + usec_offset_s if time_source == "usec" else r.t_s)
        p.append(vals[:3])
        R.append(R_from_euler321(m.roll, m.pitch, m.yaw))
    if not t:
        return PoseSeries(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
    order = np.argsort(t, kind="stable")
    return PoseSeries.from_rotations(np.array(t)[order], np.array(p)[order], np.array(R)[order])


def write_report(out_dir: str | Path, est: PoseSeries, gt: PoseSeries, *, title: str = "mavvo") -> Evaluation:
    """Evaluate ``est`` against ``gt`` (matched) and write estimate.tum, truth.tum, summary.json and
    evaluation.png into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ev, aligned = evaluate(est, gt)
    write_tum(out / "estimate.tum", est)
    write_tum(out / "truth.tum", gt)
    (out / "summary.json").write_text(json.dumps({"title": title, **ev.to_dict()}, indent=2) + "\n", encoding="utf-8")
    plot_evaluation(out / "evaluation.png", aligned, gt, ev, title=title, as_sent=est)
    return ev


def plot_evaluation(
    path: str | Path,
    aligned: PoseSeries,
    gt: PoseSeries,
    ev: Evaluation,
    *,
    title: str = "mavvo",
    as_sent: PoseSeries | None = None,
) -> Path:
    """PNG: top view of the paths (north up, east right) and the position error over time. ``as_sent``:
    the estimate as the flight controller got it (matched to ``gt``, in its frame): drawn and its error
    plotted beside the aligned one's. Alignment hides what the vehicle is told: the error of the place
    tracking was anchored at (the flight controller's own belief there) and every drift since."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    err = np.linalg.norm(aligned.positions_xyz_m - gt.positions_xyz_m, axis=1)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.6), gridspec_kw={"width_ratios": [1.1, 1]})
    ax1.plot(gt.positions_xyz_m[:, 1], gt.positions_xyz_m[:, 0], "k-", lw=1.5, label="truth")
    ax1.plot(
        aligned.positions_xyz_m[:, 1],
        aligned.positions_xyz_m[:, 0],
        "-",
        color="tab:orange",
        lw=1.2,
        label="estimate (SE(3)-aligned)",
    )
    if as_sent is not None:
        ax1.plot(
            as_sent.positions_xyz_m[:, 1],
            as_sent.positions_xyz_m[:, 0],
            "-",
            color="tab:blue",
            lw=1.0,
            label="estimate as sent (no alignment)",
        )
    ax1.plot(gt.positions_xyz_m[0, 1], gt.positions_xyz_m[0, 0], "go", label="start")
    ax1.set_xlabel("east [m]")
    ax1.set_ylabel("north [m]")
    ax1.set_aspect("equal", adjustable="datalim")
    ax1.grid(True, alpha=0.3)
    ax1.legend(loc="best", fontsize=8)
    ax1.set_title(f"{title}: top view")
    t = gt.timestamps_s - gt.timestamps_s[0]
    ax2.plot(t, err, color="tab:orange", lw=1.0, label="SE(3)-aligned")
    heading = (
        f"ATE {ev.ate_se3_m['rmse']:.3f} m RMSE ({ev.ate_se3_rmse_percent_of_path:.2f}% of {ev.path_length_m:.0f} m); "
        f"Sim(3) {ev.ate_sim3_m['rmse']:.3f} m"
    )
    if as_sent is not None:
        sent_err = np.linalg.norm(as_sent.positions_xyz_m - gt.positions_xyz_m, axis=1)
        ax2.plot(t, sent_err, color="tab:blue", lw=1.0, label="as sent (no alignment; the anchor's error included)")
        heading += f"\nas sent: {sent_err[-1]:.3f} m at the end, {sent_err.max():.3f} m at most"
        ax2.legend(loc="best", fontsize=8)
    ax2.set_xlabel("time [s]")
    ax2.set_ylabel("position error [m]")
    ax2.grid(True, alpha=0.3)
    ax2.set_title(heading, fontsize=9)
    fig.tight_layout()
    p = Path(path)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p
