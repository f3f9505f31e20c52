"""Keyframes: when to make one, what it keeps, and the chain of their poses in the world frame.

Every frame is measured against the current keyframe, so the error of a frame does not pass to the
next one; only a keyframe switch commits an error to the chain. A new keyframe is made from a frame
whose pose was accepted when

- the median rotation-compensated parallax against the keyframe reaches ``parallax_px`` (the baseline
  is long enough; longer ones lose tracks), or
- fewer than ``min_survival`` of the keyframe's tracks are left, or
- the relative pose has fewer than ``min_inliers`` inliers, or
- the camera moved along the keyframe's mean line of sight by more than ``max_depth_change`` of the
  scene's depth: in a fast climb the image zooms, tracks survive and the rotation-compensated
  parallax of the points near the centre stays small, so one keyframe would last a large zoom; KLT
  follows a patch's shift, not its scale, and the relative yaws over such pairs go wrong
  (docs/odometry.md, Keyframes).

Poses: a keyframe stores its camera position ``p_ned_m`` and the heading ``yaw_rad`` of its level
frame in the world frame (NED). A frame at ``c2`` (its camera centre in the keyframe's level frame,
metres) with relative yaw ``yaw_2_1`` (``R_2_1 = Rz(yaw_2_1)``) is at
``p = p_kf + Rz(yaw_kf) @ c2`` with heading ``yaw_kf - yaw_2_1``; a new keyframe takes that pose,
so the chain stays in one continuous frame.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from mavvo.geometry.frames import rot_z
from mavvo.options import bounded

__all__ = [
    "KeyframeOptions",
    "Keyframe",
    "KeyframePose",
    "KeyframeChain",
    "keyframe_reason",
    "sight_change",
    "carry_depths",
]


@dataclass(frozen=True)
class KeyframeOptions:
    """When a frame becomes the new keyframe (see the module docstring)."""

    parallax_px: float = bounded(40.0, "median rotation-compensated parallax against the keyframe", gt=0, le=2000)
    min_survival: float = bounded(0.5, "fraction of the keyframe's tracks still alive", gt=0, lt=1)
    min_inliers: int = bounded(60, "inliers of the relative pose", ge=0, le=5000)
    max_depth_change: float = bounded(
        0.25,
        "the camera moved toward or away from the scene by this fraction of its depth (a climb's zoom)",
        gt=0,
        le=100,
    )
    held_level_below_m: float = bounded(
        5.0,
        "while the scene is nearer than this, a new keyframe holds its level frame as exact and sits where its frame was measured (docs/odometry.md, Close range; 0: never), metres",
        ge=0,
        le=1000,
    )
    held_level_release: float = bounded(
        1.4,
        "once held, the keyframes let go only where the scene is farther than this many times held_level_below_m (depths triangulated from a few pixels of parallax wander by half)",
        ge=1,
        le=100,
    )
    history: int = bounded(1000, "keyframe poses kept for inspection", ge=1, le=100000)


@dataclass(frozen=True)
class Keyframe:
    """One keyframe.

    Attributes:
        seq, t_s: the frame's sequence number and exposure time.
        ids: (N,) int64 track ids, increasing.
        f_lvl: (N,3) their unit bearings in the keyframe's level frame.
        depth_m: (N,) metric depth along each bearing where known (carried scale), else NaN.
        p_ned_m: (3,) camera position in the world frame (NED, m).
        yaw_rad: heading of the keyframe's level frame in the world frame.
        fc_yaw_rad: the flight controller's yaw at this frame (NaN if unknown).
        attitude_sigma_rad: the roll/pitch uncertainty of its level frame (1 sigma), what the relative
            pose's attitude prior takes for this view.
        unmeasured_m: how far it may be from where it is placed by translations the images did not
            resolve (1 sigma, m): keyframes made in a turn on the spot stay where the last one was,
            each within what its parallax could hide, and that adds up until a translation is measured.
    """

    seq: int
    t_s: float
    ids: np.ndarray
    f_lvl: np.ndarray
    depth_m: np.ndarray
    p_ned_m: np.ndarray
    yaw_rad: float
    fc_yaw_rad: float
    attitude_sigma_rad: float = 0.0
    unmeasured_m: float = 0.0

    def match(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices (into this keyframe, into ``ids``) of the tracks both have; both id arrays increasing (as :class:`~mavvo.odometry.frontend.Tracks` gives them)."""
        # Both increasing: where each current id would go among the keyframe's, kept where it is there.
        pos = np.searchsorted(self.ids, ids)
        found = pos < len(self.ids)
        found[found] = self.ids[pos[found]] == ids[found]
        return pos[found], np.flatnonzero(found)

    def pose_of(self, c2_lvl_m: np.ndarray, yaw_2_1_rad: float) -> tuple[np.ndarray, float]:
        """World (position, heading) of a frame at ``c2_lvl_m`` with relative yaw ``yaw_2_1_rad``."""
        return self.p_ned_m + rot_z(self.yaw_rad) @ c2_lvl_m, self.yaw_rad - yaw_2_1_rad


@dataclass(frozen=True)
class KeyframePose:
    """A keyframe's place in the chain: sequence number, time, camera position (NED, m), heading."""

    seq: int
    t_s: float
    p_ned_m: np.ndarray
    yaw_rad: float
    reset_counter: int


def sight_change(f1_lvl: np.ndarray, c2_m: np.ndarray, depth_m: float) -> float:
    """How far the camera moved along the keyframe's mean line of sight, over the scene's depth:
    ``c2 . mean(f1) / (|mean(f1)| depth)`` for the keyframe's bearings ``f1_lvl`` (N,3) matched now and
    the frame's camera centre ``c2_m`` (3,) in the keyframe's level frame (positive: toward the scene)."""
    sight = f1_lvl.sum(axis=0)
    n = float(np.linalg.norm(sight))
    return float(c2_m @ sight) / (n * depth_m) if n > 0 and depth_m > 0 else 0.0


def keyframe_reason(
    options: KeyframeOptions, *, parallax_px: float, survival: float, inliers: int, depth_change: float = 0.0
) -> str:
    """Why the current frame should become the keyframe: ``parallax``, ``survival``, ``inliers``,
    ``depth`` or ''. ``depth_change``: the camera's move along the keyframe's mean line of sight over
    the scene's depth."""
    if parallax_px >= options.parallax_px:
        return "parallax"
    if survival < options.min_survival:
        return "survival"
    if inliers < options.min_inliers:
        return "inliers"
    if abs(depth_change) > options.max_depth_change:
        return "depth"
    return ""


def carry_depths(
    kf: Keyframe,
    i_kf: np.ndarray,
    i_cur: np.ndarray,
    n_cur: int,
    R_2_1: np.ndarray,
    t_2_1_m: np.ndarray,
    new_depth_m: np.ndarray,
    new_parallax_rad: np.ndarray,
    min_parallax_rad: float,
) -> np.ndarray:
    """Metric depths for a new keyframe made from the current frame.

    Args:
        kf: the old keyframe; ``i_kf``, ``i_cur`` the matched indices (into kf and into the current
            frame's ``n_cur`` tracks).
        R_2_1, t_2_1_m: the metric relative pose from the old keyframe to the current frame.
        new_depth_m: (len(i_kf),) metric depths along the current bearings triangulated in this pair
            (NaN where not triangulated); ``new_parallax_rad`` their parallax.
        min_parallax_rad: a new depth with less parallax than this is too uncertain to carry.

    Returns:
        (n_cur,) depths: the new triangulation where its parallax is at least ``min_parallax_rad``;
        else the old keyframe's depth moved into the new frame (this carries scale through a pure
        rotation); NaN elsewhere.
    """
    out = np.full(n_cur, np.nan)
    old = kf.depth_m[i_kf]
    X2 = (old[:, None] * kf.f_lvl[i_kf]) @ R_2_1.T + t_2_1_m
    moved = np.linalg.norm(X2, axis=1)  # NaN where the old depth is unknown
    use_new = np.isfinite(new_depth_m) & (new_parallax_rad >= min_parallax_rad)
    out[i_cur] = np.where(use_new, new_depth_m, moved)
    return out


class KeyframeChain:
    """The current keyframe and the poses of the last ``history`` keyframes."""

    def __init__(self, options: KeyframeOptions | None = None) -> None:
        self.options = options or KeyframeOptions()
        self.current: Keyframe | None = None
        self.poses: deque[KeyframePose] = deque(maxlen=self.options.history)
        self.count = 0

    def push(self, kf: Keyframe, reset_counter: int) -> None:
        """Make ``kf`` the current keyframe."""
        self.current = kf
        self.count += 1
        self.poses.append(KeyframePose(kf.seq, kf.t_s, kf.p_ned_m.copy(), kf.yaw_rad, reset_counter))

    def shift_down(self, delta_m: float) -> None:
        """Move the current keyframe down by ``delta_m`` (its height was corrected by a measurement):
        every later frame is measured from it, so it carries the correction on."""
        if self.current is not None:
            p = self.current.p_ned_m.copy()
            p[2] += delta_m
            self.current = replace(self.current, p_ned_m=p)

    def drop(self) -> None:
        """Lose the current keyframe (tracking lost); the history stays."""
        self.current = None
