"""Feature tracking: FAST corners spread over a grid, pyramidal KLT with a forward-backward check.

Pixels in, tracks out. Each track keeps one id for as long as it lives, so the odometry can match a
frame against its keyframe by id. Per frame:

1. the previous frame's tracks are followed into the new image with pyramidal Lucas-Kanade, then
   followed back (from their old positions, at full resolution by default); a track survives when both directions converge, the round trip returns within
   ``fb_max_px`` and it stays ``border_px`` inside the image;
2. when fewer than ``redetect_fraction`` of ``max_features`` survive, FAST corners are detected in the
   grid cells that have lost theirs: at most ``max_features / cells`` per cell, the strongest first, and
   none within ``min_distance_px`` of a live track or of each other.

Bearings come from the camera
model, so lens distortion is handled without undistorting images.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mavvo.geometry.camera_model import CameraModel
from mavvo.options import bounded

__all__ = ["FrontendOptions", "Tracks", "Frontend"]

_MIN_SIDE_PX = 32
_MAX_SIDE_PX = 4096


@dataclass(frozen=True)
class FrontendOptions:
    """Settings of :class:`Frontend`; the defaults suit 640x480 at 15-30 frames/s."""

    max_features: int = bounded(250, "tracks kept per frame (the detector tops up to this)", gt=0, le=5000)
    grid_cols: int = bounded(8, "detection grid columns (features are spread over the cells)", gt=0, le=64)
    grid_rows: int = bounded(6, "detection grid rows", gt=0, le=64)
    fast_threshold: int = bounded(
        20, "FAST intensity threshold, grey levels (halved once when a frame yields too few)", gt=0, lt=255
    )
    min_distance_px: float = bounded(
        12.0, "no new corner closer than this to a track or another new corner", gt=0, le=500
    )
    redetect_fraction: float = bounded(
        0.8, "detect new corners when fewer than this fraction of max_features survive", gt=0, le=1
    )
    klt_window_px: int = bounded(15, "Lucas-Kanade window side", ge=5, le=101)
    klt_levels: int = bounded(3, "pyramid levels above the full image", ge=0, le=6)
    klt_iterations: int = bounded(20, "Lucas-Kanade iterations per level", gt=0, le=1000)
    fb_max_px: float = bounded(0.5, "largest forward-backward round-trip error of a surviving track", gt=0, le=50)
    klt_back_levels: int = bounded(
        0,
        "pyramid levels of the backward check, which starts at the tracks' old positions (0: full resolution only, a third of the forward cost)",
        ge=0,
        le=6,
    )
    border_px: int = bounded(8, "tracks this close to the image edge are dropped", ge=0, le=500)


@dataclass(frozen=True)
class Tracks:
    """The live tracks of one frame.

    Attributes:
        ids: (N,) int64 track ids in increasing order (by creation), unique over the frontend's life.
        uv_px: (N,2) float64 pixel positions (distorted image coordinates).
        f_cam: (N,3) unit bearings in the camera frame (distortion removed).
        tracked: how many of the N were tracked from the previous frame (the rest are new).
    """

    ids: np.ndarray
    uv_px: np.ndarray
    f_cam: np.ndarray
    tracked: int


class Frontend:
    """Tracks features through a sequence of 8-bit grey images of one camera (see the module docstring)."""

    def __init__(self, camera: CameraModel, options: FrontendOptions | None = None) -> None:
        self.camera = camera
        self.options = opt = options or FrontendOptions()
        self._fast = cv2.FastFeatureDetector_create(opt.fast_threshold, True)
        self._fast_low = cv2.FastFeatureDetector_create(max(opt.fast_threshold // 2, 1), True)
        self._win = (opt.klt_window_px, opt.klt_window_px)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, opt.klt_iterations, 0.03)
        self._per_cell = max(1, -(-opt.max_features // (opt.grid_cols * opt.grid_rows)))
        self._next_id = 0
        self.dropped_unmappable = 0  # tracks dropped because their pixel has no bearing
        self.reset()

    def reset(self) -> None:
        """Forget all tracks (ids keep increasing)."""
        self._prev: np.ndarray | None = None
        self._ids = np.zeros(0, np.int64)
        self._uv = np.zeros((0, 2), np.float32)

    def process(self, image: np.ndarray) -> Tracks:
        """Track into ``image`` ((H,W) uint8, the camera's size) and top up with new corners."""
        img = self._check(image)
        ids, uv = self._ids, self._uv
        if self._prev is not None and len(uv):
            keep, uv = self._track(self._prev, img, uv)
            ids = ids[keep]
        tracked = len(ids)
        if tracked < self.options.redetect_fraction * self.options.max_features:
            new_uv = self._detect(img, uv)
            if len(new_uv):
                new_ids = np.arange(self._next_id, self._next_id + len(new_uv), dtype=np.int64)
                self._next_id += len(new_uv)
                ids = np.concatenate([ids, new_ids])
                uv = np.concatenate([uv, new_uv])
        uv64 = uv.astype(np.float64)
        f_cam = self.camera.pixels_to_bearings(uv64)
        # A pixel the camera model cannot undistort (the corners of a strongly distorted lens) has no
        # bearing: its track is dropped here, so no NaN ever reaches a keyframe or the estimator.
        valid = np.isfinite(f_cam.sum(axis=1))
        if not np.all(valid):
            self.dropped_unmappable += int(np.count_nonzero(~valid))
            ids, uv, uv64, f_cam = ids[valid], uv[valid], uv64[valid], f_cam[valid]
            tracked = int(np.count_nonzero(valid[:tracked]))
        self._prev, self._ids, self._uv = img, ids, uv
        return Tracks(ids=ids, uv_px=uv64, f_cam=f_cam, tracked=tracked)

    def _check(self, image: np.ndarray) -> np.ndarray:
        a = np.asarray(image)
        if a.dtype != np.uint8 or a.ndim != 2:
            raise ValueError(f"image: expected a (H,W) uint8 grey image, got {a.dtype} of shape {a.shape}")
        h, w = a.shape
        if (w, h) != (self.camera.width_px, self.camera.height_px):
            raise ValueError(
                f"image: expected {self.camera.width_px}x{self.camera.height_px} (the camera model's size), got {w}x{h}"
            )
        if not (_MIN_SIDE_PX <= min(h, w) and max(h, w) <= _MAX_SIDE_PX):
            raise ValueError(f"image: expected sides between {_MIN_SIDE_PX} and {_MAX_SIDE_PX} px, got {w}x{h}")
        return a

    def _track(self, prev: np.ndarray, cur: np.ndarray, uv0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward and backward KLT; (surviving mask over uv0, their new positions)."""
        opt = self.options
        p0 = uv0.reshape(-1, 1, 2)
        lk = dict(winSize=self._win, maxLevel=opt.klt_levels, criteria=self._criteria)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, **lk)
        # Backward from the forward result, started at the original positions: a consistent track
        # converges there without the coarse levels (the same keep/drop decision for 99.96% of the
        # tracks of a survey flight as with all levels, at a third of the cost); one that is not
        # stays off and is dropped.
        lk["maxLevel"] = opt.klt_back_levels
        p0b, st0, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        p1 = p1.reshape(-1, 2)
        d = p0b.reshape(-1, 2) - uv0
        fb = np.hypot(d[:, 0], d[:, 1])
        h, w = cur.shape
        b = opt.border_px
        inside = (p1[:, 0] >= b) & (p1[:, 0] <= w - 1 - b) & (p1[:, 1] >= b) & (p1[:, 1] <= h - 1 - b)
        keep = (st1.ravel() == 1) & (st0.ravel() == 1) & (fb < opt.fb_max_px) & inside
        return keep, p1[keep]

    def _cell(self, uv: np.ndarray, w: int, h: int) -> np.ndarray:
        """(N,) index of each pixel's detection-grid cell."""
        gc, gr = self.options.grid_cols, self.options.grid_rows
        return np.minimum((uv[:, 1] * gr / h).astype(int), gr - 1) * gc + np.minimum(
            (uv[:, 0] * gc / w).astype(int), gc - 1
        )

    def _detect(self, img: np.ndarray, live_uv: np.ndarray) -> np.ndarray:
        """New corners in cells short of their share, away from live tracks: (M,2) float32."""
        opt = self.options
        h, w = img.shape
        b = max(opt.border_px, 3)
        kps = self._fast.detect(img)
        if len(kps) < opt.max_features:
            kps = self._fast_low.detect(img)
        if not kps:
            return np.zeros((0, 2), np.float32)
        pts = np.array([k.pt for k in kps], np.float32)
        resp = np.array([k.response for k in kps], np.float32)
        ok = (pts[:, 0] >= b) & (pts[:, 0] <= w - 1 - b) & (pts[:, 1] >= b) & (pts[:, 1] <= h - 1 - b)
        pts, resp = pts[ok], resp[ok]

        # Fine occupancy grid (cell = min distance): a cell next to a live track is taken.
        d = opt.min_distance_px
        fw, fh = int(np.ceil(w / d)), int(np.ceil(h / d))
        occupied = np.zeros((fh + 2, fw + 2), bool)
        if len(live_uv):
            cu = (live_uv[:, 0] / d).astype(int) + 1
            cv = (live_uv[:, 1] / d).astype(int) + 1
            for du in (-1, 0, 1):
                for dv in (-1, 0, 1):
                    occupied[np.clip(cv + dv, 0, fh + 1), np.clip(cu + du, 0, fw + 1)] = True
        fu = (pts[:, 0] / d).astype(int) + 1
        fv = (pts[:, 1] / d).astype(int) + 1
        free = ~occupied[fv, fu]
        pts, resp, fu, fv = pts[free], resp[free], fu[free], fv[free]
        cells = self._cell(pts, w, h)
        quota = np.maximum(
            self._per_cell - np.bincount(self._cell(live_uv, w, h), minlength=opt.grid_cols * opt.grid_rows), 0
        )
        room = max(opt.max_features - len(live_uv), 0)
        # Greedy, strongest first: a corner takes its fine cell and the eight around it.
        taken: list[int] = []
        for k in np.argsort(-resp, kind="stable"):
            if len(taken) >= room:
                break
            c, v, u = cells[k], fv[k], fu[k]
            if quota[c] == 0 or occupied[v, u]:
                continue
            taken.append(int(k))
            quota[c] -= 1
            occupied[v - 1 : v + 2, u - 1 : u + 2] = True
        return pts[taken] if taken else np.zeros((0, 2), np.float32)
