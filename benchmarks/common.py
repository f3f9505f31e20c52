"""Helpers shared by the benchmarks: timing, the machine description, markdown sections.

Times are CPU time of the calling thread (``time.thread_time``), not wall-clock time: on a shared,
loaded machine the wall clock counts other processes' turns too (a loaded run inflated mavvo 8x and
short PoseLib calls 1.2x), the thread's CPU time does not. Run single-threaded (OpenCV, BLAS) so all
the work is the calling thread's. Peers are timed interleaved with mavvo in one process, repeated,
and reported as medians and ratios, with the load average beside them.
"""

from __future__ import annotations

import os
import platform
import re
import resource
import statistics
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Callable

import cv2
import numpy as np

# A Raspberry Pi 4 core against one core of the machines the benchmarks were run on: its figures are
# estimated as this many times these.
PI4_FACTOR = 3.5


def per_call_us(fn: Callable[[], object], min_time_s: float = 0.2, repeats: int = 5) -> float:
    """Median over ``repeats`` of the mean CPU time per call (µs), each repeat about ``min_time_s``."""
    return interleaved_us({"fn": fn}, min_time_s, repeats)["fn"]


def interleaved_us(fns: dict[str, Callable[[], object]], min_time_s: float = 0.2, repeats: int = 7) -> dict[str, float]:
    """Median CPU time per call (µs) of each function, the functions timed in turn within every repeat
    (so a change of load hits all of them alike), each turn about ``min_time_s / len(fns)``."""
    counts = {}
    for name, fn in fns.items():
        fn()
        n = 1
        while True:
            t0 = time.thread_time()
            for _ in range(n):
                fn()
            if time.thread_time() - t0 > min_time_s / (5 * len(fns)):
                break
            n *= 2
        counts[name] = n
    samples: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            n = counts[name]
            t0 = time.thread_time()
            for _ in range(n):
                fn()
            samples[name].append((time.thread_time() - t0) / n * 1e6)
    return {name: statistics.median(v) for name, v in samples.items()}


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, as the benchmarks report them."""
    try:
        one, five, fifteen = os.getloadavg()
    except OSError:
        return "load average unknown"
    return f"load average {one:.2f} / {five:.2f} / {fifteen:.2f} (1 / 5 / 15 min) on {os.cpu_count()} cores"


def minor_page_faults() -> int:
    """Minor page faults of this process so far (the kernel's count, not a timing)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def machine(poselib: ModuleType | None) -> str:
    """CPU, core count and the versions of everything compared."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}"
        + (f", PoseLib {getattr(poselib, '__version__', 'installed')}" if poselib else ", PoseLib not installed")
    )


def write_section(path: Path, begin: str, end: str, section: str) -> None:
    """Replace the section between the markers ``begin`` and ``end`` of a markdown file, keeping the rest."""
    text = path.read_text() if path.exists() else "# Benchmarks\n\nEach section is written by the benchmark it names.\n"
    if begin in text and end in text:
        text = re.sub(re.escape(begin) + ".*?" + re.escape(end), lambda _: section, text, flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    path.write_text(text)


def publish(section: str, markdown: Path | None, begin: str, end: str) -> None:
    """Print a benchmark's section and, when asked, write it into its place in the markdown file."""
    print(section)
    if markdown:
        write_section(markdown, begin, end, section)
        print(f"wrote {markdown}", file=sys.stderr)
