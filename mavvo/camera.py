"""Frame sources: the interface every camera implements.

The daemon reads frames through :class:`FrameSource` only, so a V4L2 device, a video file, an image
folder and the simulator's rendered camera are interchangeable.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from mavvo.types import Frame


@runtime_checkable
class FrameSource(Protocol):
    """A camera as the daemon sees it."""

    def read(self, timeout_s: float) -> Frame | None:
        """The next frame, waiting at most ``timeout_s``; None if none came in time.

        Raises :class:`mavvo.errors.CameraError` when the source has ended or failed for good.
        """

    def close(self) -> None:
        """Release the device or file; idempotent."""
