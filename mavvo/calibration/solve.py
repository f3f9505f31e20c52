"""Choosing views and solving for the intrinsics.

Views are chosen for coverage: the image is cut into a grid of cells, and a view is kept when its
corners reach cells that the views kept so far have not (or when the board is seen at another distance
or tilt); at most ``max_views``. Distortion is only as good as the image area the corners covered, so
the coverage (the fraction of cells with a corner) is reported beside the reprojection error.

Models: ``pinhole`` (OpenCV's radial-tangential k1 k2 p1 p2, and k3 on request: the coefficients mavvo's
``camera.distortion`` takes) and ``fisheye`` (equidistant k1..k4).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence

import cv2
import numpy as np

from mavvo.calibration.boards import Detection
from mavvo.errors import MavvoError
from mavvo.geometry.camera_model import CameraIntrinsics

__all__ = ["CalibrationResult", "CalibrationError", "coverage", "select_views", "calibrate"]

GRID = (8, 6)  # coverage cells across and down the image
MIN_VIEWS = 4


class CalibrationError(MavvoError):
    """Calibration could not be done (too few views, a solve that failed)."""


@dataclass(frozen=True)
class CalibrationResult:
    """The intrinsics found, with how much to trust them.

    Attributes:
        intrinsics: what to put in the ``camera:`` section.
        rms_px: reprojection error over every corner of the views used (pixels, RMS).
        view_rms_px: per view used, its RMS reprojection error.
        coverage: fraction of the ``GRID`` cells that hold a corner of a view used.
        views_used: indices (into the detections given) of the views used.
        residuals_px: (N, 2) observed minus reprojected corner, and (N, 2) where: for the plot.
    """

    intrinsics: CameraIntrinsics
    rms_px: float
    view_rms_px: tuple[float, ...]
    coverage: float
    views_used: tuple[int, ...]
    residuals_px: np.ndarray
    corners_px: np.ndarray


def _cells(d: Detection, size: tuple[int, int]) -> set[tuple[int, int]]:
    w, h = size
    cx = np.clip((d.image_px[:, 0] / w * GRID[0]).astype(int), 0, GRID[0] - 1)
    cy = np.clip((d.image_px[:, 1] / h * GRID[1]).astype(int), 0, GRID[1] - 1)
    return set(zip(cx.tolist(), cy.tolist()))


def coverage(detections: Sequence[Detection], size: tuple[int, int]) -> float:
    """Fraction of the image's ``GRID`` cells that hold at least one corner of ``detections``."""
    cells: set[tuple[int, int]] = set()
    for d in detections:
        cells |= _cells(d, size)
    return len(cells) / (GRID[0] * GRID[1])


def _signature(d: Detection) -> tuple[float, float]:
    """The board's apparent size (pixels, square root of the corners' spread) and its foreshortening
    (ratio of the spread's principal axes): distance and tilt, roughly."""
    cov = np.cov(d.image_px.T)
    ev = np.sqrt(np.maximum(np.linalg.eigvalsh(cov), 1e-9))
    return float(np.sqrt(ev[0] * ev[1])), float(ev[0] / ev[1])


def select_views(detections: Sequence[Detection], size: tuple[int, int], max_views: int = 40) -> list[int]:
    """Indices of the views to calibrate with: greedily, the view that adds the most uncovered cells,
    then views at a new distance or tilt, at most ``max_views``."""
    chosen: list[int] = []
    covered: set[tuple[int, int]] = set()
    cells = [_cells(d, size) for d in detections]
    left = set(range(len(detections)))
    while left and len(chosen) < max_views:
        best = max(left, key=lambda i: (len(cells[i] - covered), -i))
        if not cells[best] - covered:
            break
        chosen.append(best)
        covered |= cells[best]
        left.discard(best)
    seen = [_signature(detections[i]) for i in chosen]
    for i in sorted(left):
        if len(chosen) >= max_views:
            break
        s, f = _signature(detections[i])
        if all(abs(np.log(s / s0)) > 0.08 or abs(f - f0) > 0.05 for s0, f0 in seen):
            chosen.append(i)
            seen.append((s, f))
    return sorted(chosen)


def calibrate(
    detections: Sequence[Detection],
    size: tuple[int, int],
    model: Literal["pinhole", "fisheye"] = "pinhole",
    max_views: int = 40,
    k3: bool = False,
) -> CalibrationResult:
    """Intrinsics from the boards found in images of ``size`` (width, height) pixels; ``k3``: also the
    third radial coefficient (pinhole; for wide-angle lenses)."""
    used = select_views(detections, size, max_views)
    if len(used) < MIN_VIEWS:
        raise CalibrationError(
            f"the board was found in {len(detections)} images of which {len(used)} add coverage; expected at least {MIN_VIEWS}: "
            "move the board over the whole image, nearer and farther, tilted"
        )
    obj = [detections[i].board_m.astype(np.float32).reshape(-1, 1, 3) for i in used]
    img = [detections[i].image_px.astype(np.float32).reshape(-1, 1, 2) for i in used]
    w, h = size
    try:
        if model == "fisheye":
            K0 = np.array([[w / 2.0, 0, w / 2.0], [0, w / 2.0, h / 2.0], [0, 0, 1]])
            flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
            _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(obj, img, size, K0, np.zeros((4, 1)), flags=flags)
            dist = tuple(float(x) for x in D.ravel()[:4])
        else:
            flags = 0 if k3 else cv2.CALIB_FIX_K3  # k3 only for wide lenses: on a narrow one it soaks up noise
            _, K, D, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
            dist = tuple(float(x) for x in D.ravel()[: 5 if k3 else 4])
    except cv2.error as e:
        raise CalibrationError(f"the solve failed ({e.err}); try views that cover the image better") from e
    residuals, corners, view_rms = [], [], []
    for o, p, r, t in zip(obj, img, rvecs, tvecs):
        if model == "fisheye":
            proj, _ = cv2.fisheye.projectPoints(o, r, t, K, D)
        else:
            proj, _ = cv2.projectPoints(o, r, t, K, D)
        res = (p - proj).reshape(-1, 2).astype(np.float64)
        residuals.append(res)
        corners.append(p.reshape(-1, 2).astype(np.float64))
        view_rms.append(float(np.sqrt(np.mean(np.sum(res**2, axis=1)))))
    all_res = np.vstack(residuals)
    intrinsics = CameraIntrinsics(
        width_px=int(w),
        height_px=int(h),
        fx_px=float(K[0, 0]),
        fy_px=float(K[1, 1]),
        cx_px=float(K[0, 2]),
        cy_px=float(K[1, 2]),
        model=model,
        distortion=dist,
    )
    return CalibrationResult(
        intrinsics,
        float(np.sqrt(np.mean(np.sum(all_res**2, axis=1)))),
        tuple(view_rms),
        coverage([detections[i] for i in used], size),
        tuple(used),
        all_res,
        np.vstack(corners),
    )
