"""Calibration boards: checkerboards and ChArUco boards, their corners in the board's frame, and finding
them in an image.

Board frame: x along the columns, y along the rows, z out of the board's back, metres; the first inner
corner at the origin. A checkerboard of ``COLSxROWS`` counts its *inner* corners (OpenCV's pattern
size); a ChArUco board of ``COLSxROWS`` counts its *squares*, and its detection may see any subset of
its ``(COLS-1) x (ROWS-1)`` inner corners.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

from mavvo.errors import ConfigError

__all__ = ["BoardSpec", "Detection", "parse_board", "detect"]

_CHARUCO_DICTIONARY = cv2.aruco.DICT_5X5_1000


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board: ``cols`` x ``rows`` (inner corners of a checkerboard, squares of a ChArUco
    board), ``square_m`` the side of one square, ``marker_m`` the ChArUco markers' side (default 0.75 of
    a square)."""

    cols: int
    rows: int
    square_m: float
    charuco: bool = False
    marker_m: float | None = None

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2 or (self.charuco and (self.cols < 3 or self.rows < 3)):
            raise ConfigError(
                f"--board: expected at least {'3x3 squares' if self.charuco else '2x2 inner corners'}, got {self.cols}x{self.rows}"
            )
        if not self.square_m > 0:
            raise ConfigError(f"--square-m: expected a positive length in metres, got {self.square_m}")

    def corners_m(self) -> np.ndarray:
        """(N, 3) the inner corners in the board frame, row by row (z = 0)."""
        cols, rows = (self.cols - 1, self.rows - 1) if self.charuco else (self.cols, self.rows)
        grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float64) * self.square_m
        return np.hstack([grid, np.zeros((len(grid), 1))])

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV ChArUco board (``charuco`` only)."""
        marker = self.marker_m if self.marker_m is not None else 0.75 * self.square_m
        return cv2.aruco.CharucoBoard(
            (self.cols, self.rows), self.square_m, marker, cv2.aruco.getPredefinedDictionary(_CHARUCO_DICTIONARY)
        )


@dataclass(frozen=True)
class Detection:
    """A board found in one image: (N, 2) corner pixels and the (N, 3) board-frame corners they show."""

    image_px: np.ndarray
    board_m: np.ndarray


def parse_board(text: str) -> tuple[int, int]:
    """``COLSxROWS`` (e.g. ``9x6``) as two integers; ConfigError naming ``--board`` otherwise."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise ConfigError(f"--board: expected COLSxROWS such as 9x6, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def detect(image: np.ndarray, board: BoardSpec) -> Detection | None:
    """The board in a grey (or BGR) image, corners refined to sub-pixel; None when it is not seen
    whole (checkerboard) or with fewer than 6 corners (ChArUco), or when what the detector returned is
    no grid of this board (corners outside the image or not finite, a wrong count, unknown or repeated
    ChArUco ids): one frame's broken detection must not end the calibration."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    board_m = board.corners_m()
    try:
        if board.charuco:
            corners, ids, _, _ = cv2.aruco.CharucoDetector(board.charuco_board()).detectBoard(grey)
            if ids is None or len(ids) < 6:
                return None
            ids = ids.ravel()
            if ids.min() < 0 or ids.max() >= len(board_m) or len(np.unique(ids)) != len(ids):
                return None
            d = Detection(np.asarray(corners, np.float64).reshape(-1, 2), board_m[ids])
        else:
            found, corners = cv2.findChessboardCornersSB(
                grey, (board.cols, board.rows), flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
            )
            if not found or corners is None:
                return None
            d = Detection(np.asarray(corners, np.float64).reshape(-1, 2), board_m)
    except (cv2.error, ValueError):
        return None
    h, w = grey.shape[:2]
    inside = np.all(np.isfinite(d.image_px)) and np.all((d.image_px >= -0.5) & (d.image_px <= [w - 0.5, h - 0.5]))
    return d if len(d.image_px) == len(d.board_m) and inside else None
