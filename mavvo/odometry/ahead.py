"""Tracking one frame ahead: the next frame's tracking on a helper thread while the current frame's
pose is estimated.

The frontend's KLT and FAST are OpenCV calls that release the GIL, and the relative pose's compiled
kernels run without it too (numba ``nogil``), so on a computer with two or more cores the tracking of
frame k+1 overlaps the estimation of frame k. The frontend still sees every image exactly once and in
order, so the tracks, and with them every estimate, are the same with or without the helper thread.
It pays only when frame k+1 is already there while frame k is estimated, that is when frames queue
up; a lone frame is tracked on the calling thread as before (``docs/benchmarks.md``: one and two
threads).
"""

from __future__ import annotations

import queue
import threading
from concurrent.futures import Future
from typing import Callable

import numpy as np

from mavvo.odometry.frontend import Tracks

__all__ = ["TrackAhead"]


class TrackAhead:
    """Feeds a tracker (:meth:`mavvo.odometry.pipeline.Odometry.track`) its images in order, the next
    one on a helper thread.

    :meth:`start` hands the image the caller will ask for next to the helper thread (once the
    previous image's tracks are in); :meth:`tracks` returns an image's tracks, the helper's result
    when it was started for this very array, else tracked on the calling thread. Call both from one
    thread. Without the helper (``thread=False``) :meth:`start` does nothing and :meth:`tracks` is
    the tracker itself.

    Args:
        track: tracks one image, keeping state from image to image; only this object may call it
            while it is open.
        thread: whether to start the helper thread (on the first :meth:`start`).

    Attributes:
        ahead: frames whose tracks came from the helper thread.
    """

    def __init__(self, track: Callable[[np.ndarray], Tracks], *, thread: bool = True) -> None:
        self._track = track
        self.ahead = 0
        # A daemon thread, not a ThreadPoolExecutor's: those are joined at interpreter exit, so a
        # helper stuck inside OpenCV would keep the service from exiting for systemd to restart it.
        self._jobs: queue.SimpleQueue[tuple[np.ndarray, Future[Tracks]] | None] | None = (
            queue.SimpleQueue() if thread else None
        )
        self._helper: threading.Thread | None = None
        self._pending: tuple[np.ndarray, Future[Tracks]] | None = None

    def start(self, image: np.ndarray) -> bool:
        """Start tracking ``image``, the next one :meth:`tracks` will be asked for. Returns whether
        the helper took it (not without a helper thread, nor while another image is pending)."""
        if self._jobs is None or self._pending is not None:
            return False
        if self._helper is None:
            self._helper = threading.Thread(target=self._serve, args=(self._jobs,), name="mavvo-track", daemon=True)
            self._helper.start()
        self._pending = (image, Future())
        self._jobs.put(self._pending)
        return True

    def _serve(self, jobs: queue.SimpleQueue[tuple[np.ndarray, Future[Tracks]] | None]) -> None:
        """The helper thread: track each image handed over, until the None that :meth:`close` sends."""
        while (job := jobs.get()) is not None:
            image, future = job
            try:
                future.set_result(self._track(image))
            except BaseException as e:  # noqa: BLE001 - handed to the caller, who raises it in tracks()
                future.set_exception(e)

    def tracks(self, image: np.ndarray) -> Tracks:
        """The tracks of ``image`` ((H,W) uint8); raises what the tracker raises (a ValueError for a
        malformed image), also when the helper thread tracked it."""
        pending, self._pending = self._pending, None
        if pending is not None:
            started, future = pending
            if started is image:
                self.ahead += 1
                return future.result()
            # Another image than the one started: the tracker tracks that one first (an extra frame
            # in its sequence, which costs no track); what it made of it, or its error, is not wanted.
            future.exception()
        return self._track(image)

    def close(self) -> None:
        """Wait for a started image and stop the helper thread."""
        if self._pending is not None:
            self._pending[1].exception()  # its error, if any, belongs to a frame nobody asked for
            self._pending = None
        if self._jobs is not None:
            self._jobs.put(None)
            self._jobs = None
