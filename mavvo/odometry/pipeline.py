"""The visual odometry: paired frames in, filtered metric NED poses out.

:meth:`Odometry.step` takes one :class:`mavvo.types.PairedFrame` (image, roll/pitch at exposure,
optionally the flight controller's yaw, rangefinder and height) and returns a
:class:`mavvo.types.PoseEstimate`. It is pure: no threads, sockets or clocks; the same frames give the
same estimates (RANSAC is seeded with the frame's sequence number).

Per frame: track features (:mod:`mavvo.odometry.frontend`), move a rolling shutter's to the frame's time
(:mod:`mavvo.odometry.rolling_shutter`), derotate their bearings with the given roll/pitch, estimate yaw and
translation direction against the keyframe with the 3-point RANSAC (:mod:`mavvo.estimation.relpose`), fix
the baseline in metres (:mod:`mavvo.odometry.scale`), place the frame in the world frame through the
keyframe (:mod:`mavvo.odometry.keyframes`), and smooth (:mod:`mavvo.odometry.filter`).
A frame that becomes the keyframe is placed where the filter puts it, its carried depths scaled to
that baseline, unless it is degraded for another reason than a scale that is not metric
(:func:`mavvo.odometry.measurement.keyframe_position`).

World frame: the flight controller's local NED frame, so that what is sent needs no alignment. The
first keyframe is placed where the flight controller believes the vehicle is
(``PairedFrame.fc_position_ned_m``; the origin when it says nothing) with its yaw (0 when it sends
none); afterwards vision carries position and heading. Vision's yaw drifts slowly; a compass's does not
but is disturbed in flight (the motors' current, the EKF's in-flight yaw alignment), and then vision's is
the better of the two. So the heading is pulled toward the flight controller's yaw
(:mod:`mavvo.odometry.heading`) only when ``heading_source`` says that yaw is clean: by default while
the flight controller is disarmed, which takes north on the ground before take-off, and in flight only
while its yaw agrees with vision's within a gate that widens with vision's uncertainty (a compass the
motors turn by degrees is left alone; an undisturbed one keeps vision's slow drift in check).

States: ``initialising`` (a keyframe was just made: the pose is the anchor), ``tracking``,
``degraded`` (a pose, trusted less: pure rotation, no metric scale source, few inliers; quality at most
``degraded_quality_max``) and ``failed`` (no pose from vision; the estimate is the filter's prediction,
quality -1, not to be sent). Tracking is lost when fewer than ``min_tracks`` of the keyframe's tracks
survive, or after ``max_failed_frames`` frames in a row without a pose; meanwhile the filter coasts (the
tilt's acceleration, the range's height). The next frame with enough features goes on from where the
filter coasted to after at most ``coast_max_s``, else re-initialises (:mod:`mavvo.odometry.recovery`):
at the flight controller's own estimate (no step for its EKF: the stream keeps its sigma while
``anchor_sigma_m`` goes into the drift) or a dead-reckoned or held pose with the uncertainty it has.
Every change of the position that is not motion (a re-initialisation, a filter restart) bumps
``reset_counter`` exactly once.

A camera that does not move keeps measuring its position: with under a pixel of median parallax and nothing
to triangulate the frame is where its keyframe is, within the baseline a pixel at the scene's depth allows.

``PoseEstimate.drift_m`` is the 1-sigma long-term error since the origin: anchor uncertainties plus
``drift_per_m`` of the distance flown and the heading uncertainty times the distance from the anchor.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from mavvo.estimation.relpose import estimate_upright_relpose
from mavvo.estimation.relpose_types import RelposeFailure, UprightRelpose
from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.frames import R_from_euler321, R_lvl_body, R_lvl_cam, as_rotation, euler321_from_R, skew
from mavvo.geometry.medians import median
from mavvo.geometry.refine import tilt_rotation
from mavvo.odometry.filter import PoseFilter, Update, wrap_angle
from mavvo.odometry.frontend import Frontend, Tracks
from mavvo.odometry.heading import HeadingChain, relative_yaw_var
from mavvo.odometry.height import HeightAnchor
from mavvo.odometry.keyframes import Keyframe, KeyframeChain, carry_depths, keyframe_reason, sight_change
from mavvo.odometry.measurement import (
    UNTRUSTED_SCALE_REASON,
    Measurement,
    NoPose,
    keyframe_position,
    position_noise,
    unresolved_baseline_m,
)
from mavvo.odometry.options import OdometryOptions
from mavvo.odometry.recovery import Drift, GoodPose, coast_sigma_m, heading_now_rad, reinit_anchor, velocity_sigma_m_s
from mavvo.odometry.rolling_shutter import RollingShutter
from mavvo.odometry.scale import ScaleEstimate, estimate_scale, scale_from_scene_depth, triangulate_unit
from mavvo.odometry.tilt_motion import TiltMotion
from mavvo.types import PairedFrame, PoseEstimate, ScaleSource, StateReason, VisionState, VoDiagnostics

__all__ = ["Odometry"]

log = logging.getLogger(__name__)

_TRUSTED_SCALE = frozenset({ScaleSource.RANGEFINDER, ScaleSource.ALTITUDE, ScaleSource.FIXED, ScaleSource.CARRIED})
# No parallax and less turn than this against the keyframe: standing still, not a degraded pure rotation.
_STATIONARY_YAW_RAD = math.radians(2.0)
# A held level frame's roll/pitch sigma (keyframes.held_level_below_m): the relative pose then corrects
# the frame's view, not the keyframe's. 0.05 deg already gave back most of the carpet's gain (docs/odometry.md).
_HELD_LEVEL_SIGMA_RAD = math.radians(0.01)


class Odometry:
    """Visual odometry for one camera (see the module docstring).

    Args:
        camera: intrinsics and distortion of the images.
        R_body_cam: (3,3) camera mounting, camera vectors into the body frame (FRD).
        options: :class:`OdometryOptions`.
        reset_counter: the first ``reset_counter`` (0..255): one the flight controller has not seen
            from this service, so that a restarted service's first estimate counts as a reset.
        readout_s: a rolling shutter's top-to-bottom readout time (0: a global shutter).
    """

    def __init__(
        self,
        camera: CameraModel,
        R_body_cam: np.ndarray,
        options: OdometryOptions | None = None,
        reset_counter: int = 0,
        readout_s: float = 0.0,
    ) -> None:
        self.camera = camera
        self.R_body_cam = as_rotation("R_body_cam", R_body_cam)
        self.options = opt = options or OdometryOptions()
        self.frontend = Frontend(camera, opt.frontend)
        self._rolling = RollingShutter(camera, readout_s)
        self.chain = KeyframeChain(opt.keyframes)
        self.filter = PoseFilter(opt.filter)
        self.height = HeightAnchor(opt.height)
        self._height_fused = False  # this frame's range was fused: a keyframe made from it takes the filter's down
        self._focal_px = 0.5 * (camera.fx_px + camera.fy_px)
        self._max_err_rad = opt.ransac.max_err_px / self._focal_px
        self._min_parallax_rad = math.radians(opt.scale.min_parallax_deg)
        self._carry_min_parallax_rad = math.radians(opt.scale.carry_min_parallax_deg)
        self._yaw_sigma_rad = math.radians(opt.yaw_sigma_deg)
        self.heading = HeadingChain(opt)
        self._att_sigma_rad = math.radians(opt.attitude_sigma_deg)
        if not 0 <= reset_counter <= 255:
            raise ValueError(f"reset_counter: expected 0..255, got {reset_counter}")
        self.reset_counter = reset_counter
        self._drift = Drift()
        self._heading_sigma_rad = math.radians(opt.heading_sigma_deg)
        self._good: GoodPose | None = None
        self._tilt = TiltMotion()
        self._outage_s = -math.inf  # the first frame of the last outage: the filter took the tilt's velocity there
        self._may_coast = False  # a pose was accepted since the last start and no restart was asked for
        self._failed_in_row = 0
        self._metric_interval = False  # a trusted scale has been carried into the current keyframe
        self._scene_depth_m: float | None = None
        self._last_yaw_2_1 = 0.0  # yaw of the last frame against the keyframe: the yaw prior without the FC's

    # ----------------------------------------------------------------------------------------------
    def restart(self) -> None:
        """Give up the current keyframe: the next frame re-initialises (anchored as after a long loss)."""
        self.chain.drop()
        self._failed_in_row, self._may_coast = 0, False

    def track(self, image: np.ndarray) -> Tracks:
        """Track features into ``image``: for a frame that has no attitude (a short gap in the flight
        controller's stream: no pose, but the tracks live on, so the next paired frame still matches
        its keyframe), or ahead of :meth:`step`, which then takes the tracks."""
        return self.frontend.process(image)

    def step(self, frame: PairedFrame, tracks: Tracks | None = None) -> PoseEstimate | None:
        """One frame (exposure times increasing). None until the first frame with enough features.

        ``tracks``: what :meth:`track` returned for ``frame.image`` when the caller tracked it already
        (:class:`mavvo.odometry.ahead.TrackAhead`, on another thread); tracked here otherwise.
        """
        if not (math.isfinite(frame.roll_rad) and math.isfinite(frame.pitch_rad)):
            raise ValueError(
                f"frame {frame.seq}: roll_rad and pitch_rad must be finite, got {frame.roll_rad}, {frame.pitch_rad}"
            )
        heading = self.filter.yaw_rad if self._good is None else heading_now_rad(self._good, frame.yaw_rad)
        self._tilt.step(frame.t_exposure_s, frame.roll_rad, frame.pitch_rad, heading)
        if tracks is None:
            tracks = self.track(frame.image)
        f_cam = self._rolling.bearings(tracks, frame.t_exposure_s)
        f_lvl = f_cam @ R_lvl_cam(frame.roll_rad, frame.pitch_rad, self.R_body_cam).T
        kf = self.chain.current
        if kf is None:
            return self._initialise(frame, tracks, f_lvl)
        i_kf, i_cur = kf.match(tracks.ids)
        if len(i_kf) < self.options.min_tracks:
            self.chain.drop()
            return self._failed(frame, StateReason.TRACKING_LOST, len(i_kf))
        m = self._measure(frame, kf, i_kf, i_cur, f_lvl)
        if isinstance(m, NoPose):
            self._failed_in_row += 1
            if self._failed_in_row >= self.options.max_failed_frames:
                self.chain.drop()
            return self._failed(frame, m.reason, len(i_kf))
        self._failed_in_row = 0
        return self._accept(frame, tracks, f_lvl, kf, i_kf, i_cur, m)

    # ----------------------------------------------------------------------------------------------
    def _initialise(self, frame: PairedFrame, tracks: Tracks, f_lvl: np.ndarray) -> PoseEstimate | None:
        if len(tracks.ids) < self.options.min_tracks:
            if self._good is None:
                return None
            return self._failed(frame, StateReason.TOO_FEW_FEATURES, len(tracks.ids))
        fc_yaw = frame.yaw_rad
        fc_p = None if frame.fc_position_ned_m is None else np.asarray(frame.fc_position_ned_m, dtype=float)
        v = None
        if self._good is None:
            p, yaw = (np.zeros(3) if fc_p is None else fc_p.copy()), (fc_yaw if math.isfinite(fc_yaw) else 0.0)
            sigma = self.options.position_sigma_m
            if fc_p is not None:
                self._drift.anchor_var_m2 = self.options.anchor_sigma_m**2
        elif self._may_coast and frame.t_exposure_s - self._good.t_s <= self.options.coast_max_s:
            return self._coast(frame, tracks, f_lvl)
        else:
            yaw, v = heading_now_rad(self._good, fc_yaw), self._good.v_ned_m_s
            v_sigma = velocity_sigma_m_s(self.filter)
            p, sigma, how = reinit_anchor(self._good, frame.t_exposure_s, fc_p, v_sigma, self.options)
            # The flight controller's own belief is no step for its EKF (the stream's sigma), but it
            # is only as true as that belief: its uncertainty goes into the long-term drift.
            self._drift.anchor_var_m2 += self.options.anchor_sigma_m**2 if fc_p is not None else sigma**2
            self.reset_counter = (self.reset_counter + 1) % 256
            log.info("re-initialised at frame %d (reset %d), anchored at %s", frame.seq, self.reset_counter, how)
        h = self.height.height_m(frame.range_m, frame.roll_rad, frame.pitch_rad)
        p = p.copy()
        p[2] = self.height.start(float(p[2]), h, first=self._good is None)
        self._drift.anchor_p_ned_m, self._drift.flown_m, self._drift.last_p_ned_m = p.copy(), 0.0, None
        self._first_keyframe(frame, tracks, f_lvl, p, yaw)
        self.heading.restart(fc_yaw)
        self._failed_in_row = 0
        self.filter.reset(
            frame.t_exposure_s, p, yaw, v_ned_m_s=v, pos_cov_m2=sigma**2 * np.eye(3), yaw_sigma_rad=self._yaw_sigma_rad
        )
        self._good = GoodPose.of(self.filter, frame.t_exposure_s, fc_yaw)
        diag = VoDiagnostics(
            state=VisionState.INITIALISING, reason=StateReason.NEW_KEYFRAME, tracks=len(tracks.ids), keyframe=True
        )
        return self._estimate(frame, diag, quality=1)

    def _first_keyframe(self, frame: PairedFrame, tracks: Tracks, f_lvl: np.ndarray, p: np.ndarray, yaw: float) -> None:
        """A keyframe of a new chain (no depths carried into it) at ``p`` (NED, m), heading ``yaw``."""
        depths = np.full(len(tracks.ids), np.nan)
        sigma = self._attitude_sigma_rad(frame)
        kf = Keyframe(frame.seq, frame.t_exposure_s, tracks.ids, f_lvl, depths, p, yaw, frame.yaw_rad, sigma)
        self.chain.push(kf, self.reset_counter)
        self._last_yaw_2_1 = 0.0
        self._metric_interval = False
        self._tilt.lost()  # a new chain's positions may start off the last one's

    def _coast(self, frame: PairedFrame, tracks: Tracks, f_lvl: np.ndarray) -> PoseEstimate:
        """After a short outage (:mod:`mavvo.odometry.recovery`): a keyframe where the filter coasted to,
        the filter's state and the reset counter untouched."""
        assert self._good is not None
        self._predict_coasting(frame)
        yaw = heading_now_rad(self._good, frame.yaw_rad)
        self.filter.shift_yaw(wrap_angle(yaw - self.filter.yaw_rad))  # not the coasted yaw rate's
        p, sigma = self.filter.position_ned_m, coast_sigma_m(self._good, frame.t_exposure_s)
        self.filter.set_position_covariance(np.diag([sigma**2, sigma**2, self.filter.position_covariance[2, 2]]))
        self.height.keyframe_at(self.filter.position_covariance[2, 2])
        self._drift.anchor_var_m2 += 2.0 * sigma**2
        self._first_keyframe(frame, tracks, f_lvl, p, yaw)
        self._failed_in_row = 0
        log.info("tracking goes on at frame %d after %.2f s coasting", frame.seq, frame.t_exposure_s - self._good.t_s)
        diag = VoDiagnostics(
            state=VisionState.DEGRADED, reason=StateReason.NEW_KEYFRAME, tracks=len(tracks.ids), keyframe=True
        )
        return self._estimate(frame, diag, quality=1)

    def _measure(
        self, frame: PairedFrame, kf: Keyframe, i_kf: np.ndarray, i_cur: np.ndarray, f_lvl: np.ndarray
    ) -> Measurement | NoPose:
        """The frame's pose against the keyframe, or the reason there is none."""
        opt = self.options
        f1, f2 = kf.f_lvl.take(i_kf, axis=0), f_lvl.take(i_cur, axis=0)
        rp = self._relpose(frame, kf, f1, f2)
        if not rp.success and rp.reason != RelposeFailure.PURE_ROTATION:
            return NoPose(StateReason(rp.reason.value))
        if rp.num_inliers < opt.min_inliers:
            return NoPose(StateReason.TOO_FEW_INLIERS)
        self._last_yaw_2_1 = rp.yaw_rad
        T1, T2 = tilt_rotation(rp.tilt1_rad), tilt_rotation(rp.tilt2_rad)
        f1, f2 = f1 @ T1.T, f2 @ T2.T
        R_lvl_body2 = T2 @ R_lvl_body(frame.roll_rad, frame.pitch_rad)
        roll2, pitch2, _ = euler321_from_R(R_lvl_body2)  # the frame's roll/pitch with vision's correction
        inl = rp.inliers
        f1i, f2i = f1.compress(inl, axis=0), f2.compress(inl, axis=0)
        n = len(i_kf)
        depth2 = np.full(n, np.nan)
        par = np.zeros(n)
        if rp.reason == RelposeFailure.PURE_ROTATION:
            a = f1i @ rp.R_2_1.T
            par[inl] = np.arccos(np.clip(np.einsum("ij,ij->i", a, f2i), -1.0, 1.0))
            c2, scale = np.zeros(3), None
        else:
            lam1, lam2, par_i, valid = triangulate_unit(f1i, f2i, rp.R_2_1, rp.t_2_1, self._min_parallax_rad)
            par[inl] = par_i
            pts = lam1[valid, None] * f1i.compress(valid, axis=0)
            carried = kf.depth_m[i_kf][inl][valid]
            known = np.isfinite(carried) & (par_i[valid] >= self._carry_min_parallax_rad)
            down2 = R_lvl_body2[:, 2]
            c2_unit = -rp.R_2_1.T @ rp.t_2_1
            scale = estimate_scale(
                opt.scale,
                points_lvl=pts,
                parallax_rad=par_i[valid],
                c2_lvl1=c2_unit,
                down_lvl2=down2,
                range_m=frame.range_m,
                height_m=frame.height_m,
                carried_depth_m=carried[known],
                depth_unit=lam1[valid][known],
                first_interval=not self._metric_interval,
            )
            if scale is None:
                scale = scale_from_scene_depth(
                    pts,
                    self._depth_m(),
                    ScaleSource.HELD if self._scene_depth_m else ScaleSource.ASSUMED,
                    opt.scale.min_points,
                )
            if scale is None:
                # Too little parallax to triangulate: the baseline is below what the images resolve
                # (about depth * min_parallax), so the frame is where the keyframe is (_accept).
                c2 = np.zeros(3)
            else:
                c2 = scale.baseline_m * c2_unit
                d2 = np.full(int(np.count_nonzero(inl)), np.nan)
                d2[valid] = scale.baseline_m * lam2[valid]
                depth2[inl] = d2
                if self._trusted(scale):
                    self._scene_depth_m = median(scale.baseline_m * lam1[valid])
        p, yaw = kf.pose_of(c2, rp.yaw_rad)
        parallax_px = median(par[inl]) * self._focal_px
        return Measurement(p, yaw, rp, scale, c2, parallax_px, depth2, par, (roll2, pitch2), (f1i, f2i))

    def _relpose(self, frame: PairedFrame, kf: Keyframe, f1: np.ndarray, f2: np.ndarray) -> UprightRelpose:
        """The relative pose of the frame's level bearings ``f2`` against the keyframe's ``f1``, its yaw
        expected from the flight controller's (else the last frame's against this keyframe)."""
        if math.isfinite(kf.fc_yaw_rad) and math.isfinite(frame.yaw_rad):
            prior = wrap_angle(kf.fc_yaw_rad - frame.yaw_rad)
        else:
            prior = self._last_yaw_2_1
        # With attitude correction on, the relative pose corrects both views' roll/pitch under the
        # flight controller's uncertainty, and what follows works in the corrected level frames.
        opt = self.options
        sigmas = self._view_attitude_sigmas_rad(kf, frame) if opt.ransac.attitude_correction else None
        return estimate_upright_relpose(
            f1,
            f2,
            max_err_rad=self._max_err_rad,
            seed=frame.seq,
            options=opt.ransac,
            yaw_prior_rad=prior,
            attitude_sigma_rad=sigmas,
        )

    def _degraded_reason(self, frame: PairedFrame, m: Measurement) -> StateReason:
        """Why the frame's pose is trusted less (NONE: it is not)."""
        rp = m.relpose
        if rp.reason == RelposeFailure.PURE_ROTATION and abs(rp.yaw_rad) >= _STATIONARY_YAW_RAD:
            return StateReason.PURE_ROTATION
        if m.scale is not None and not self._trusted(m.scale):
            return UNTRUSTED_SCALE_REASON[m.scale.source]
        if rp.num_inliers < self.options.keyframes.min_inliers:
            return StateReason.FEW_INLIERS
        if frame.interpolation_sigma_rad > self._att_sigma_rad:
            return StateReason.ATTITUDE_INTERPOLATED
        return StateReason.NONE

    def _remember_good(self, frame: PairedFrame) -> None:
        """The frame's pose was accepted: where a re-initialisation anchors, and the distance flown."""
        f = self.filter
        self._may_coast = True
        self._good = GoodPose.of(f, frame.t_exposure_s, frame.yaw_rad)
        d = self._drift
        if d.last_p_ned_m is not None:
            d.flown_m += float(np.linalg.norm(self._good.p_ned_m - d.last_p_ned_m))
        d.last_p_ned_m = self._good.p_ned_m

    def _accept(
        self,
        frame: PairedFrame,
        tracks: Tracks,
        f_lvl: np.ndarray,
        kf: Keyframe,
        i_kf: np.ndarray,
        i_cur: np.ndarray,
        m: Measurement,
    ) -> PoseEstimate:
        opt = self.options
        rp = m.relpose
        reason = self._degraded_reason(frame, m)
        degraded = reason != StateReason.NONE
        quality = self._quality(rp, degraded=degraded)
        p_meas, noise_cov = position_noise(
            opt,
            frame,
            kf,
            m,
            depth_m=self._depth_m(),
            focal_px=self._focal_px,
            speed_m_s=float(np.linalg.norm(self.filter.velocity_ned_m_s)),
            view_attitude_sigmas_rad=self._view_attitude_sigmas_rad(kf, frame),
        )
        pos_cov = noise_cov * (100.0 / quality) ** 2
        yaw_sigma = self._yaw_sigma_rad * 100.0 / quality
        self.filter.predict(frame.t_exposure_s)
        outcome = self.filter.update(p_meas, m.yaw_rad, pos_cov_m2=pos_cov, yaw_sigma_rad=yaw_sigma)
        accepted = outcome != Update.REJECTED
        self._height_fused = self._fuse_height(frame, tracking=accepted)
        if outcome == Update.RESTARTED:
            # The filter jumped to the measurement: a change of the sent pose that is not motion.
            self.reset_counter = (self.reset_counter + 1) % 256
            log.info(
                "filter restarted at frame %d after %d rejections (reset %d)",
                frame.seq,
                opt.filter.max_rejections,
                self.reset_counter,
            )
        survival = len(i_kf) / len(kf.ids)
        moved = sight_change(kf.f_lvl.take(i_kf, axis=0), m.c2_m, self._depth_m())
        why = dict(parallax_px=m.parallax_px, survival=survival, inliers=rp.num_inliers, depth_change=moved)
        why_kf = keyframe_reason(opt.keyframes, **why) if accepted else ""
        if why_kf:
            self._new_keyframe(frame, tracks, f_lvl, kf, i_kf, i_cur, m, reason)
            # The new keyframe's error is now in every measurement made from it, so no later one
            # averages it away: the chain's random walk, which the filter's covariance must carry
            # (docs/odometry.md, Position noise at close range).
            self.filter.commit_position_noise(pos_cov)
            self.height.keyframe_pushed(pos_cov[2, 2])
        if accepted:
            self._remember_good(frame)
            if p_meas is not None:
                self._tilt.measured(p_meas[:2], pos_cov[:2, :2])
        diag = VoDiagnostics(
            state=VisionState.DEGRADED if degraded else VisionState.TRACKING,
            reason=reason,
            tracks=len(tracks.ids),
            inliers=rp.num_inliers,
            inlier_ratio=rp.inlier_ratio,
            parallax_px=m.parallax_px,
            residual_rms_px=rp.residual_rms_rad * self._focal_px,
            scale_source=m.scale.source if m.scale is not None else ScaleSource.NONE,
            keyframe=bool(why_kf),
            attitude_gap_s=frame.attitude_gap_s,
            attitude_sigma_deg=math.degrees(self._attitude_sigma_rad(frame)),
        )
        return self._estimate(frame, diag, quality=quality, roll_pitch_rad=m.roll_pitch_rad)

    def _new_keyframe(
        self,
        frame: PairedFrame,
        tracks: Tracks,
        f_lvl: np.ndarray,
        kf: Keyframe,
        i_kf: np.ndarray,
        i_cur: np.ndarray,
        m: Measurement,
        reason: StateReason,
    ) -> None:
        rp = m.relpose
        held = self._holds_level(kf)
        p_kf, k = keyframe_position(
            kf, m, reason, self.filter.position_ned_m, self._view_error_m(frame, m), held_level=held
        )
        if self._height_fused:  # the measured height, not the sum of the translations, carries on
            p_kf = p_kf.copy()
            p_kf[2] = self.filter.position_ned_m[2]
        t_m = -rp.R_2_1 @ m.c2_m * k  # metric t_2_1
        depth = carry_depths(
            kf,
            i_kf,
            i_cur,
            len(tracks.ids),
            rp.R_2_1,
            t_m,
            m.depth2_m * k,
            m.parallax_rad,
            self._carry_min_parallax_rad,
        )
        yaw = wrap_angle(m.yaw_rad)
        yaw_var = relative_yaw_var(m.relpose, *m.inlier_bearings)  # a keyframe's only: not on every frame
        nudge = self.heading.commit(yaw, yaw_var, frame.yaw_rad, frame.fc_armed, frame.t_exposure_s - kf.t_s)
        if nudge:
            yaw = wrap_angle(yaw + nudge)
            self.filter.shift_yaw(nudge)  # a correction of the frame's heading, not a measurement to gate
        # The new keyframe keeps its level frame as vision corrected it.
        f_kf = f_lvl @ tilt_rotation(m.relpose.tilt2_rad).T
        unmeasured = unresolved_baseline_m(kf, m, self._depth_m(), self._focal_px) if m.scale is None else 0.0
        self.chain.push(
            Keyframe(
                frame.seq,
                frame.t_exposure_s,
                tracks.ids,
                f_kf,
                depth,
                p_kf,
                yaw,
                frame.yaw_rad,
                _HELD_LEVEL_SIGMA_RAD if held else self._attitude_sigma_rad(frame),
                unmeasured,
            ),
            self.reset_counter,
        )
        self._last_yaw_2_1 = 0.0
        known = np.isfinite(depth)
        self._metric_interval = (
            m.scale is not None and self._trusted(m.scale) and np.count_nonzero(known) >= self.options.scale.min_points
        )
        if np.any(known):
            self._scene_depth_m = median(depth[known])

    def _holds_level(self, kf: Keyframe) -> bool:
        """Whether a keyframe made now holds its level frame (the close range, docs/odometry.md): the
        scene nearer than ``keyframes.held_level_below_m``, or while ``kf`` holds its own, nearer than
        ``held_level_release`` times that (a chain let go and taken up again pays for each switch)."""
        opt = self.options.keyframes
        release = opt.held_level_release if kf.attitude_sigma_rad == _HELD_LEVEL_SIGMA_RAD else 1.0
        return self._depth_m() < opt.held_level_below_m * release

    def _view_error_m(self, frame: PairedFrame, m: Measurement) -> np.ndarray:
        """(3,) m: the part of the frame's measured position its own roll/pitch error made, as the last
        update's innovation tells it (measurement.keyframe_position says why it matters)."""
        # The sigma the measurement's noise counted for the frame's tilt (position_noise): the shares of
        # the innovation are only right for what its covariance holds.
        sigma = frame.interpolation_sigma_rad if m.relpose.attitude_resolved else self._attitude_sigma_rad(frame)
        # A tilt error (about north and east) turns the view: what is seen along the optical axis at the
        # scene's depth moves by depth x (tilt x axis).
        axis = R_from_euler321(*m.roll_pitch_rad, m.yaw_rad) @ self.R_body_cam[:, 2]
        turn = skew(axis)
        tilt_cov = (self._depth_m() * sigma) ** 2 * (turn @ np.diag([1.0, 1.0, 0.0]) @ turn.T)
        return self.filter.error_share_m(tilt_cov)

    def _predict_coasting(self, frame: PairedFrame) -> None:
        """The filter to the frame with no vision: the tilt's acceleration (when a multirotor's) and the range."""
        tilt = self.options.filter.tilt_acceleration
        self.filter.predict(frame.t_exposure_s, self._tilt.accel_ned_m_s2 if tilt else None)
        self._fuse_height(frame)

    def _fuse_height(self, frame: PairedFrame, *, tracking: bool = False) -> bool:
        """The frame's range into the filter (:mod:`mavvo.odometry.height`): whether it set or moved the
        down. Where the range won, the keyframe moves too, or vision would put the old height back."""
        h = self.height.height_m(frame.range_m, frame.roll_rad, frame.pitch_rad)
        outcome = self.height.fuse(self.filter, h, tracking=tracking)
        if outcome is not None and self.height.correction_m:
            self.chain.shift_down(self.height.correction_m)
        return outcome in (Update.FUSED, Update.RESTARTED)

    def _failed(self, frame: PairedFrame, reason: StateReason, tracks: int) -> PoseEstimate:
        self._tilt.lost()
        self._predict_coasting(frame)  # the filter runs from the first keyframe on
        if self._good is not None and self._good.t_s >= self._outage_s and self.options.filter.tilt_acceleration:
            self._outage_s = frame.t_exposure_s  # coast from where the vehicle is going, not the lagging filter
            self.filter.set_horizontal_velocity(self._tilt.v_ne_m_s)
        return self._estimate(frame, VoDiagnostics(state=VisionState.FAILED, reason=reason, tracks=tracks), quality=-1)

    def _depth_m(self) -> float:
        """The scene's depth: the last measured, else the assumed ``scale.initial_depth_m``."""
        return self._scene_depth_m or self.options.scale.initial_depth_m

    def _trusted(self, scale: ScaleEstimate) -> bool:
        """Metric: a measured source, or the scene depth held from one while the interval is metric."""
        return scale.source in _TRUSTED_SCALE or (scale.source == ScaleSource.HELD and self._metric_interval)

    # ----------------------------------------------------------------------------------------------
    def _quality(self, rp: UprightRelpose, degraded: bool) -> int:
        opt = self.options
        span = max(opt.good_inliers - opt.min_inliers, 1)
        inl = min(max((rp.num_inliers - opt.min_inliers) / span, 0.0), 1.0)
        ratio = min(rp.inlier_ratio / 0.8, 1.0)
        resid = (
            rp.residual_rms_rad * self._focal_px / opt.ransac.max_err_px if math.isfinite(rp.residual_rms_rad) else 1.0
        )
        q = 100.0 * math.sqrt(inl) * ratio * min(max(1.0 - 0.5 * resid, 0.2), 1.0)
        q = max(1, int(round(q)))
        return min(q, opt.degraded_quality_max) if degraded else q

    def _attitude_sigma_rad(self, frame: PairedFrame) -> float:
        """The frame's roll/pitch uncertainty: the flight controller's and the pairing's interpolation."""
        return math.hypot(self._att_sigma_rad, frame.interpolation_sigma_rad)

    def _view_attitude_sigmas_rad(self, kf: Keyframe, frame: PairedFrame) -> tuple[float, float]:
        """Roll/pitch uncertainty of the keyframe's view and of the frame's (1 sigma each)."""
        return kf.attitude_sigma_rad or self._att_sigma_rad, self._attitude_sigma_rad(frame)

    def _estimate(
        self, frame: PairedFrame, diag: VoDiagnostics, quality: int, roll_pitch_rad: tuple[float, float] | None = None
    ) -> PoseEstimate:
        f = self.filter
        cov = np.zeros((6, 6))
        cov[:3, :3], cov[5, 5] = f.position_covariance, f.yaw_variance
        cov[3, 3] = cov[4, 4] = self._attitude_sigma_rad(frame) ** 2
        drift = self._drift.sigma_m(p := f.position_ned_m, self.options.drift_per_m, self._heading_sigma_rad)
        return PoseEstimate(
            t_exposure_s=frame.t_exposure_s,
            seq=frame.seq,
            p_ned_m=p,
            rpy_rad=np.array([*(roll_pitch_rad or (frame.roll_rad, frame.pitch_rad)), f.yaw_rad]),
            v_ned_m_s=f.velocity_ned_m_s,
            covariance=cov,
            v_covariance=f.velocity_covariance,
            quality=quality,
            reset_counter=self.reset_counter,
            diagnostics=diag,
            # max(., 0): the filter's covariance is kept positive, but a sent figure must not depend on it.
            drift_m=max(drift, math.sqrt(max(float(np.trace(cov[:2, :2])), 0.0) / 2.0)),
        )
