"""Choosing views and solving for the intrinsics.

Views are chosen for coverage: the image is cut into a grid of cells, and a view is kept when its
corners reach cells that the views kept so far have not (or when the board is seen at another distance
or tilt); at most ``max_views``. Distortion is only as good as the image area the corners covered, so
the coverage (the fraction of cells with a corner) is reported beside the reprojection error.

A solve is checked before it is trusted: views whose own reprojection error is far above the rest's
(a board detected wrongly in one frame, motion blur) are dropped and the rest solved again; a result
whose corners still do not fit one camera (RMS over ``MAX_RMS_PX``: the ``--board`` size wrong, so a
sub-grid was found, or a bent board) or whose intrinsics no camera of that image has (a principal point
outside it) is refused. The
focal length's standard deviation (OpenCV's, pinhole) and the views' largest tilt say whether the views
pin the focal length down: boards seen nearly face-on leave it and the distance interchangeable.

Models: ``pinhole`` (OpenCV's radial-tangential k1 k2 p1 p2, and k3 on request: the coefficients mavvo's
``camera.distortion`` takes) and ``fisheye`` (equidistant k1..k4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence

import cv2
import numpy as np

from mavvo.calibration.boards import Detection
from mavvo.errors import MavvoError
from mavvo.geometry.camera_model import CameraIntrinsics

__all__ = ["CalibrationResult", "CalibrationError", "calibrate", "coverage", "select_views"]

GRID = (8, 6)  # coverage cells across and down the image
MIN_VIEWS = 4
_RETRY = "one printed board per view, flat and whole, tilted 30-45 deg in some views, over the whole image"
MAX_RMS_PX = 3.0  # above this the corners do not fit one camera: refused
# A view is an outlier when its RMS is over this many times the views' median, and over _OUTLIER_MIN_PX.
_OUTLIER_FACTOR = 3.0
_OUTLIER_MIN_PX = 0.5


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
        views_dropped: indices of the views dropped as outliers (their RMS far above the rest's).
        fx_sigma_px: the focal length's standard deviation (OpenCV's estimate; NaN for fisheye).
        max_tilt_deg: the largest angle between a view's board and the image plane.
    """

    intrinsics: CameraIntrinsics
    rms_px: float
    view_rms_px: tuple[float, ...]
    coverage: float
    views_used: tuple[int, ...]
    residuals_px: np.ndarray
    corners_px: np.ndarray
    views_dropped: tuple[int, ...] = ()
    fx_sigma_px: float = float("nan")
    max_tilt_deg: float = float("nan")


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


@dataclass(frozen=True)
class _Solve:
    K: np.ndarray
    D: np.ndarray
    rvecs: tuple[np.ndarray, ...]
    tvecs: tuple[np.ndarray, ...]
    fx_sigma_px: float


def _solve(obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int], model: str, k3: bool) -> _Solve:
    w, h = size
    try:
        if model == "fisheye":
            K0 = np.array([[w / 2.0, 0, w / 2.0], [0, w / 2.0, h / 2.0], [0, 0, 1]])
            flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
            _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(obj, img, size, K0, np.zeros((4, 1)), flags=flags)
            return _Solve(K, D, tuple(rvecs), tuple(tvecs), float("nan"))
        flags = 0 if k3 else cv2.CALIB_FIX_K3  # k3 only for wide lenses: on a narrow one it soaks up noise
        _, K, D, rvecs, tvecs, std, _, _ = cv2.calibrateCameraExtended(obj, img, size, None, None, flags=flags)
        return _Solve(K, D, tuple(rvecs), tuple(tvecs), float(std.ravel()[0]))
    except cv2.error as e:
        raise CalibrationError(f"the solve failed ({e.err}); try views that cover the image better") from e


def _view_rms(
    obj: list[np.ndarray], img: list[np.ndarray], sol: _Solve, model: str
) -> tuple[list[np.ndarray], list[float]]:
    """Each view's residuals (N, 2) observed minus reprojected, and its RMS."""
    residuals, rms = [], []
    for o, p, r, t in zip(obj, img, sol.rvecs, sol.tvecs):
        project = cv2.fisheye.projectPoints if model == "fisheye" else cv2.projectPoints
        proj, _ = project(o, r, t, sol.K, sol.D)
        res = (p - proj).reshape(-1, 2).astype(np.float64)
        residuals.append(res)
        rms.append(float(np.sqrt(np.mean(np.sum(res**2, axis=1)))))
    return residuals, rms


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
    sol = _solve(obj, img, size, model, k3)
    residuals, view_rms = _view_rms(obj, img, sol, model)
    limit = max(_OUTLIER_FACTOR * float(np.median(view_rms)), _OUTLIER_MIN_PX)
    keep = [k for k, r in enumerate(view_rms) if r <= limit]
    dropped = tuple(used[k] for k in range(len(used)) if k not in keep)
    if dropped and len(keep) >= MIN_VIEWS:  # solved again without them
        used = [used[k] for k in keep]
        obj, img = [obj[k] for k in keep], [img[k] for k in keep]
        sol = _solve(obj, img, size, model, k3)
        residuals, view_rms = _view_rms(obj, img, sol, model)
    else:
        dropped = ()
    all_res = np.vstack(residuals)
    rms = float(np.sqrt(np.mean(np.sum(all_res**2, axis=1))))
    w, h = size
    n_dist = 4 if model == "fisheye" else (5 if k3 else 4)
    K = sol.K
    try:
        intrinsics = CameraIntrinsics(
            width_px=int(w),
            height_px=int(h),
            fx_px=float(K[0, 0]),
            fy_px=float(K[1, 1]),
            cx_px=float(K[0, 2]),
            cy_px=float(K[1, 2]),
            model=model,
            distortion=tuple(float(x) for x in sol.D.ravel()[:n_dist]),
        )
    except ValueError as e:  # what the camera model refuses (a negative focal length)
        raise CalibrationError(f"the solve gave intrinsics no camera of this image has ({e}): {_RETRY}") from e
    if not rms <= MAX_RMS_PX:
        raise CalibrationError(
            f"reprojection RMS {rms:.2f} px (expected under {MAX_RMS_PX:g}): the corners do not fit one camera; "
            "is --board the count of inner corners (COLSxROWS) of this board? a bent or blurred board?"
        )
    tilts = [math.degrees(math.acos(min(1.0, abs(float(cv2.Rodrigues(r)[0][2, 2]))))) for r in sol.rvecs]
    return CalibrationResult(
        intrinsics,
        rms,
        tuple(view_rms),
        coverage([detections[i] for i in used], size),
        tuple(used),
        all_res,
        np.vstack([p.reshape(-1, 2).astype(np.float64) for p in img]),
        dropped,
        sol.fx_sigma_px,
        max(tilts),
    )
