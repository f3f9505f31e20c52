"""Helpers shared by the benchmarks: timing, the machine description, markdown sections."""

from __future__ import annotations

import os
import platform
import re
import resource
import sys
import statistics
import time
from pathlib import Path
from types import ModuleType
from typing import Callable

import cv2
import numpy as np


def per_call_us(fn: Callable[[], object], min_time_s: float = 0.2, repeats: int = 5) -> float:
    """Median over ``repeats`` of the mean time per call, each repeat lasting about ``min_time_s``."""
    fn()
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        if time.perf_counter() - t0 > min_time_s / 5:
            break
        n *= 2
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        samples.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(samples)


def raise_malloc_thresholds(nbytes: int = 4 << 20) -> None:
    """Allocate and free one array of ``nbytes``. glibc's malloc then serves arrays up to that size
    from its heap and keeps twice that much freed memory before returning it to the kernel (its
    dynamic mmap and trim thresholds): the state of any process that has once freed such an array.
    Not undoable; before it, a process whose arrays stay small gets freed memory returned at once and
    faults it in again on the next call."""
    np.ones(nbytes // 8).sum()


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
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}" + (
        f", PoseLib {getattr(poselib, '__version__', 'installed')}" if poselib else ", PoseLib not installed"
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
