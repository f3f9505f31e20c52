"""mavvo beside what a user would write instead, on a small quad's camera: the same rendered frames,
attitude and range for each.

    python benchmarks/small_quad.py [--scenarios indoor_hops,indoor_carpet,indoor_patches,indoor_patches_trim,indoor_tiles,indoor_concrete,outdoor_grass] [--seeds own,101,102,103,104] [--markdown docs/benchmarks.md]

Methods, each fed the same paired frames (:class:`mavvo.sim.scenarios.paired_frames.PairedSequence`: the
scenario's rendered camera, roll/pitch/yaw with its noise, the rangefinder) and started at the true
position of the first frame:

- mavvo: :class:`mavvo.odometry.pipeline.Odometry` with default settings; its estimates of quality >= 1
  (what the service sends); a reset is a change of ``reset_counter``;
- optical flow x range (ArduPilot's optical-flow path): KLT of corners from the previous frame, each
  bearing turned by the attitude change and put on the flat ground at the measured height
  (range x cos(tilt)); the median ground displacement is the motion; the height is the range's;
- KLT + findHomography (RANSAC, 2 px), scale from the range: the same, from the homography's inliers
  only.

For the two peers a reset is a frame where fewer than 8 tracks survive (they re-detect and lose that
frame's motion); they send an estimate for every frame with a motion. Errors: the last estimate against
the truth at its time, without alignment (what the autopilot feels), horizontal and vertical, and in
percent of the path. CPU per frame: the thread's CPU time in each method's step (tracking included),
median over frames. Same frames, methods stepped in turn on each frame. Each peer's row also compares
its end errors with mavvo's draw by draw (the same noise for both): the 90% bootstrap interval of the
difference of the medians and the draws where mavvo ends closer, since a median over a few draws moves
by centimetres from one set of draws to another.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import load_average, machine, publish  # noqa: E402
from benchmarks.compare import paired_medians  # noqa: E402
from mavvo.fleet.engine import Outcome, run_tasks  # noqa: E402
from mavvo.geometry.frames import R_from_euler321  # noqa: E402
from mavvo.odometry.pipeline import Odometry  # noqa: E402
from mavvo.sim.scenarios.loader import load_scenario  # noqa: E402
from mavvo.sim.scenarios.paired_frames import PairedSequence  # noqa: E402

BEGIN, END = "<!-- small_quad:begin -->", "<!-- small_quad:end -->"
_MIN_TRACKS = 8
_CORNERS = 200


class FlowTimesRange:
    """Optical flow x range; with ``homography`` the flow's outliers are dropped by findHomography."""

    def __init__(self, sequence: PairedSequence, p0: np.ndarray, homography: bool) -> None:
        self.model = sequence.scenario.camera.camera_model()
        self.R_body_cam = sequence.R_body_cam
        self.homography = homography
        self.p = p0.astype(float).copy()
        self.z0_ground = None
        self.prev = None
        self.range_m: float | None = None
        self.resets = 0

    def _ground(self, uv: np.ndarray, frame) -> np.ndarray | None:
        """(N,3) world points on the flat ground below, NED, relative to the camera."""
        R_wc = R_from_euler321(frame.roll_rad, frame.pitch_rad, frame.yaw_rad) @ self.R_body_cam
        f = self.model.pixels_to_bearings(uv.astype(np.float64)) @ R_wc.T
        h = frame.range_m * np.cos(frame.roll_rad) * np.cos(frame.pitch_rad)
        ok = f[:, 2] > 0.2
        return None if h <= 0 else np.where(ok[:, None], f * (h / np.where(ok, f[:, 2], 1.0))[:, None], np.nan)

    def step(self, frame) -> np.ndarray | None:
        img = frame.image
        if frame.range_m is not None:
            self.range_m = frame.range_m
        elif self.range_m is None:  # a lost reading is held, as a user's script would
            self.prev = None
            return None
        frame = dataclasses.replace(frame, range_m=self.range_m)
        height = frame.range_m * np.cos(frame.roll_rad) * np.cos(frame.pitch_rad)
        if self.z0_ground is None:
            self.z0_ground = self.p[2] + height
        out = None
        if self.prev is not None:
            prev_img, prev_frame, pts = self.prev
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev_img, img, pts, None, winSize=(15, 15), maxLevel=2)
            good = st.ravel() == 1
            a, b = pts.reshape(-1, 2)[good], nxt.reshape(-1, 2)[good]
            if len(a) >= _MIN_TRACKS and self.homography:
                _, inl = cv2.findHomography(a, b, cv2.RANSAC, 2.0)
                if inl is not None:
                    a, b = a[inl.ravel() == 1], b[inl.ravel() == 1]
            if len(a) >= _MIN_TRACKS:
                ga, gb = self._ground(a, prev_frame), self._ground(b, frame)
                if ga is not None and gb is not None:
                    d = np.nanmedian(ga - gb, axis=0)  # the camera moved by the ground's apparent motion
                    if np.all(np.isfinite(d[:2])):
                        self.p[:2] += d[:2]
                        self.p[2] = self.z0_ground - height
                        out = self.p.copy()
            else:
                self.resets += 1
        pts = cv2.goodFeaturesToTrack(img, _CORNERS, 0.01, 6)
        self.prev = (img, frame, pts) if pts is not None and len(pts) >= _MIN_TRACKS else None
        return out


def _height_ok(p_ned_m: np.ndarray, true_ned_m: np.ndarray) -> bool:
    """Issue 50's bar for a height measured by a rangefinder: within 5 cm + 2% of the height (the
    ground is the plane z = 0)."""
    return bool(abs(p_ned_m[2] - true_ned_m[2]) < 0.05 + 0.02 * abs(true_ned_m[2]))


def _draw(task: tuple[str, str]) -> dict[str, dict[str, float]]:
    """One (scenario, seed) draw: an engine task."""
    cv2.setNumThreads(1)
    return _run(load_scenario(task[0]), task[1])


def _run(scenario, seed: str) -> dict[str, dict[str, float]]:
    sc = scenario if seed == "own" else dataclasses.replace(scenario, seed=int(seed))
    seq = PairedSequence(sc)
    frames = list(seq)
    truth = seq.camera_truth(np.array([f.t_exposure_s for f in frames]))
    p0 = truth.positions_xyz_m[0]
    path = float(np.linalg.norm(np.diff(truth.positions_xyz_m, axis=0), axis=1).sum())
    odo = Odometry(sc.camera.camera_model(), seq.R_body_cam, readout_s=sc.camera.rolling_shutter_ms * 1e-3)
    methods = {
        "mavvo": odo,
        "optical flow x range": FlowTimesRange(seq, p0, homography=False),
        "KLT + findHomography, range scale": FlowTimesRange(seq, p0, homography=True),
    }
    last: dict[str, tuple[int, np.ndarray]] = {}
    height_ok: dict[str, list[bool]] = {m: [] for m in methods}  # |z error| < 5 cm + 2% of the height
    sq_err: dict[str, list[float]] = {m: [] for m in methods}  # squared error of each estimate, m^2
    cpu: dict[str, list[float]] = {m: [] for m in methods}
    count = {m: 0 for m in methods}
    counters: list[int] = []
    started = False
    for i, f in enumerate(frames):
        for name, m in methods.items():
            # Until it starts (enough features), mavvo is told where the vehicle is, as the peers were
            # at the first frame; afterwards it is on its own.
            told = name == "mavvo" and not started
            f_in = dataclasses.replace(f, fc_position_ned_m=truth.positions_xyz_m[i]) if told else f
            t0 = time.thread_time()
            r = m.step(f_in)
            cpu[name].append(time.thread_time() - t0)
            if name == "mavvo":
                started = started or r is not None
                if r is not None and r.quality >= 1:
                    last[name], count[name] = (i, r.p_ned_m), count[name] + 1
                    height_ok[name].append(_height_ok(r.p_ned_m, truth.positions_xyz_m[i]))
                    sq_err[name].append(float(np.sum((r.p_ned_m - truth.positions_xyz_m[i]) ** 2)))
                    counters.append(r.reset_counter)
            elif r is not None:
                last[name], count[name] = (i, r), count[name] + 1
                height_ok[name].append(_height_ok(r, truth.positions_xyz_m[i]))
                sq_err[name].append(float(np.sum((r - truth.positions_xyz_m[i]) ** 2)))
    out = {}
    for name in methods:
        # A method that never gave an estimate is as far off as the whole path (it told the autopilot nothing).
        i, p = last.get(name, (0, np.full(3, np.inf)))
        e = p - truth.positions_xyz_m[i]
        resets = int(np.count_nonzero(np.diff(counters))) if name == "mavvo" else methods[name].resets
        out[name] = {
            "h": float(np.linalg.norm(e[:2])),
            "v": float(abs(e[2])),
            "end": float(np.linalg.norm(e)),
            "rms": float(np.sqrt(np.mean(sq_err[name]))) if sq_err[name] else float("inf"),
            "path": path,
            "resets": resets,
            "frames": count[name] / len(frames),
            "cpu_ms": 1e3 * statistics.median(cpu[name]),
            "height_ok": float(np.mean(height_ok[name])) if height_ok[name] else 0.0,
        }
    return out


def against_mavvo_cell(runs: list[dict[str, dict[str, float]]], name: str) -> str:
    """A peer's cell: mavvo's end error minus the peer's, draw by draw (both flew the same noise), as
    the 90% bootstrap interval of the medians' difference and the draws where mavvo ended closer. Five
    draws' medians move by centimetres with the draws; the interval says whether a gap is more than that."""
    if name == "mavvo":
        return "-"
    ours, peer = (np.array([run[m]["end"] for run in runs]) for m in ("mavvo", name))
    p = paired_medians(ours, peer)
    closer = int(np.count_nonzero(ours < peer))
    return f"{p.diff_low:+.2f} to {p.diff_high:+.2f} m; {closer} of {len(runs)}"


def _table(runs: list[dict[str, dict[str, float]]]) -> list[str]:
    """Markdown rows: per method, medians over the runs (and the worst end error)."""
    rows = [
        "| method | end error, no alignment: median (worst) | % of path | horizontal | vertical | RMS over the flight: median (worst) | resets | frames with an estimate | height within 5 cm + 2% (lowest) | CPU per frame | mavvo minus this, end error: 90% interval of the medians' difference; draws mavvo ends closer |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name in runs[0]:
        r = [run[name] for run in runs]

        def med(k: str, r: list = r) -> float:
            return statistics.median(x[k] for x in r)

        rows.append(
            f"| {name} | {med('end'):.2f} m ({max(x['end'] for x in r):.2f} m) | {100 * med('end') / med('path'):.1f}% | "
            f"{med('h'):.2f} m | {med('v'):.2f} m | {med('rms'):.2f} m ({max(x['rms'] for x in r):.2f} m) | "
            f"{med('resets'):.0f} | {100 * med('frames'):.0f}% | "
            f"{100 * med('height_ok'):.0f}% ({100 * min(x['height_ok'] for x in r):.0f}%) | {med('cpu_ms'):.1f} ms | "
            f"{against_mavvo_cell(runs, name)} |"
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--scenarios",
        default="indoor_hops,indoor_carpet,indoor_patches,indoor_patches_trim,indoor_tiles,indoor_concrete,outdoor_grass",
        help="comma-separated names or paths",
    )
    ap.add_argument("--seeds", default="own,101,102,103,104", help="draws of the noise: own is the scenario's seed")
    ap.add_argument("--markdown", type=Path)
    ap.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="draws at once, each in its own worker process of the sweep engine (default 1: a quiet core per draw)",
    )
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    seeds = [s for s in args.seeds.split(",") if s]
    names = [s for s in args.scenarios.split(",") if s]
    load_before = load_average()
    # Every (scenario, seed) draw is independent: one task each on the sweep engine (mavvo.fleet.engine,
    # as make draws and mavvo batch use); within a draw the methods still take turns frame by frame.
    runs: dict[tuple[str, str], dict[str, dict[str, float]]] = {}

    def record(o: Outcome) -> None:
        if o.error is not None:
            raise SystemExit(f"small_quad: draw {o.key} failed: {o.error}")
        runs[o.key] = o.result
        print(f"small_quad: {o.key[0]}, seed {o.key[1]} done", file=sys.stderr, flush=True)

    run_tasks(_draw, [((n, s), (n, s)) for n in names for s in seeds], record, workers=args.jobs)
    tables = []
    for name in names:
        scenario = load_scenario(name)
        tables += [f"### `{name}`: {scenario.description}", "", *_table([runs[(name, s)] for s in seeds]), ""]
    section = "\n".join(
        [
            BEGIN,
            "## A small quad's camera (`benchmarks/small_quad.py`)",
            "",
            f"Measured {dt.date.today().isoformat()} on {machine(None)}; {load_before}. The same rendered frames, "
            f"attitude and range for each method, stepped in turn on every frame; {len(seeds)} draws of the noise "
            f"(seeds {', '.join(seeds)}), medians (worst). The peers take their height from the range (as ArduPilot's "
            "optical-flow path does) and hold the last reading through a dropout; mavvo fuses it. Regenerate with "
            "`make bench`.",
            "",
            *tables,
            END,
        ]
    )
    publish(section, args.markdown, BEGIN, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
