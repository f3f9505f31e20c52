"""Feature tracking: corners spread over a grid (FAST, or Shi-Tomasi on faint texture), pyramidal KLT with a forward-backward check.

Pixels in, tracks out. Each track keeps one id for as long as it lives, so the odometry can match a
frame against its keyframe by id. Per frame:

1. the previous frame's tracks are followed into the new image with pyramidal Lucas-Kanade, then
   followed back (from their old positions, at full resolution by default); a track survives when both
   directions converge, the round trip returns within ``fb_max_px`` and it stays ``border_px`` inside
   the image. Where the texture is faint (``klt_highpass_below``), KLT sees each image less its local
   mean (``klt_highpass_px``): brightness the camera adds, vignetting and exposure offsets, does not
   move with the scene and would hold tracks back; there the round trip may be ``fb_max_faint_px``.
   When ``consensus_min_share`` of the survivors end over ``consensus_max_px`` off the pair's affine
   consensus, those are dropped: tracks that slipped a period of a repeated pattern pass the round trip;
2. when fewer than ``redetect_fraction`` of ``max_features`` survive, corners are detected in the
   grid cells that have lost theirs: at most ``max_features / cells`` per cell, the strongest first, and
   none within ``min_distance_px`` of a live track or of each other. The candidates are FAST corners
   at ``fast_threshold``, or at half of it when those are too few, but never below four sigmas of the
   image's noise (below that FAST finds corners in the noise itself, which KLT follows by less than a
   pixel either way: tracks that pass for standing still). Where even those are too few (a low-contrast
   floor, blur), Shi-Tomasi corners found at half resolution: halving averages the noise away but keeps
   a faint texture, and a corner counts when its smallest structure-tensor eigenvalue is five times
   what noise alone gives there (noise's 99.9th percentile is three times its median).

Pixel settings (spacing, KLT window, border, pyramid levels) are given for ``reference_width_px``
(640) and scale with the camera's width: at 320x240 the spacing is 6 px, the window 11 px (its floor)
and the pyramid one level shorter.

Bearings come from the camera
model, so lens distortion is handled without undistorting images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar

import cv2
import numpy as np

from mavvo.geometry.affine_consensus import off_affine_consensus
from mavvo.geometry.camera_model import CameraModel
from mavvo.options import bounded

__all__ = ["FrontendOptions", "Tracks", "Frontend"]

_MIN_SIDE_PX = 32
_MAX_SIDE_PX = 4096
_MIN_SPACING_PX = 4.0  # corners closer than this share most of a KLT window
_MIN_WINDOW_PX = 11  # a smaller KLT window follows noise on blurred, low-contrast images
_MIN_THRESHOLD = 5  # the lowest FAST threshold, whatever the noise estimate says
# FAST below this many noise sigmas finds corners in the noise itself: on a plain patch of floor (noise
# sigma 3) 10-24 per frame at 3 sigma, their structure no more than the noise's; 0-2 at 4 sigma.
# KLT follows such a corner by less than a pixel either way, so it passes for a track that does not move.
_NOISE_CORNER_SIGMAS = 4.0
_QUANTISATION_SIGMA = 0.5  # grey levels: rounding alone leaves about 0.3
# The high-pass is taken only of texture under klt_highpass_below grey levels RMS and rounded to 8 bits:
# doubled, rounding is a smaller part of what KLT sees than halved (docs/odometry.md, Small-quad
# flights), and a 4-sigma excursion of such texture stays far from clipping at 0 or 255.
_HIGHPASS_GAIN = 2.0
_MIN_CONSENSUS_TRACKS = 12  # fewer tracks than this make no consensus worth dropping a track for
_NOISE_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


@dataclass(frozen=True)
class FrontendOptions:
    """Settings of :class:`Frontend`. Pixel counts are for an image ``reference_width_px`` wide and
    scale with the camera's width (see :class:`Frontend`); the feature count does not: the estimator
    needs as many tracks from a small image as from a large one."""

    # Keys a configuration may still carry from an earlier release: what replaced them.
    RETIRED_KEYS: ClassVar[dict[str, str]] = {
        "fast_threshold_adapts": "faint texture is now always found (Shi-Tomasi at half resolution when FAST finds too few); remove the key",
    }

    max_features: int = bounded(250, "tracks kept per frame (the detector tops up to this)", gt=0, le=5000)
    grid_cols: int = bounded(8, "detection grid columns (features are spread over the cells)", gt=0, le=64)
    grid_rows: int = bounded(6, "detection grid rows", gt=0, le=64)
    fast_threshold: int = bounded(
        20,
        "FAST intensity threshold, grey levels (halved, but not below 4 noise sigmas, for a frame that yields too few; then Shi-Tomasi at half resolution)",
        gt=0,
        lt=255,
    )
    min_distance_px: float = bounded(
        12.0, "no new corner closer than this to a track or another new corner (at reference_width_px)", gt=0, le=500
    )
    reference_width_px: int = bounded(
        640, "the image width the pixel settings are given for; other widths scale them", ge=32, le=16384
    )
    redetect_fraction: float = bounded(
        0.8, "detect new corners when fewer than this fraction of max_features survive", gt=0, le=1
    )
    klt_window_px: int = bounded(15, "Lucas-Kanade window side (at reference_width_px; at least 11)", ge=5, le=101)
    klt_levels: int = bounded(
        3, "pyramid levels above the full image (at reference_width_px; one fewer per halving)", ge=0, le=6
    )
    klt_iterations: int = bounded(20, "Lucas-Kanade iterations per level", gt=0, le=1000)
    klt_highpass_px: int = bounded(
        33,
        "KLT follows the image minus its mean over a box this many pixels wide (not scaled: it spans the texture a window sees), so that brightness the camera adds (vignetting, exposure offsets) does not drag the tracks; 0: the raw image",
        ge=0,
        le=1001,
    )
    klt_highpass_below: float = bounded(
        8.0,
        "the high-pass is used only on faint texture: where the image's local contrast (RMS of the image less its box mean, grey levels) is below this; on strong texture the scene's coarse structure, which the filter takes out, matters more (a fast climb's zoom); 0: never",
        ge=0,
        le=255,
    )
    fb_max_px: float = bounded(
        0.5,
        "largest forward-backward round-trip error of a surviving track (a jump to the next square of a repeated pattern comes back a whole period off)",
        gt=0,
        le=50,
    )
    fb_max_faint_px: float = bounded(
        1.0,
        "the same where the texture is faint (below klt_highpass_below): KLT's own scatter is larger there, and a tighter bound kills tracks that are right (docs/odometry.md, Small-quad flights)",
        gt=0,
        le=50,
    )
    klt_back_levels: int = bounded(
        0,
        "pyramid levels of the backward check, which starts at the tracks' old positions (0: full resolution only, a third of the forward cost)",
        ge=0,
        le=6,
    )
    consensus_max_px: float = bounded(
        8.0,
        "a track ending further than this from where the pair's consensus motion (an affine map fitted robustly to all surviving tracks) puts it is dropped: a jump to the next identical square of a repeated pattern passes the round trip (at reference_width_px); 0: no check",
        ge=0,
        le=500,
    )
    consensus_min_share: float = bounded(
        0.2,
        "the check drops tracks only when at least this share of the pair's tracks is off the consensus: where the scene has depth (a forward camera) the parallax puts a few tracks off an affine map, never this many (docs/odometry.md, Repeated patterns)",
        ge=0,
        le=1,
    )
    border_px: int = bounded(8, "tracks this close to the image edge are dropped (at reference_width_px)", ge=0, le=500)


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


def noise_sigma(img: np.ndarray) -> float:
    """Sensor noise of a grey image, 1 sigma in grey levels (Immerkaer 1996: the mean absolute response to
    a mask that cancels smooth structure, sqrt(pi/2) / (6 (W-2)(H-2)) sum |I * N|)."""
    r = cv2.filter2D(img.astype(np.float32), -1, _NOISE_MASK, borderType=cv2.BORDER_ISOLATED)[1:-1, 1:-1]
    return float(math.sqrt(math.pi / 2.0) * np.abs(r).mean() / 6.0)


def _image_noise_sigma(img: np.ndarray) -> float:
    """:func:`noise_sigma` of the image's central quarter (within 0.02 of the whole image's on
    indoor_hops' frames, at a quarter of the cost), at least what rounding leaves."""
    h, w = img.shape
    return max(noise_sigma(img[h // 4 : h - h // 4, w // 4 : w - w // 4]), _QUANTISATION_SIGMA)


_EIG_BLOCK = 5  # Shi-Tomasi block at half resolution: 10 px of the image
_EIG_OVER_NOISE = 5.0  # a corner's smallest eigenvalue over noise alone's median (its 99.9th percentile: 3)


@lru_cache(maxsize=1)
def _eig_per_noise_var() -> float:
    """Median of :func:`_half_res_min_eig` over Gaussian noise of unit variance (its value for noise
    alone; it scales with the variance)."""
    rng = np.random.default_rng(20101005)
    img = np.clip(128.0 + 8.0 * rng.standard_normal((240, 320)) + 0.5, 0, 255).astype(np.uint8)
    return float(np.median(_half_res_min_eig(img))) / 64.0


def _half_res_min_eig(img: np.ndarray) -> np.ndarray:
    return cv2.cornerMinEigenVal(cv2.pyrDown(img), _EIG_BLOCK, 3)


def _min_eigen_corners(img: np.ndarray, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """Shi-Tomasi corners found at half resolution: (M,2) float32 full-resolution pixels and their
    strength. Halving averages the noise away but keeps a faint texture's structure."""
    e = _half_res_min_eig(img)
    peak = (e == cv2.dilate(e, np.ones((3, 3), np.uint8))) & (e > _EIG_OVER_NOISE * _eig_per_noise_var() * noise**2)
    v, u = np.nonzero(peak)
    pts = np.column_stack([2.0 * u, 2.0 * v]).astype(np.float32)  # pyrDown centres dst(x, y) on src(2x, 2y)
    return pts, e[v, u].astype(np.float32)


def local_contrast(img: np.ndarray, box_px: int) -> float:
    """RMS of the image less its mean over a ``box_px`` box, grey levels, measured on every 4th pixel
    of every 4th row (a box a quarter as wide there): the texture's own contrast, what the brightness
    the camera adds is to be weighed against (docs/odometry.md has what floors and scenes measure)."""
    small = np.ascontiguousarray(img[::4, ::4])
    k = max((box_px // 4) | 1, 3)
    mean = cv2.blur(small, (k, k), borderType=cv2.BORDER_REFLECT)
    # On every frame: the squared difference summed in one OpenCV pass, no difference image.
    return math.sqrt(cv2.norm(small, mean, cv2.NORM_L2SQR) / small.size)


def _noise_floor(noise: float) -> int:
    """The lowest FAST threshold that does not find corners in noise of ``noise`` sigma (grey levels)."""
    return max(_MIN_THRESHOLD, math.ceil(_NOISE_CORNER_SIGMAS * noise))


class Frontend:
    """Tracks features through a sequence of 8-bit grey images of one camera (see the module docstring)."""

    def __init__(self, camera: CameraModel, options: FrontendOptions | None = None) -> None:
        self.camera = camera
        self.options = opt = options or FrontendOptions()
        # Pixel settings follow the image's size: a 320x240 camera sees the same scene in half the pixels.
        s = camera.width_px / opt.reference_width_px
        self.min_distance_px = max(opt.min_distance_px * s, _MIN_SPACING_PX)
        win = max(int(round(opt.klt_window_px * s)) | 1, min(_MIN_WINDOW_PX, opt.klt_window_px))
        self._win = (win, win)
        self.klt_levels = max(opt.klt_levels + int(round(math.log2(s))), min(opt.klt_levels, 1))
        self.border_px = int(round(opt.border_px * s))
        self.consensus_max_px = opt.consensus_max_px * s
        self._highpass = max(opt.klt_highpass_px | 1, 3) if opt.klt_highpass_px > 0 else 0
        self._fast = cv2.FastFeatureDetector_create(opt.fast_threshold, True)
        self._fast_low = cv2.FastFeatureDetector_create(max(opt.fast_threshold // 2, 1), True)  # set per frame
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, opt.klt_iterations, 0.03)
        self._per_cell = max(1, -(-opt.max_features // (opt.grid_cols * opt.grid_rows)))
        self._next_id = 0
        self.dropped_unmappable = 0  # tracks dropped because their pixel has no bearing
        self.reset()

    def reset(self) -> None:
        """Forget all tracks (ids keep increasing)."""
        self._prev: np.ndarray | None = None
        self._prev_fit: np.ndarray | None = None  # the previous image filtered for KLT, when it was
        self._ids = np.zeros(0, np.int64)
        self._uv = np.zeros((0, 2), np.float32)

    def process(self, image: np.ndarray) -> Tracks:
        """Track into ``image`` ((H,W) uint8, the camera's size) and top up with new corners."""
        img = self._check(image)
        ids, uv = self._ids, self._uv
        fit = None
        if self._prev is not None and len(uv):
            # Both images of a pair the same way: filtered where this frame's texture is faint.
            pair, fb_max_px = (self._prev, img), self.options.fb_max_px
            if self._highpass and local_contrast(img, self._highpass) < self.options.klt_highpass_below:
                fit = self._klt_image(img)
                pair = (self._prev_fit if self._prev_fit is not None else self._klt_image(self._prev), fit)
                fb_max_px = self.options.fb_max_faint_px
            keep, uv = self._track(*pair, uv, fb_max_px)
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
        self._prev_fit = fit
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

    def _klt_image(self, img: np.ndarray) -> np.ndarray:
        """What KLT follows: twice the image less its local mean (a box of ``klt_highpass_px``), on mid-grey.

        Lucas-Kanade matches brightness, so brightness that does not move with the scene (the
        vignetting's ramp, scaled by exposure steps) pulls a track toward standing still; on a faint
        floor the flow near the edges came out short, and the tilt the relative pose fitted to that
        shortfall put the translations' scale off (docs/odometry.md, "What the camera adds"). A box's
        mean leaves a linear ramp out exactly and an exposure step's offset too, and costs two passes at
        any box size. The box is the same number of pixels at any image width: it has to span a few KLT
        windows and the texture they follow, not a share of the image.
        """
        mean = cv2.blur(img, (self._highpass, self._highpass), borderType=cv2.BORDER_REFLECT)
        return cv2.addWeighted(img, _HIGHPASS_GAIN, mean, -_HIGHPASS_GAIN, 128.0)

    def _track(
        self, prev: np.ndarray, cur: np.ndarray, uv0: np.ndarray, fb_max_px: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Forward and backward KLT, a round trip within ``fb_max_px``; (surviving mask over uv0, their
        new positions)."""
        opt = self.options
        p0 = uv0.reshape(-1, 1, 2)
        lk = dict(winSize=self._win, maxLevel=self.klt_levels, criteria=self._criteria)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, **lk)
        # Backward from the forward result, started at the original positions: a consistent track
        # converges there without the coarse levels (the same keep/drop decision for 99.96% of the
        # tracks of a survey flight as with all levels, at a third of the cost); one that is not
        # stays off and is dropped.
        lk["maxLevel"] = min(opt.klt_back_levels, self.klt_levels)
        p0b, st0, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        p1 = p1.reshape(-1, 2)
        d = p0b.reshape(-1, 2) - uv0
        fb = np.hypot(d[:, 0], d[:, 1])
        h, w = cur.shape
        b = self.border_px
        inside = (p1[:, 0] >= b) & (p1[:, 0] <= w - 1 - b) & (p1[:, 1] >= b) & (p1[:, 1] <= h - 1 - b)
        keep = (st1.ravel() == 1) & (st0.ravel() == 1) & (fb < fb_max_px) & inside
        if self.consensus_max_px > 0 and np.count_nonzero(keep) >= _MIN_CONSENSUS_TRACKS:
            off = off_affine_consensus(uv0, p1, keep, self.consensus_max_px)
            if np.count_nonzero(off & keep) >= opt.consensus_min_share * np.count_nonzero(keep):
                keep &= ~off
        return keep, p1.compress(keep, axis=0)

    def _cell(self, uv: np.ndarray, w: int, h: int) -> np.ndarray:
        """(N,) index of each pixel's detection-grid cell."""
        gc, gr = self.options.grid_cols, self.options.grid_rows
        return np.minimum((uv[:, 1] * gr / h).astype(int), gr - 1) * gc + np.minimum(
            (uv[:, 0] * gc / w).astype(int), gc - 1
        )

    def _candidates(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corner candidates (M,2) float32 pixels and their strengths (M,), comparable among themselves
        (see the module docstring for the detector that gives them)."""
        want = self.options.max_features
        kps = self._fast.detect(img)
        if len(kps) < want:
            noise = _image_noise_sigma(img)
            low = max(self.options.fast_threshold // 2, _noise_floor(noise))
            if low < self.options.fast_threshold:
                self._fast_low.setThreshold(low)
                kps = self._fast_low.detect(img)
            if len(kps) < want:
                return _min_eigen_corners(img, noise)
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        return pts, np.array([k.response for k in kps], np.float32)

    def _detect(self, img: np.ndarray, live_uv: np.ndarray) -> np.ndarray:
        """New corners in cells short of their share, away from live tracks: (M,2) float32."""
        opt = self.options
        h, w = img.shape
        b = max(self.border_px, 3)
        pts, resp = self._candidates(img)
        if len(pts) == 0:
            return np.zeros((0, 2), np.float32)
        ok = (pts[:, 0] >= b) & (pts[:, 0] <= w - 1 - b) & (pts[:, 1] >= b) & (pts[:, 1] <= h - 1 - b)
        pts, resp = pts[ok], resp[ok]

        # Fine occupancy grid (cell = min distance): a cell next to a live track is taken.
        d = self.min_distance_px
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
