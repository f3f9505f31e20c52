"""Instructions per frame of the whole odometry, this tree beside other revisions: a cost figure that
does not move with the machine's load or clock.

    python benchmarks/instructions.py [--against 6ddffe3 ...] [--scenario survey] [--frames 100] [--markdown docs/benchmarks.md]

CPU time on a shared machine moved by 30% between runs minutes apart (docs/status.md, the pipeline's
row), so a change of a few percent in the odometry's cost cannot be told from it. The instructions
executed can: valgrind's callgrind counts them, and the same code on the same input counts the same
on every run to about 0.1% over 100 frames (two copies of one tree read 41.96M and 41.92M a frame:
the garbage collector and the allocator need not repeat themselves; hash seeds are fixed). Over 3
frames the same two read 4.5% apart, so count 100 or more. What is counted is
one pass of a fresh :class:`Odometry` over the scenario's first ``--frames`` frames, after a first
pass over them has compiled and loaded every kernel (instrumentation is switched on only for the
second pass, with ``callgrind_control``). Every
revision steps the same frames: rendered once here, by this tree's simulator, and handed to each as
arrays. Revisions are exported with ``git archive`` into a temporary folder and run with this
checkout's packages.

Instructions are not time (a cache miss or a division costs more than an addition), but for the same
program on the same input a change of the count is a change of the work: the check for a regression
that the timings here cannot give. Needs valgrind (Debian's package ``valgrind``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import datetime as dt
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import machine, publish  # noqa: E402

BEGIN, END = "<!-- instructions:begin -->", "<!-- instructions:end -->"
_COLLECTED = re.compile(r"Collected\s*:\s*(\d+)")


def _render(scenario: str, frames: int, path: Path) -> None:
    """The scenario's first ``frames`` paired frames as arrays in ``path`` (.npz), NaN for no reading."""
    from mavvo.sim.scenarios.loader import load_scenario
    from mavvo.sim.scenarios.paired_frames import PairedSequence

    sc = load_scenario(scenario)
    sc = dataclasses.replace(sc, duration_s=frames / sc.camera.rate_hz + 2.0)  # a little past the last frame
    seq = PairedSequence(sc)
    out = []
    for f in seq:
        out.append(f)
        if len(out) == frames:
            break
    if len(out) < frames:
        raise SystemExit(f"--frames: the scenario {scenario!r} gives {len(out)} frames, asked for {frames}")
    start = seq.camera_truth(np.array([out[0].t_exposure_s])).positions_xyz_m[0]
    none = float("nan")
    np.savez(
        path,
        image=np.stack([f.image for f in out]),
        t=np.array([f.t_exposure_s for f in out]),
        seq=np.array([f.seq for f in out]),
        rpy=np.array([(f.roll_rad, f.pitch_rad, f.yaw_rad) for f in out]),
        range_m=np.array([none if f.range_m is None else f.range_m for f in out]),
        height_m=np.array([none if f.height_m is None else f.height_m for f in out]),
        start_ned_m=start,
    )


def _child(tree: Path, scenario: str, frames_file: Path) -> None:
    """Under callgrind: step the frames once to compile, then count a fresh odometry's pass."""
    sys.path.insert(0, str(tree))
    import cv2

    cv2.setNumThreads(1)
    from mavvo.odometry.pipeline import Odometry
    from mavvo.sim.scenarios.loader import load_scenario
    from mavvo.types import PairedFrame

    sc = load_scenario(scenario)
    # Each read of an .npz key loads the whole array again: read each once (100 frames would hold 100 copies).
    d = dict(np.load(frames_file))

    def reading(x: float) -> float | None:
        return None if np.isnan(x) else float(x)

    frames = [
        PairedFrame(
            d["image"][i],
            float(d["t"][i]),
            int(d["seq"][i]),
            *map(float, d["rpy"][i]),
            range_m=reading(d["range_m"][i]),
            height_m=reading(d["height_m"][i]),
        )
        for i in range(len(d["t"]))
    ]
    start = d["start_ned_m"]

    def run() -> None:
        odo = Odometry(sc.camera.camera_model(), sc.camera.R_body_cam())
        started = False
        for f in frames:
            started = odo.step(f if started else dataclasses.replace(f, fc_position_ned_m=start)) is not None or started

    run()  # kernels compiled or loaded, caches filled
    toggle = ["callgrind_control", "-i"]
    subprocess.run([*toggle, "on", str(os.getpid())], check=True, capture_output=True)
    run()
    subprocess.run([*toggle, "off", str(os.getpid())], check=True, capture_output=True)


def _count(tree: Path, scenario: str, frames_file: Path, work: Path) -> int:
    """Instructions of the counted pass of ``tree``'s odometry."""
    cmd = [
        "valgrind",
        "--tool=callgrind",
        "--instr-atstart=no",
        f"--callgrind-out-file={work / 'callgrind.%p'}",
        sys.executable,
        __file__,
        "--child",
        str(tree),
        "--scenario",
        scenario,
        "--frames-file",
        str(frames_file),
    ]
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONHASHSEED="0")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    m = _COLLECTED.findall(proc.stderr)
    if proc.returncode != 0 or not m:
        tail = "\n".join(proc.stderr.splitlines()[-15:])
        raise SystemExit(f"the count for {tree} failed (exit {proc.returncode}):\n{tail}")
    return int(m[-1])


def _export(rev: str, into: Path) -> Path:
    """Revision ``rev`` of this repository, its files only, in a new folder under ``into``."""
    dest = into / re.sub(r"[^\w.-]", "_", rev)
    dest.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], capture_output=True)
    if archive.returncode != 0:
        raise SystemExit(f"--against: {rev!r} is not a revision of {ROOT}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
    return dest


def _section(scenario: str, frames: int, counts: dict[str, int], argv: list[str]) -> str:
    here = counts["this tree"]
    rows = [f"| {name} | {n / frames / 1e6:.2f} | {n / here:.3f}x |" for name, n in counts.items()]
    return "\n".join(
        [
            BEGIN,
            "## Instructions per frame",
            "",
            f"Measured {dt.date.today().isoformat()} on {machine(None).replace(', PoseLib not installed', '')}; `python benchmarks/instructions.py {' '.join(argv)}`. "
            f"Instructions (valgrind's callgrind) of one pass of a fresh odometry over the first {frames} frames of "
            f"`{scenario}`, after a pass that compiled every kernel; the same frames for every revision. The same code "
            "on the same input counts the same on every run to about 0.1%, whatever the machine's load: a larger change "
            "here is a change of the work.",
            "",
            "| code | million instructions per frame | vs this tree |",
            "|---|---:|---:|",
            *rows,
            END,
        ]
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--against",
        action="append",
        default=[],
        metavar="REV",
        help="a git revision to count beside this tree (repeatable)",
    )
    p.add_argument("--scenario", default="survey", help="shipped scenario name (default survey)")
    p.add_argument(
        "--frames",
        type=int,
        default=100,
        help="frames counted (default 100; a few read several percent apart for the same code)",
    )
    p.add_argument("--markdown", type=Path, help="rewrite this benchmark's section of this markdown file")
    p.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--frames-file", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child is not None:
        _child(args.child, args.scenario, args.frames_file)
        return 0
    if args.frames < 1:
        p.error(f"--frames: expected a positive number, got {args.frames}")
    missing = [t for t in ("valgrind", "callgrind_control") if shutil.which(t) is None]
    if missing:
        p.error(f"needs {' and '.join(missing)} on PATH (Debian's package valgrind)")
    from mavvo.errors import ConfigError

    with tempfile.TemporaryDirectory(prefix="mavvo-instructions-") as tmp:
        work = Path(tmp)
        frames_file = work / "frames.npz"
        try:
            _render(args.scenario, args.frames, frames_file)
        except ConfigError as e:
            p.error(f"--scenario: {e}")
        trees = {"this tree": ROOT} | {rev: _export(rev, work) for rev in dict.fromkeys(args.against)}
        print(f"counting {len(trees)} trees over {args.frames} frames (a few minutes each)", file=sys.stderr)
        with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            futures = {
                name: pool.submit(_count, tree, args.scenario, frames_file, work) for name, tree in trees.items()
            }
            counts = {name: f.result() for name, f in futures.items()}
    publish(_section(args.scenario, args.frames, counts, argv), args.markdown, BEGIN, END)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
