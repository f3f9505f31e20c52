"""Speed and drone-case accuracy of the upright solvers, beside PoseLib and OpenCV in the same run.

    python benchmarks/solvers.py [--markdown docs/benchmarks.md] [--scenes 1000]

Run single-threaded (``make bench`` sets OMP/OPENBLAS threads to 1). Times are the median of several
repetitions; the table reports ratios to the peers measured in this same run, since absolute times
drift on shared machines.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import sys
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import PI4_FACTOR, interleaved_us, load_average, machine, minor_page_faults, publish  # noqa: E402
from mavvo import geometry as solvers  # noqa: E402
from mavvo.geometry.frames import angle_between_rad, rot_x, rotation_angle_rad  # noqa: E402
from mavvo.sim.world.twoview import TwoViewScene, make_scene  # noqa: E402

try:
    import poselib  # type: ignore[import-not-found]
except ImportError:  # the comparison is optional
    poselib = None

import cv2  # noqa: E402

# PoseLib's upright solvers take gravity along camera y; ours along z. This maps our z onto y.
TO_POSELIB = rot_x(-np.pi / 2)
BEGIN, END = "<!-- solvers:begin -->", "<!-- solvers:end -->"


def recovered(Es: list[tuple[np.ndarray, np.ndarray]], scene: TwoViewScene, tol: float = 1e-6) -> bool:
    return any(rotation_angle_rad(R, scene.R_2_1) < tol and angle_between_rad(t, scene.t_2_1) < tol for R, t in Es)


def mavvo_poses(scene: TwoViewScene) -> list[tuple[np.ndarray, np.ndarray]]:
    return [
        solvers.upright_pose_from_essential(E, scene.f1_lvl, scene.f2_lvl)
        for E in solvers.solve_upright_3pt(scene.f1_lvl, scene.f2_lvl)
    ]


def poselib_poses(scene: TwoViewScene) -> list[tuple[np.ndarray, np.ndarray]]:
    C = TO_POSELIB
    out = []
    for pose in poselib.relpose_upright_3pt(scene.f1_lvl @ C.T, scene.f2_lvl @ C.T):
        R, t = C.T @ pose.R @ C, C.T @ pose.t
        out.append((R, t / np.linalg.norm(t)))
    return out


def run(n_scenes: int) -> str:
    rng = np.random.default_rng(0)
    scenes = [make_scene(rng, 5, motion=("sideways", "forward", "random")[i % 3]) for i in range(1024)]
    F1 = np.stack([s.f1_lvl[:3] for s in scenes])
    F2 = np.stack([s.f2_lvl[:3] for s in scenes])
    s0 = scenes[0]
    rows: list[tuple[str, float, str]] = []

    # mavvo and PoseLib interleaved in every repetition (benchmarks/common.py).
    fns = {
        "single": lambda: solvers.solve_upright_3pt(s0.f1_lvl[:3], s0.f2_lvl[:3]),
        **{f"batch{B}": (lambda B=B: solvers.solve_upright_3pt_batch(F1[:B], F2[:B])) for B in (1, 64, 1024)},
        "4pt": lambda: solvers.solve_upright_4pt(s0.f1_lvl[:4], s0.f2_lvl[:4]),
        "linear5pt": lambda: solvers.solve_upright_linear5pt(s0.f1_lvl, s0.f2_lvl),
    }
    if poselib is not None:
        a, b = s0.f1_lvl[:3] @ TO_POSELIB.T, s0.f2_lvl[:3] @ TO_POSELIB.T
        fns["poselib3"] = lambda: poselib.relpose_upright_3pt(a, b)
        fns["poselib5"] = lambda: poselib.relpose_5pt(s0.f1_cam, s0.f2_cam)
    p1 = (s0.f1_cam[:, :2] / s0.f1_cam[:, 2:]).astype(np.float64)
    p2 = (s0.f2_cam[:, :2] / s0.f2_cam[:, 2:]).astype(np.float64)
    fns["opencv5"] = lambda: cv2.findEssentialMat(p1, p2, np.eye(3), method=cv2.LMEDS)
    us = interleaved_us(fns)
    single3 = us["single"]
    batch = {B: us[f"batch{B}"] / B for B in (1, 64, 1024)}
    peer3 = us.get("poselib3")
    peer5 = us.get("poselib5")
    rows: list[tuple[str, float, str]] = [("mavvo `solve_upright_3pt`, one call", single3, "goal < 20 us")]
    for B in (1, 64, 1024):
        rows.append(
            (
                f"mavvo `solve_upright_3pt_batch`, B = {B}, per sample",
                batch[B],
                "goal within 2x of PoseLib's call" if B == 64 else "",
            )
        )
    rows.append(("mavvo `solve_upright_4pt` (4 points), one call", us["4pt"], ""))
    rows.append(("mavvo `solve_upright_linear5pt` (5 points), one call", us["linear5pt"], ""))
    if peer3 is not None and peer5 is not None:
        rows.append(("PoseLib `relpose_upright_3pt` (C++), one call", peer3, ""))
        rows.append(("PoseLib `relpose_5pt` (C++), one call", peer5, ""))
    rows.append(("OpenCV `findEssentialMat` on 5 points (LMEDS: one 5-point solve plus scoring)", us["opencv5"], ""))
    faults = minor_page_faults()
    solvers.solve_upright_3pt_batch(F1, F2)
    faults = minor_page_faults() - faults
    tracemalloc.start()
    solvers.solve_upright_3pt_batch(F1, F2)
    peak_mib = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()

    # Accuracy on the two drone cases: share of noise-free scenes recovered within 1e-6 rad.
    rng = np.random.default_rng(1)
    cases = {
        "(a) motion along gravity": [
            make_scene(rng, 3, motion="vertical", mount=("nadir", "oblique")[i % 2]) for i in range(n_scenes)
        ],
        "(b) nadir camera over flat ground": [
            make_scene(rng, 3, motion=("sideways", "forward", "random")[i % 3], structure="ground")
            for i in range(n_scenes)
        ],
        "general scenes": [
            make_scene(rng, 3, motion=("sideways", "forward", "random")[i % 3], mount=("nadir", "oblique")[i % 2])
            for i in range(n_scenes)
        ],
    }
    acc_rows = []
    for name, data in cases.items():
        ours = np.mean([recovered(mavvo_poses(s), s) for s in data])
        theirs = np.mean([recovered(poselib_poses(s), s) for s in data]) if poselib is not None else float("nan")
        acc_rows.append((name, ours, theirs))

    def ratio(x: float, ref: float | None) -> str:
        return f"{x / ref:.2f}x" if ref else "n/a"

    lines = [
        BEGIN,
        "## Upright solvers (`benchmarks/solvers.py`)",
        "",
        f"Measured {dt.date.today().isoformat()} on {machine(poselib)}; {load_average()}; single-threaded "
        f"(OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}). "
        "CPU time of the calling thread, mavvo and its peers interleaved in each of 7 repetitions, medians. "
        "The 3-point is one compiled kernel per sample (numba); a batch runs it per sample in compiled code. "
        "Regenerate with `make bench`.",
        "",
        f"One 1024-sample batch allocates {peak_mib:.2f} MiB (tracemalloc) and takes {faults} minor page faults.",
        "",
        "| what | time (us) | vs PoseLib upright 3-point | Raspberry Pi 4 estimate (us) | goal |",
        "|---|---:|---:|---:|---|",
    ]
    for name, t_us, goal in rows:
        lines.append(f"| {name} | {t_us:.2f} | {ratio(t_us, peer3)} | {PI4_FACTOR * t_us:.1f} | {goal} |")
    b64 = (
        "n/a"
        if peer3 is None
        else f"{batch[64] / peer3:.2f}x PoseLib's call ({'met' if batch[64] <= 2 * peer3 else 'missed'})"
    )
    lines += [
        "",
        f"Goals: the 3-point at B = 64 (what the sampling draws) is {batch[64]:.2f} us per sample, {b64}; "
        f"one unbatched call is {single3:.1f} us ({'met' if single3 < 20 else 'missed'}: under 20 us).",
        "",
        f"Share of {n_scenes} noise-free scenes in which some returned solution matches the truth within 1e-6 rad "
        "in rotation and in translation direction:",
        "",
        "| case | mavvo 3-point | PoseLib upright 3-point |",
        "|---|---:|---:|",
    ]
    for name, ours, theirs in acc_rows:
        lines.append(f"| {name} | {ours:.1%} | {'n/a' if np.isnan(theirs) else f'{theirs:.1%}'} |")
    lines += ["", END]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--markdown", type=Path, help="rewrite this benchmark's section of this markdown file")
    parser.add_argument("--scenes", type=int, default=1000, help="scenes per accuracy case (default 1000)")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    section = run(args.scenes)
    publish(section, args.markdown, BEGIN, END)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
