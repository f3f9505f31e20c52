"""Small frozen dataclasses that cross module boundaries."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    Attributes:
        image: (H,W) uint8 grey image.
        t_exposure_s: middle of the exposure on the host clock (``time.monotonic`` on a drone, the
            simulation clock in the simulator), seconds.
        seq: frame counter of the source, starting at 0; a gap means frames were lost before mavvo.
    """

    image: np.ndarray
    t_exposure_s: float
    seq: int
