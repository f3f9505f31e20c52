"""Independent tasks on Dask: local worker processes or a running cluster, resumable, faults kept local.

One code path for every sweep (``mavvo batch``, ``make draws``): ``run_tasks(fn, tasks)`` calls
``fn(payload)`` once per task on a Dask worker and hands each outcome to ``on_outcome`` as it comes, in
completion order. An outcome is the function's result or a one-line reason it failed:

- an exception inside ``fn`` is that task's failure (its type and message), never the batch's;
- a worker that dies under a task (killed, out of memory) has the task retried on another worker once
  (``distributed.scheduler.allowed-failures`` 1 on a local cluster); dying again, it fails;
- Ctrl-C (KeyboardInterrupt) cancels what is pending and returns; what finished has been handed out.

Locally a ``LocalCluster`` of ``workers`` processes with one thread each (numba, OpenCV and BLAS each
also pinned to one thread: a worker per core, no oversubscription); ``scheduler="tcp://host:8786"``
reaches a running cluster instead, whose workers must have mavvo installed. Dask is the ``fleet`` extra
and is imported only here, when a sweep starts.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

from mavvo.errors import ConfigError, MavvoError

__all__ = ["Outcome", "Progress", "SweepStatus", "run_tasks", "default_workers", "quiet_dask_logs"]

log = logging.getLogger(__name__)

_MISSING = "mavvo batch needs Dask: pip install 'mavvo[fleet]' (make setup installs it)"
# Each worker process: one thread for every library that would start its own pool.
_ONE_THREAD = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}


@dataclass(frozen=True)
class Outcome:
    """What one task came to: ``result`` (None when it failed) or ``error``, a one-line reason."""

    key: Hashable
    result: Any = None
    error: str | None = None
    cpu_s: float = 0.0  # CPU time of the worker process over the task (all its threads)


@dataclass(frozen=True)
class Progress:
    done: int
    failed: int
    total: int
    elapsed_s: float

    @property
    def eta_s(self) -> float | None:
        """Remaining time at the rate so far; None before the first task finished."""
        finished = self.done + self.failed
        return None if finished == 0 else self.elapsed_s / finished * (self.total - finished)


@dataclass(frozen=True)
class SweepStatus:
    finished: int
    failed: int
    cancelled: int  # not run: interrupted
    workers: int


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def quiet_dask_logs() -> None:
    """Dask's loggers at WARNING (they set their own levels when Dask is imported: import it first)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return
    for name in list(logging.root.manager.loggerDict):
        if name == "distributed" or name.startswith("distributed."):
            logging.getLogger(name).setLevel(logging.WARNING)


def _guarded(fn: Callable[[Any], Any], payload: Any) -> tuple[Any, str | None, float]:
    """On the worker: ``fn(payload)`` with its failure turned into a reason, and the CPU time it took."""
    import cv2

    cv2.setNumThreads(1)
    cpu0 = time.process_time()
    try:
        result, error = fn(payload), None
    except MavvoError as e:  # bad input: its message says what and where
        result, error = None, str(e)
    except Exception as e:  # a bug or a broken file: one failed task, not the end of the sweep
        result, error = None, f"{type(e).__name__}: {e}".splitlines()[0]
    return result, error, time.process_time() - cpu0


def _client(workers: int, scheduler: str | None) -> tuple[Any, Any]:
    """(client, local cluster or None)."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as e:
        raise ConfigError(_MISSING) from e
    if scheduler is not None:
        try:
            return Client(scheduler, timeout="10s"), None
        except (OSError, TimeoutError) as e:
            raise ConfigError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there ({e})") from e
    # A worker that dies under a task: the task is retried once elsewhere, then fails.
    dask.config.set({"distributed.scheduler.allowed-failures": 1})
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=logging.ERROR,
        env=_ONE_THREAD,
    )
    return Client(cluster), cluster


def run_tasks(
    fn: Callable[[Any], Any],
    tasks: Sequence[tuple[Hashable, Any]],
    on_outcome: Callable[[Outcome], None],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: Callable[[Progress], None] | None = None,
) -> SweepStatus:
    """Run ``fn(payload)`` for each ``(key, payload)`` (see the module docstring). ``fn`` and the
    payloads must pickle (a module-level function, plain data)."""
    n_workers = workers or default_workers()
    client, cluster = _client(n_workers, scheduler)  # first: says what to install when Dask is missing
    from distributed import as_completed
    from distributed.client import FutureCancelledError

    try:
        from distributed.scheduler import KilledWorker
    except ImportError:  # older releases
        from distributed import KilledWorker  # type: ignore[no-redef]

    started = time.monotonic()
    done = failed = 0
    futures: dict[Any, Hashable] = {}
    try:
        if cluster is None:
            n_workers = len(client.scheduler_info().get("workers", {}))
        for key, payload in tasks:
            futures[client.submit(_guarded, fn, payload, pure=False)] = key
        for future in as_completed(list(futures)):
            key = futures[future]
            try:
                result, error, cpu_s = future.result()
            except KilledWorker:
                result, error, cpu_s = None, "its worker died twice (killed, or out of memory)", 0.0
            except FutureCancelledError:
                continue
            if error is None:
                done += 1
            else:
                failed += 1
            on_outcome(Outcome(key, result, error, cpu_s))
            if progress is not None:
                progress(Progress(done, failed, len(futures), time.monotonic() - started))
    except KeyboardInterrupt:
        log.warning("interrupted: cancelling %d pending tasks", len(futures) - done - failed)
        client.cancel(list(futures))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return SweepStatus(done + failed, failed, len(futures) - done - failed, n_workers)
