"""Height anchored where a height is measured: a downward rangefinder's tilt-compensated range as a
measurement of the down coordinate.

Vision fixes each translation's length from the range (:mod:`mavvo.odometry.scale`), but the down
coordinate it sends is still a sum of those translations: every scale error and every re-initialisation
that dead-reckons adds to it (on a real small quad at 0.3-1.5 m, 0.8-1.4 m of drift in 30 s with the
range paired to 90% of the frames). Here the range measures it directly, over flat ground:

    h = r cos(roll) cos(pitch)              the rangefinder looks along body z: height above the ground
    z_down = g - h                          g: the ground's down coordinate in the world frame

``g`` is taken when tracking starts (the anchor's down coordinate plus the height then) and kept; a
restart after tracking was lost starts at ``g - h`` rather than at a dead-reckoned height. Each frame
with a range has sigma ``range_sigma_m + range_sigma_per_m * h`` (the sensor's noise, plus what a tilt
error and an uneven floor add with height).

While vision tracks, its down coordinate is its keyframe's plus a relative part that is millimetre-tight;
what drifts is the keyframe's down, fixed when the keyframe was made and repeated by every frame measured
from it. So the range corrects the keyframe, a scalar Kalman filter on its down coordinate relative to the
ground with variance ``P`` (``keyframe_var_m2``: a range's sigma^2 when the ground is taken or after a
restart, the filter's after a coast, plus each new keyframe's vertical measurement variance)::

    y = (g - h) - z                     innovation against the frame's down (the keyframe's, through vision)
    S = P + sigma^2, gated with one degree of freedom
    K = P / S;  dz = K y;  P = (1 - K) P
    keyframe and filter moved down by dz; then the range updates the filter (its covariance)

While the keyframe the ground was taken from lasts, it defines the frame: ``g`` moves instead
(``g -= K y``), which makes it the ranges' inverse-variance weighted mean rather than the first range.

While vision is lost (coasting), the range is fused into the filter directly (``PoseFilter.update_down``,
gated). A single range that disagrees (a glitch) is rejected. ``step_frames`` in a row that began
with the range jumping by 0.1 m or more from the reading before are the ground itself stepping (a table,
a kerb, a roof: no vehicle moves that far in one frame): ``g`` moves by the step, so the vehicle does
not. A run that began smoothly means the estimate drifted or lagged beyond what its variance allowed:
the range wins, the down coordinate is set to it and the caller moves the keyframe by as much.
Tilted beyond ``max_tilt_deg`` the beam may miss the ground under the vehicle: not used.
Without a range the down coordinate behaves as before.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from mavvo.odometry.filter import PoseFilter, Update
from mavvo.options import bounded

__all__ = ["HeightOptions", "HeightAnchor"]

log = logging.getLogger(__name__)

_STEP_MIN_M = 0.1  # a ground step shows as the range jumping this much from one reading to the next


@dataclass(frozen=True)
class HeightOptions:
    """The ``odometry.height`` keys."""

    from_range: bool = bounded(
        True, "fuse the downward rangefinder's tilt-compensated range as a measurement of height"
    )
    range_sigma_m: float = bounded(0.03, "its noise, 1 sigma ...", gt=0, le=10)
    range_sigma_per_m: float = bounded(
        0.01, "... plus this much per metre of height (tilt error, uneven floor)", ge=0, le=1
    )
    step_frames: int = bounded(
        5,
        "this many ranges in a row that disagree with the height: the ground stepped (a table, a kerb)",
        ge=1,
        le=1000,
    )
    max_tilt_deg: float = bounded(
        30.0, "tilted more than this, the beam may miss the ground below: not used", gt=0, le=80
    )


class HeightAnchor:
    """The ground's down coordinate ``ground_down_m`` and the height measurements fused against it."""

    def __init__(self, options: HeightOptions | None = None) -> None:
        self.options = options or HeightOptions()
        self.ground_down_m: float | None = None
        self._disagree = 0
        self._last_height_m: float | None = None
        self._jump_m = 0.0  # the range's change at the frame a run of disagreement began
        self.steps = 0  # the ground stepped (counted)
        self.correction_m = 0.0  # how far this frame's range moved the down coordinate (and the keyframe)
        self.keyframe_var_m2 = 0.0  # variance of the current keyframe's down coordinate (relative to g), m^2
        self._ground_moves = False  # the current keyframe is the one g was taken from: the range refines g

    def height_m(self, range_m: float | None, roll_rad: float, pitch_rad: float) -> float | None:
        """Height above the ground from a range along body z, or None (no range, too tilted)."""
        if range_m is None or not math.isfinite(range_m) or range_m <= 0:
            return None
        c = math.cos(roll_rad) * math.cos(pitch_rad)
        if c < math.cos(math.radians(self.options.max_tilt_deg)):
            return None
        return range_m * c

    def start(self, down_m: float, height_m: float | None, *, first: bool) -> float:
        """Tracking starts (``first``) or restarts at ``down_m`` with ``height_m`` measured (None: no
        range): the down coordinate to start at. The first start takes the ground from it; a restart
        keeps the ground (it has not moved because tracking was lost) and starts at the measured height,
        not at the dead-reckoned or the flight controller's down coordinate."""
        self._disagree, self._last_height_m = 0, height_m
        self._ground_moves = False
        if height_m is None or not self.options.from_range:
            if first:
                self.ground_down_m = None
            return down_m
        if first or self.ground_down_m is None:
            self._take_ground(down_m, height_m)
            return down_m
        self.keyframe_at(self._sigma_m(height_m) ** 2)
        return self.ground_down_m - height_m

    def keyframe_pushed(self, added_var_m2: float) -> None:
        """A new keyframe, its down coordinate off the old one's by a variance ``added_var_m2``."""
        self.keyframe_var_m2 += added_var_m2
        self._ground_moves = False

    def keyframe_at(self, var_m2: float) -> None:
        """A new chain's keyframe (after a coast or a restart) with a down coordinate of variance ``var_m2``."""
        self.keyframe_var_m2 = var_m2
        self._ground_moves = False

    def _take_ground(self, down_m: float, height_m: float) -> None:
        """The ground from one range at the current keyframe, whose down coordinate defines the frame:
        as uncertain as that range, refined by the next ones while the keyframe lasts."""
        self.ground_down_m = down_m + height_m
        self.keyframe_var_m2 = self._sigma_m(height_m) ** 2
        self._ground_moves = True

    def _sigma_m(self, height_m: float) -> float:
        return self.options.range_sigma_m + self.options.range_sigma_per_m * height_m

    def fuse(self, flt: PoseFilter, height_m: float | None, *, tracking: bool = False) -> Update | None:
        """Fuse one frame's height into ``flt`` (already predicted to the frame's time; with ``tracking``,
        updated with vision's measurement from the keyframe, whose down ``correction_m`` then says how far
        to move): FUSED, REJECTED (a glitch, or the ground stepped), RESTARTED (the range won: the down
        coordinate was set to it), or None (no height to fuse)."""
        if height_m is None or not self.options.from_range:
            return None
        if self.ground_down_m is None:  # the first range after a start
            self._take_ground(float(flt.position_ned_m[2]), height_m)
            return None
        sigma = self._sigma_m(height_m)
        previous, self._last_height_m = self._last_height_m, height_m
        self.correction_m = 0.0
        down_m = self.ground_down_m - height_m
        if tracking:
            y = down_m - float(flt.position_ned_m[2])
            S = self.keyframe_var_m2 + sigma**2
            if y * y / S <= flt.gate(1):
                K = self.keyframe_var_m2 / S
                self.keyframe_var_m2 *= 1.0 - K
                self._disagree = 0
                if self._ground_moves:  # the keyframe defines the frame: the ground is what is off
                    self.ground_down_m -= K * y
                    return Update.FUSED
                self.correction_m = K * y
                flt.shift_down(self.correction_m)
                flt.update_down(down_m, sigma, gated=False)
                return Update.FUSED
        elif flt.update_down(down_m, sigma) is Update.FUSED:
            self._disagree = 0
            return Update.FUSED
        if self._disagree == 0:  # how the range moved as the disagreement began
            self._jump_m = 0.0 if previous is None else height_m - previous
        self._disagree += 1
        if self._disagree < self.options.step_frames:
            return Update.REJECTED
        self._disagree = 0
        if abs(self._jump_m) >= _STEP_MIN_M:  # the range jumped and stayed: the ground moved, not the vehicle
            new = float(flt.position_ned_m[2]) + height_m
            log.info("the ground under the rangefinder stepped by %+.2f m", self.ground_down_m - new)
            self.ground_down_m = new
            self.keyframe_var_m2 += sigma**2  # the new ground is as good as one range
            self.steps += 1
            return Update.REJECTED
        # The range moved smoothly away from the estimate: the estimate lagged or drifted. The range wins.
        self.correction_m = self.ground_down_m - height_m - float(flt.position_ned_m[2])
        flt.set_down(self.ground_down_m - height_m, sigma)
        self.keyframe_at(sigma**2)
        return Update.RESTARTED
