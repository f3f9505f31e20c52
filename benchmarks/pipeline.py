"""Speed of the whole odometry per frame, by stage, beside a plain OpenCV pipeline in the same run.

    python benchmarks/pipeline.py [--scenario survey] [--frames 300] [--markdown docs/benchmarks.md]

Frames of a scenario are rendered first (not timed), then fed to :class:`mavvo.odometry.pipeline.Odometry` on
one core. Stages are timed by wrapping the functions the odometry calls: tracking
(:class:`mavvo.odometry.frontend.Frontend`), relative pose (:func:`mavvo.estimation.relpose.estimate_upright_relpose`),
scale (:func:`mavvo.odometry.scale.estimate_scale`) and the filter. The reference is what a minimal OpenCV
monocular pipeline does per frame on the same images: KLT of the previous frame's corners
(``goodFeaturesToTrack`` when they run low), ``findEssentialMat`` with USAC_MAGSAC and
``recoverPose``. Peak memory is what Python and numpy allocated during the run (tracemalloc).
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
import tracemalloc
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mavvo.odometry.pipeline as odometry_module  # noqa: E402
from benchmarks.common import machine, publish  # noqa: E402
from mavvo.odometry.pipeline import Odometry  # noqa: E402
from sim.scenarios.loader import load_scenario  # noqa: E402
from sim.scenarios.paired_frames import PairedSequence  # noqa: E402

BEGIN, END = "<!-- pipeline:begin -->", "<!-- pipeline:end -->"


class _Stopwatch:
    """Accumulates the time spent in wrapped callables, per stage name."""

    def __init__(self) -> None:
        self.total_s: dict[str, float] = {}

    def wrap(self, name: str, fn):
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.total_s[name] = self.total_s.get(name, 0.0) + time.perf_counter() - t0

        return timed


def _run_mavvo(frames, scenario, R_body_cam) -> tuple[np.ndarray, dict[str, float], int]:
    vo = Odometry(scenario.camera.camera_model(), R_body_cam)
    watch = _Stopwatch()
    vo.frontend.process = watch.wrap("tracking", vo.frontend.process)
    vo.filter.predict = watch.wrap("filter", vo.filter.predict)
    vo.filter.update = watch.wrap("filter", vo.filter.update)
    saved = {name: getattr(odometry_module, name) for name in ("estimate_upright_relpose", "estimate_scale")}
    odometry_module.estimate_upright_relpose = watch.wrap("relative pose", saved["estimate_upright_relpose"])
    odometry_module.estimate_scale = watch.wrap("scale", saved["estimate_scale"])
    try:
        times = []
        for pf in frames:
            t0 = time.perf_counter()
            vo.step(pf)
            times.append(time.perf_counter() - t0)
    finally:
        for name, fn in saved.items():
            setattr(odometry_module, name, fn)
    # Memory on a second run: tracemalloc slows numpy down too much to time under it.
    vo = Odometry(scenario.camera.camera_model(), R_body_cam)
    tracemalloc.start()
    for pf in frames:
        vo.step(pf)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return np.array(times), watch.total_s, peak


def _run_opencv(frames, K: np.ndarray) -> np.ndarray:
    times = []
    prev = None
    pts = None
    for pf in frames:
        t0 = time.perf_counter()
        img = pf.image
        if prev is not None and pts is not None and len(pts) >= 8:
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, pts, None, winSize=(15, 15), maxLevel=3)
            ok = st.ravel() == 1
            p0, p1 = pts[ok], nxt[ok]
            if len(p0) >= 8:
                E, mask = cv2.findEssentialMat(p0, p1, K, method=cv2.USAC_MAGSAC, prob=0.99, threshold=1.5)
                if E is not None and E.shape == (3, 3):
                    cv2.recoverPose(E, p0, p1, K, mask=mask)
            pts = p1.reshape(-1, 1, 2)
        if pts is None or len(pts) < 200:
            pts = cv2.goodFeaturesToTrack(img, 250, 0.01, 12)
        prev = img
        times.append(time.perf_counter() - t0)
    return np.array(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="survey", help="shipped scenario name or YAML path (default survey)")
    parser.add_argument("--frames", type=int, default=300, help="frames to render and time (default 300)")
    parser.add_argument("--markdown", type=Path, help="rewrite this benchmark's section of this markdown file")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)

    scenario = load_scenario(args.scenario)
    seq = PairedSequence(scenario)
    frames = []
    for pf in seq:
        frames.append(pf)
        if len(frames) >= args.frames:
            break
    print(f"rendered {len(frames)} frames of {scenario.name}", file=sys.stderr)
    times, stages, peak = _run_mavvo(frames, scenario, seq.R_body_cam)
    cv_times = _run_opencv(frames, scenario.camera.camera_model().K)

    n = len(times)
    mean_ms = 1e3 * times.mean()
    cv_ms = 1e3 * cv_times.mean()
    pct = {q: 1e3 * np.percentile(times, q) for q in (50, 90, 99)}
    rows = ["| stage | ms per frame | share |", "|---|---|---|"]
    for name in ("tracking", "relative pose", "scale", "filter"):
        ms = 1e3 * stages.get(name, 0.0) / n
        rows.append(f"| {name} | {ms:.2f} | {100 * ms / mean_ms:.0f}% |")
    rest = mean_ms - 1e3 * sum(stages.values()) / n
    rows.append(f"| the rest (matching, triangulation, keyframes) | {rest:.2f} | {100 * rest / mean_ms:.0f}% |")
    rows.append(f"| **all** | **{mean_ms:.2f}** | |")
    cam = scenario.camera
    section = "\n".join(
        [
            BEGIN,
            "## Odometry pipeline",
            "",
            f"Measured {dt.date.today().isoformat()} on {machine(None).replace(', PoseLib not installed', '')}; "
            f"`python benchmarks/pipeline.py --scenario {args.scenario} --frames {args.frames}`, one core, "
            f"{n} frames of {cam.width_px}x{cam.height_px} from the `{scenario.name}` scenario.",
            "",
            f"mavvo: **{1000 / mean_ms:.0f} frames/s** ({mean_ms:.2f} ms per frame; latency p50 {pct[50]:.2f} ms, "
            f"p90 {pct[90]:.2f} ms, p99 {pct[99]:.2f} ms, max {1e3 * times.max():.2f} ms). Goal 150 frames/s, bar 60.",
            "",
            *rows,
            "",
            f"A minimal OpenCV pipeline on the same frames (KLT, `findEssentialMat` USAC_MAGSAC, `recoverPose`; "
            f"no scale, keyframes or filter) took {cv_ms:.2f} ms per frame: mavvo/OpenCV = {mean_ms / cv_ms:.2f}x. "
            f"Peak memory allocated during the run: {peak / 2**20:.1f} MiB.",
            END,
        ]
    )
    publish(section, args.markdown, BEGIN, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
