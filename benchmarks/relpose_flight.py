"""Relative pose on pairs that look like flight: KLT tracks on rendered frames, and roll/pitch with the
errors a flight controller makes, mavvo beside OpenCV and PoseLib in the same run.

    python benchmarks/relpose_flight.py [--quick] [--markdown docs/benchmarks.md] [--plots docs/img]

Pairs (:func:`mavvo.sim.scenarios.tracked_pairs.tracked_pairs`): the simulated camera renders a flight
(``survey``: nadir; ``forward``: a forward camera), mavvo's own frontend tracks it, and every 5th frame
is paired with the one 10 frames later (0.5 s) on the tracks both hold (up to 500 tracks a frame, 6 px
apart: 200-500 a pair): real tracking noise, real tracking failures as outliers. The truth is the
trajectory's camera pose at both exposures. Each path is flown over ``FLIGHTS`` textures (the shipped
one and others: ``tracked_pairs(variant=k)``) and the pairs pooled: one flight's 159 pairs left the
forward camera's medians a few percent either way of what nine flights give.

Roll/pitch given to mavvo: the truth plus, per view and axis, independent Gaussian errors (0, 0.2,
0.5, 1 deg), or correlated ones: a bias common to both views (0.5 or 1 deg per axis, drawn per pair:
a slowly varying bias is the same at two exposures half a second apart) plus 0.05 deg of noise.

Methods, each on the same tracks: mavvo with roll/pitch taken as exact (the paper's setting; the
odometry's with ``attitude_correction`` off), mavvo with each view's attitude sigma given (the
error's own sigma, at least 0.2 deg: what a configuration would say; the odometry's default); both
get the yaw change as a prior, as the odometry gives it (the flight controller's, here the truth
plus 1 deg of noise: over flat ground a nadir view has a twin pose turned by 180 deg that only the
prior tells apart); OpenCV ``findEssentialMat`` USAC_MAGSAC + ``recoverPose`` on the undistorted
pixels, PoseLib ``estimate_relative_pose`` (success_prob 0.99, and its defaults) where installed.
Success: rotation error < 2 deg and translation direction error < 10 deg. Times are per-thread CPU
time per call, medians.
"""

from __future__ import annotations

import argparse
import datetime as dt
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402

from benchmarks.common import load_average, machine, publish  # noqa: E402
from benchmarks.compare import BEST_PEER_HEADER, YAW_PRIOR_NOISE_DEG, TrialErrors, best_peer_cells  # noqa: E402
from mavvo.estimation.relpose import estimate_relpose_known_gravity  # noqa: E402
from mavvo.estimation.relpose_types import RelposeOptions  # noqa: E402
from mavvo.fleet.engine import Outcome, run_tasks  # noqa: E402
from mavvo.geometry.camera_model import CameraModel  # noqa: E402
from mavvo.geometry.frames import R_lvl_cam, angle_between_rad, rotation_angle_rad  # noqa: E402
from mavvo.odometry.frontend import FrontendOptions  # noqa: E402
from mavvo.sim.scenarios.tracked_pairs import TrackedPair, tracked_pairs  # noqa: E402

try:
    import poselib  # type: ignore[import-not-found]
except ImportError:  # the comparison is optional
    poselib = None

BEGIN, END = "<!-- relpose-flight:begin -->", "<!-- relpose-flight:end -->"
THRESHOLD_PX = 1.0
INDEPENDENT_DEG = (0.0, 0.2, 0.5, 1.0)
CORRELATED_DEG = (0.5, 1.0)
CORRELATED_NOISE_DEG = 0.05
# Denser tracking than the odometry's defaults (250 tracks a frame, min 12 px apart), so that a pair holds
# 200-500 common tracks: with the defaults the forward camera keeps a median 118 over 10 frames.
FRONTEND = FrontendOptions(max_features=500, min_distance_px=6.0)
FLIGHTS = 3  # textures per path (one with --quick)


def attitude_errors(rng: np.random.Generator, kind: str, level_deg: float) -> np.ndarray:
    """(2, 2) roll/pitch errors (rad) of view 1 and view 2."""
    if kind == "independent":
        return np.radians(level_deg) * rng.standard_normal((2, 2))
    bias = np.radians(level_deg) * rng.standard_normal(2)
    return bias[None, :] + np.radians(CORRELATED_NOISE_DEG) * rng.standard_normal((2, 2))


Method = Callable[[TrackedPair, np.ndarray, np.ndarray, float, int], "tuple[np.ndarray, np.ndarray] | None"]


def mavvo(camera: CameraModel, with_sigma: bool) -> Method:
    opt = RelposeOptions(max_iterations=1000)

    def run(p: TrackedPair, R1: np.ndarray, R2: np.ndarray, sigma_rad: float, seed: int):  # type: ignore[no-untyped-def]
        prior = p.yaw_2_1 + math.radians(YAW_PRIOR_NOISE_DEG) * np.random.default_rng(seed).standard_normal()
        r = estimate_relpose_known_gravity(
            p.uv1,
            p.uv2,
            camera,
            R1,
            R2,
            max_err_px=THRESHOLD_PX,
            seed=seed,
            options=opt,
            attitude_sigma_rad=(sigma_rad, sigma_rad) if with_sigma else None,
            yaw_prior_rad=prior,
        )
        return (r.R_c2_c1, r.t_c2_c1) if r.success else None

    return run


def opencv(camera: CameraModel) -> Method:
    def run(p: TrackedPair, R1: np.ndarray, R2: np.ndarray, sigma_rad: float, seed: int):  # type: ignore[no-untyped-def]
        cv2.setRNGSeed(seed)
        E, mask = cv2.findEssentialMat(
            p.uv1, p.uv2, camera.K, method=cv2.USAC_MAGSAC, prob=0.99, threshold=THRESHOLD_PX
        )
        if E is None or E.shape != (3, 3):
            return None
        _, R, t, _ = cv2.recoverPose(E, p.uv1, p.uv2, camera.K, mask=mask)
        return R, t[:, 0]

    return run


def poselib_method(camera: CameraModel, defaults: bool) -> Method:
    cam = {
        "model": "PINHOLE",
        "width": camera.width_px,
        "height": camera.height_px,
        "params": [camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px],
    }

    def run(p: TrackedPair, R1: np.ndarray, R2: np.ndarray, sigma_rad: float, seed: int):  # type: ignore[no-untyped-def]
        ransac = (
            {"max_epipolar_error": THRESHOLD_PX, "seed": seed}
            if defaults
            else {"max_epipolar_error": THRESHOLD_PX, "success_prob": 0.99, "min_iterations": 0, "seed": seed}
        )
        pose, _ = poselib.estimate_relative_pose(p.uv1, p.uv2, cam, cam, ransac, {})
        return pose.R, pose.t

    return run


def evaluate(
    pairs: list[TrackedPair], methods: dict[str, Method], kind: str, level_deg: float, seed: int
) -> dict[str, tuple[TrialErrors, float]]:
    """Each method's errors per pair and its median time per call (us), every method on the same
    attitude errors."""
    rng = np.random.default_rng(seed)
    sigma = math.radians(max(level_deg, 0.2))
    out: dict[str, dict[str, list[float]]] = {m: {"rot": [], "trans": [], "us": []} for m in methods}
    for i, p in enumerate(pairs):
        e = attitude_errors(rng, kind, level_deg)
        R1 = R_lvl_cam(p.rp1[0] + e[0, 0], p.rp1[1] + e[0, 1], p.R_body_cam)
        R2 = R_lvl_cam(p.rp2[0] + e[1, 0], p.rp2[1] + e[1, 1], p.R_body_cam)
        for name, fn in methods.items():
            t0 = time.thread_time()
            pose = fn(p, R1, R2, sigma, i)
            out[name]["us"].append((time.thread_time() - t0) * 1e6)
            if pose is None or not np.all(np.isfinite(pose[0])) or np.linalg.norm(pose[1]) == 0:
                rot = trans = math.inf
            else:
                rot = math.degrees(rotation_angle_rad(pose[0], p.R_c2_c1))
                trans = math.degrees(angle_between_rad(pose[1] / np.linalg.norm(pose[1]), p.t_c2_c1))
            out[name]["rot"].append(rot)
            out[name]["trans"].append(trans)
    return {
        m: (TrialErrors(np.array(d["rot"]), np.array(d["trans"])), statistics.median(d["us"])) for m, d in out.items()
    }


def _flight_task(task: tuple[str, float, int]) -> tuple[list, Any]:
    """One rendered flight's tracked pairs and its camera: an engine task."""
    cv2.setNumThreads(1)
    name, duration, variant = task
    return tracked_pairs(name, duration, frontend_options=FRONTEND, variant=variant)


def _methods(camera: Any) -> dict[str, Method]:
    methods: dict[str, Method] = {
        "mavvo, roll/pitch exact": mavvo(camera, False),
        "mavvo, attitude sigma": mavvo(camera, True),
        "OpenCV USAC_MAGSAC": opencv(camera),
    }
    if poselib is not None:
        methods["PoseLib p=0.99"] = poselib_method(camera, False)
        methods["PoseLib defaults"] = poselib_method(camera, True)
    return methods


def _level_task(task: tuple[list, Any, str, float]) -> dict[str, tuple[Any, float]]:
    """Every method on every pair at one roll/pitch noise level (the methods take turns pair by pair in
    this one thread, so their per-thread CPU times compare): an engine task."""
    cv2.setNumThreads(1)
    pairs, camera, kind, level = task
    return evaluate(pairs, _methods(camera), kind, level, seed=int(level * 100) + (7 if kind == "correlated" else 0))


def run(quick: bool, plots: Path | None, jobs: int = 1) -> str:
    """The flights are rendered and the noise levels evaluated as independent tasks on the sweep engine
    (mavvo.fleet.engine; ``jobs`` worker processes, 1 by default: a quiet core for the timings)."""
    cv2.setNumThreads(1)
    scenarios = {"survey": 20.0 if quick else 40.0, "forward": 20.0 if quick else 40.0}
    flights: dict[tuple[str, int], tuple[list, Any]] = {}

    def keep(store: dict) -> Callable[[Outcome], None]:
        def record(o: Outcome) -> None:
            if o.error is not None:
                raise SystemExit(f"relpose_flight: task {o.key} failed: {o.error}")
            store[o.key] = o.result

        return record

    variants = range(1 if quick else FLIGHTS)
    tasks = [((n, v), (n, d, v)) for n, d in scenarios.items() for v in variants]
    run_tasks(_flight_task, tasks, keep(flights), workers=jobs)
    rows = []
    method_names = list(_methods(flights[(next(iter(scenarios)), 0)][1]))
    n_pairs = {}
    levels = [
        (kind, level) for kind, ls in (("independent", INDEPENDENT_DEG), ("correlated", CORRELATED_DEG)) for level in ls
    ]
    for name in scenarios:
        camera = flights[(name, 0)][1]  # the scenario's camera: the same in every flight
        pairs = [p for v in variants for p in flights[(name, v)][0]]
        n_pairs[name] = (len(pairs), int(np.median([len(p.uv1) for p in pairs])))
        results: dict[tuple[str, float], dict] = {}
        run_tasks(_level_task, [((k, lv), (pairs, camera, k, lv)) for k, lv in levels], keep(results), workers=jobs)
        for kind, level in levels:
            for m, (errors, us) in results[(kind, level)].items():
                rows.append(
                    {
                        "scenario": name,
                        "kind": kind,
                        "level": level,
                        "method": m,
                        "errors": errors,
                        "us": us,
                        "pairs": len(pairs),
                    }
                )
        print(f"  {name} done", file=sys.stderr)
    lines = [
        BEGIN,
        "## Relative pose on flight-like pairs (`benchmarks/relpose_flight.py`)",
        "",
        f"Measured {dt.date.today().isoformat()} on {machine(poselib)}; {load_average()} at the end; "
        "pairs 0.5 s apart from the simulated camera, tracked by mavvo's frontend; per-thread CPU time per call, medians; "
        "regenerate with `make bench`. "
        + "; ".join(
            f"{k}: {n} pairs over {1 if quick else FLIGHTS} textures, median {m} tracks"
            for k, (n, m) in n_pairs.items()
        )
        + ".",
        "",
        "| flight | roll/pitch error | method | success | rotation err (deg) | translation err (deg) | time (us) |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        e = r["errors"]
        lines.append(
            f"| {r['scenario']} | {_error_label(r)} | {r['method']} | {e.found} of {r['pairs']} | {np.median(e.rot_deg):.3f} | "
            f"{np.median(e.trans_deg):.2f} | {r['us']:.0f} |"
        )
    lines += [
        "",
        f"mavvo with the attitude sigma against the peers ({', '.join(m for m in method_names if not m.startswith('mavvo'))}) on the same pairs:",
        "",
        "| flight | roll/pitch error | " + " | ".join(BEST_PEER_HEADER) + " |",
        "|---|---|" + "---|" * len(BEST_PEER_HEADER),
    ]
    for (scenario, _kind, _level), group in _groups(rows).items():
        peers = {
            m: r["errors"] for m, r in group.items() if not m.startswith("mavvo")
        }  # OpenCV always, PoseLib where installed
        cells = best_peer_cells(group["mavvo, attitude sigma"]["errors"], peers)
        lines.append(f"| {scenario} | {_error_label(group['mavvo, attitude sigma'])} | " + " | ".join(cells) + " |")
    if plots is not None:
        lines += [
            "",
            f"![success against roll/pitch noise]({_plot(plots / 'relpose_flight_success.png', rows, method_names)})",
        ]
    return "\n".join(lines + ["", END])


def _error_label(row: dict) -> str:
    return f"{row['level']:g} deg " + (
        "per view" if row["kind"] == "independent" else f"bias + {CORRELATED_NOISE_DEG:g} deg"
    )


def _groups(rows: list[dict]) -> dict[tuple[str, str, float], dict[str, dict]]:
    """Rows by (flight, kind of error, level), then by method."""
    out: dict[tuple[str, str, float], dict[str, dict]] = {}
    for r in rows:
        out.setdefault((r["scenario"], r["kind"], r["level"]), {})[r["method"]] = r
    return out


def _plot(path: Path, rows: list[dict], methods: list[str]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scen = sorted({r["scenario"] for r in rows})
    fig, axes = plt.subplots(1, len(scen), figsize=(5 * len(scen), 3.4), sharey=True)
    for ax, s in zip(np.atleast_1d(axes), scen):
        for m in methods:
            pts = [
                (r["level"], r["errors"].found / r["pairs"])
                for r in rows
                if r["scenario"] == s and r["method"] == m and r["kind"] == "independent"
            ]
            ax.plot([a for a, _ in pts], [100 * b for _, b in pts], marker="o", label=m)
        ax.set_title(f"{s}: independent roll/pitch errors", fontsize=9)
        ax.set_xlabel("roll/pitch noise per view and axis [deg]")
        ax.set_ylim(-5, 105)
    np.atleast_1d(axes)[0].set_ylabel("success [%]")
    np.atleast_1d(axes)[0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return f"img/{path.name}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter flights, one texture each")
    ap.add_argument(
        "--markdown", type=Path, default=None, help="write the table into this file between the relpose-flight markers"
    )
    ap.add_argument("--plots", type=Path, default=None, help="write the success plot into this folder")
    ap.add_argument("--jobs", type=int, default=1, help="tasks at once on the sweep engine (default 1: quiet timings)")
    args = ap.parse_args(argv)
    section = run(args.quick, args.plots, args.jobs)
    publish(section, args.markdown, BEGIN, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
