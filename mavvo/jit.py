"""Compiled kernels: numba's ``njit`` with mavvo's settings, in one place.

A kernel is plain Python over arrays and scalars (loops, no numpy call per element), compiled to machine
code on its first call and cached on disk, so later processes load it in milliseconds: in
``NUMBA_CACHE_DIR`` when set (the systemd unit sets it; ``make setup`` warms it), else in
``__pycache__`` beside the source. ``NUMBA_DISABLE_JIT=1`` runs the same source as Python, for a
debugger: kernels therefore guard their divisions themselves rather than rely on numba's error model.
"""

from __future__ import annotations

from typing import Callable, TypeVar

import numba

__all__ = ["kernel"]

F = TypeVar("F", bound=Callable)


def kernel(fn: F) -> F:
    """``fn`` compiled in nopython mode, cached, releasing the GIL while it runs."""
    return numba.njit(cache=True, nogil=True)(fn)  # type: ignore[return-value]
