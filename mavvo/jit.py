"""Compiled kernels: numba's ``njit`` with mavvo's settings, in one place.

A kernel is plain Python over arrays and scalars (loops, no numpy call per element), compiled to machine
code on its first call and cached on disk, so later processes load it in milliseconds: in
``NUMBA_CACHE_DIR`` when set (the systemd unit sets it; ``make setup`` warms it), else in
``__pycache__`` beside the source. ``NUMBA_DISABLE_JIT=1`` runs the same source as Python, for a
debugger: kernels therefore guard their divisions themselves rather than rely on numba's error model.

numba keys a cached kernel on its own file's contents only, yet compiles the kernels it calls into it:
after a change to a callee in another file, the caller would load from the cache with the old callee.
:func:`refresh_cache` therefore stamps each cache directory with a digest of every kernel's source and
empties mavvo's entries there when the digest differs (``warm_kernels`` calls it first).
"""

from __future__ import annotations

import hashlib
import inspect
from pathlib import Path
from typing import Any, Callable, TypeVar

import numba

__all__ = ["kernel", "refresh_cache"]

F = TypeVar("F", bound=Callable)

_KERNELS: list[Any] = []  # every kernel made, for refresh_cache
_STAMP_FILE = "mavvo-kernels.sha256"


def kernel(fn: F | None = None, *, fastmath: bool | set[str] = False, inline: bool = False) -> Any:
    """``fn`` compiled in nopython mode, cached, releasing the GIL while it runs. ``@kernel`` or
    ``@kernel(fastmath=..., inline=...)``: LLVM's fast-math flags for that kernel (a set such as
    ``{"reassoc"}`` lets it vectorise a sum; say beside the kernel why it is safe there); ``inline``
    puts a small per-element kernel into each kernel calling it before compilation, so that the
    caller's loop is compiled, and vectorised, as one."""

    def wrap(f: F) -> F:
        compiled = numba.njit(cache=True, nogil=True, fastmath=fastmath, inline="always" if inline else "never")(f)
        _KERNELS.append(compiled)
        return compiled  # type: ignore[no-any-return]

    return wrap if fn is None else wrap(fn)


def refresh_cache() -> list[Path]:
    """Empty mavvo's entries in every kernel cache directory whose stamp is not the digest of the
    kernel sources loaded now, and stamp it; the cache files removed. Call it before the kernels are
    used; the entries of a kernel this process already compiled (a frame rotation checked while
    starting up) are of the sources loaded now and stay. Nothing to do with ``NUMBA_DISABLE_JIT=1``;
    a directory that cannot be written is left as numba found it (numba then looks elsewhere for a
    writable one)."""
    caches = [k._cache for k in _KERNELS if hasattr(k, "_cache")]
    if not caches:
        return []
    sources = sorted({Path(f) for k in _KERNELS if (f := inspect.getsourcefile(k.py_func))})
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in sources)).hexdigest()
    stems = {p.stem for p in sources}
    # <module>.<function>-<line>: how numba names a kernel's cache files (then .py<version>...)
    fresh = {
        f"{Path(inspect.getsourcefile(k.py_func) or '').stem}.{k.py_func.__qualname__}-{k.py_func.__code__.co_firstlineno}"
        for k in _KERNELS
        if getattr(k, "signatures", None)
    }
    removed: list[Path] = []
    for cache_dir in sorted({Path(c.cache_path) for c in caches}):
        stamp = cache_dir / _STAMP_FILE
        try:
            if stamp.is_file() and stamp.read_text().strip() == digest:
                continue
            for f in sorted(cache_dir.glob("*.nb[ic]")):
                if f.name.split(".", 1)[0] in stems and f.name.split(".py", 1)[0] not in fresh:
                    f.unlink()
                    removed.append(f)
            cache_dir.mkdir(parents=True, exist_ok=True)
            stamp.write_text(digest + "\n")
        except OSError:
            continue
    return removed
