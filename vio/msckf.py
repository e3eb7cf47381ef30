"""Multi-State Constraint Kalman Filter (Mourikis and Roumeliotis, ICRA 2007; open_vins ``UpdaterMSCKF``).

State: IMU ``[R_WB, p_WB, v_WB, b_g, b_a]``, optional camera-IMU extrinsic and time offset, and a sliding
window of pose clones (:mod:`viotb.vio.state`). Each camera frame: propagate with the IMU to the frame time,
try a zero-velocity update, clone the pose, and update with the features whose tracks ended (or that are
about to lose their oldest clone). These landmarks never enter the state: they are triangulated, linearized
and projected out with the left null space of their Jacobian. With ``MsckfParams.max_slam_features > 0``
tracks longer than the window become persistent SLAM landmarks in the state instead
(:mod:`viotb.vio.slam_features`), updated at every clone until their track is lost.

Bad inputs: non-finite IMU values and non-increasing IMU times raise ``ValueError`` naming the value and the
times (they are rejected, not skipped). A frame without image or features is the documented degraded mode:
the filter propagates only and :meth:`MsckfEstimator.health` reports 0 tracked features and the condition
``"no_features"``. Divergence (non-finite state or covariance, non-PSD covariance, runaway innovation,
position sigma beyond a bound) is reported through ``health().diverged`` with a reason; the filter then stops
updating and never raises from numpy.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.feature_database import FeatureDatabase
from viotb.vio.frontend import FrontEnd, Tracks, make_frontend
from viotb.vio.frontend_stereo import make_stereo_frontend
from viotb.vio.imu_intrinsics import ImuIntrinsics
from viotb.vio.imu_prediction import LazyCovarianceEstimate, PredictionChain
from viotb.vio.initialization import InertialInitializer, init_params_for
from viotb.vio.keyframing import KeyframeSelector
from viotb.vio.lie import log_so3
from viotb.vio.lifecycle import attempt_initialization, excitation_wanted, frame_health
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.msckf_update import UpdateStats, msckf_update
from viotb.vio.propagator import Propagator
from viotb.vio.slam_features import (
    SlamStats,
    initialize_landmarks,
    landmark_observations,
    marginalize_lost_landmarks,
    take_new_landmarks,
    update_landmarks,
)
from viotb.vio.state import (
    EXTRINSIC_BLOCK,
    IMU_BLOCK,
    POS,
    TIME_OFFSET_BLOCK,
    State,
    ekf_update,
    is_psd,
    marginal_covariance,
    marginalize_oldest_clone,
    read_init_record,
)
from viotb.vio.types import (
    CalibrationDrift,
    CameraFrame,
    HealthStatus,
    ImuNoise,
    ImuSample,
    StateEstimate,
)
from viotb.vio.update_helpers import (
    Chi2Table,
)
from viotb.vio.window_init import couple_static_tilt_bias
from viotb.vio.zero_velocity import ZeroVelocityDetector


class MsckfEstimator:
    """The MSCKF estimator (implements :class:`viotb.vio.types.Estimator`).

    Args:
        calib: Cam0 intrinsics, extrinsics (``R_BC``, ``p_BC``) and time offset.
        noise: IMU noise densities.
        params: Settings.
        frontend: Optional front end overriding ``params.frontend`` (it must fill the cam1 fields of its
            tracks itself on a stereo rig).
        calib_right: Cam1 intrinsics and extrinsics of a stereo rig (synchronized with cam0, the same time
            offset), or None for mono. Frames without right data are then used as mono frames.
    """

    name = "msckf"

    def __init__(
        self,
        calib: CameraCalibration,
        noise: ImuNoise,
        params: MsckfParams | None = None,
        frontend: FrontEnd | None = None,
        calib_right: CameraCalibration | None = None,
    ) -> None:
        """Create an uninitialized filter."""
        self.calib = calib
        self.calib_right = calib_right
        self.noise = noise
        self.params = params if params is not None else MsckfParams()
        p = self.params
        if p.max_slam_features < 0:
            raise ValueError(f"MsckfParams.max_slam_features must be >= 0, got {p.max_slam_features}")
        if not 2 <= p.max_clones <= 60:
            raise ValueError(f"MsckfParams.max_clones must be in 2..60, got {p.max_clones}")
        if p.update_linearization not in ("current_oc", "current", "first_estimates"):
            raise ValueError(
                "MsckfParams.update_linearization must be 'current_oc', 'current' or 'first_estimates', "
                f"got {p.update_linearization!r}"
            )
        ImuIntrinsics.from_choice(p.imu_intrinsics)  # ValueError naming the field on a bad choice
        if not (np.isfinite(p.imu_intrinsic_sigma) and p.imu_intrinsic_sigma > 0.0):
            raise ValueError(f"MsckfParams.imu_intrinsic_sigma must be > 0, got {p.imu_intrinsic_sigma}")
        if frontend is None:
            mono = make_frontend(p.frontend, calib.camera, p.klt, "MsckfParams")
            frontend = make_stereo_frontend(mono, calib, calib_right, p.stereo)
        self.frontend = frontend
        self.propagator = Propagator(noise, p.integration, p.use_fej)
        n_cams = 1 if calib_right is None else 2
        self.database = FeatureDatabase(p.max_clones + 3, num_cameras=n_cams)
        self.chi2 = Chi2Table(2 * n_cams * (p.max_clones + 2) + 20)
        self.state: State | None = None
        self.initializer = InertialInitializer(calib, noise, init_params_for(p.frontend))
        self._focal_px = 0.5 * (calib.camera.fx + calib.camera.fy)
        self._focal_right_px = None
        if calib_right is not None:
            self._focal_right_px = 0.5 * (calib_right.camera.fx + calib_right.camera.fy)
        self._prev_tracks: Tracks | None = None
        self._prev_frame_t_imu: float | None = None
        self._last_imu: ImuSample | None = None
        self._health = HealthStatus(t_s=0.0, initialized=False)
        self._diverged_reason = ""
        self._runaway_count = 0
        self._last_update_t_s: float | None = None  # the newest frame that updated (ZUPT or features)
        self._version = 0
        self._chain: PredictionChain | None = None
        self._published: tuple[PredictionChain, int, LazyCovarianceEstimate] | None = None  # estimate() memo
        self.last_stats = UpdateStats()
        self.last_slam_stats = SlamStats()
        self.zupt_count = 0
        self.keyframe_rule = KeyframeSelector(p.keyframing)
        self.zero_velocity = ZeroVelocityDetector(
            p.zero_velocity, noise, p.chi2_multiplier * float(self.chi2(9))
        )

    # ------------------------------------------------------------------ protocol
    def initialize(self, init: object) -> None:
        """Start the filter from an ``InitResult`` (t_s, R_WB, p_WB, v_WB, biases, cov_diag (15,))."""
        t_s, vals, cov = read_init_record(init)
        p = self.params
        if p.static_tilt_bias_sigma_m_s2 is not None and getattr(init, "method", "") == "static":
            cov = couple_static_tilt_bias(cov, vals.R_WB, p.static_tilt_bias_sigma_m_s2)
        ext_cov = None
        if p.estimate_extrinsics:
            ext_cov = np.diag([p.extrinsic_sigma_rad**2] * 3 + [p.extrinsic_sigma_m**2] * 3)
        td_var = p.time_offset_sigma_s**2 if p.estimate_time_offset else None
        intr = ImuIntrinsics.from_choice(p.imu_intrinsics)
        intr_cov = None if intr is None else np.eye(intr.dim) * p.imu_intrinsic_sigma**2
        self.state = State(
            t_s,
            vals,
            cov,
            self.calib.R_BC,
            self.calib.p_BC,
            self.calib.time_offset_s,
            ext_cov,
            td_var,
            intr,
            intr_cov,
        )
        self._version += 1
        self._last_update_t_s = t_s
        self._health = HealthStatus(t_s=t_s, initialized=True)
        # Only a static initialization proves the platform is at rest; after any other (dynamic, or from an
        # external source such as a perturbed truth in the Gymnasium envs) the ZUPT stays off when
        # ``zero_velocity.only_at_beginning``.
        self.zero_velocity.has_moved = getattr(init, "method", "static") != "static"

    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer one IMU reading (ValueError naming value/time on NaN/inf or non-increasing time)."""
        self.propagator.feed_imu(sample)
        self._last_imu = sample
        if self.state is None and self.initializer is not None:
            self.initializer.feed_imu(sample)

    def feed_camera(self, frame: CameraFrame) -> None:
        """Track features, propagate, and update (see the module docstring for the degraded modes)."""
        t_imu = frame.t_s + (self.state.time_offset_s if self.state is not None else self.calib.time_offset_s)
        tracks = self.frontend.process(frame, t_imu)
        if self.state is None:
            self._try_initialize(tracks)
            self._prev_tracks = tracks
            return
        if self._diverged_reason:
            self._health = self._make_health(frame.t_s, tracks, UpdateStats(), ())
            return
        try:
            self._process(frame, tracks)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
            if isinstance(exc, ValueError) and "clone time" in str(exc):
                raise
            self._declare_divergence(f"numerical failure in the update: {exc}")
            self._health = self._make_health(frame.t_s, tracks, UpdateStats(), ())
        self._prev_tracks = tracks

    def estimate(self) -> StateEstimate | None:
        """Latest state propagated to the newest IMU sample (the filter itself is not changed).

        The mean is predicted one IMU interval per new sample; the covariance only when ``cov`` is read
        (:mod:`viotb.vio.imu_prediction`), with the same values. A call with no IMU sample and no filter
        change since the last returns the same (frozen) record.
        """
        st = self.state
        if st is None:
            return None
        t_new = self._last_imu.t_s if self._last_imu is not None else st.t_s
        chain = self._chain
        if chain is None or chain.version != self._version or chain.t_s > t_new:
            d = st.propagated_dim  # the IMU block and the online intrinsics after it
            chain = self._chain = PredictionChain(
                self._version, st.t_s, st.imu, st.cov[:d, :d], self.propagator, st.intrinsics
            )
        index, vals = chain.advance(t_new)
        published = self._published
        if published is not None and published[0] is chain and published[1] == index:
            # No IMU sample since the last call on this chain: the same prediction, the same record.
            return published[2]
        omega = np.zeros(3)
        if self._last_imu is not None:
            omega = np.asarray(self._last_imu.gyro_B_rad_s, dtype=float) - vals.gyro_bias_rad_s
            if st.intrinsics is not None:
                omega = st.intrinsics.T_g @ omega
        est = LazyCovarianceEstimate.from_chain(chain, index, vals, omega)
        self._published = (chain, index, est)
        return est

    def health(self) -> HealthStatus:
        """Health after the latest camera frame."""
        return self._health

    def last_tracks_px(self) -> np.ndarray:
        """Distorted pixels of the features tracked in the latest frame, shape (M, 2) (for viewers)."""
        tracks = self._prev_tracks
        return np.zeros((0, 2)) if tracks is None else tracks.uv_px

    def wants_excitation(self) -> bool:
        """True while the horizontal accelerometer bias is still poorly known.

        See :func:`viotb.vio.lifecycle.excitation_wanted`; the threshold is
        ``params.excitation_accel_bias_sigma_m_s2``.
        """
        st = self.state
        if st is None:
            return False
        P = marginal_covariance(st, [st.block(IMU_BLOCK)])
        return excitation_wanted(P, self.params.excitation_accel_bias_sigma_m_s2)

    def feed_truth(self, truth: StateEstimate) -> None:
        """Truth is not used by the filter (no-op; part of :class:`viotb.vio.types.Estimator`)."""

    # ------------------------------------------------------------------ internals
    def _try_initialize(self, tracks: Tracks) -> None:
        init, health = attempt_initialization(self.initializer, tracks)
        if init is not None:
            self.initialize(init)
        self._health = health

    def _make_health(
        self, t_s: float, tracks: Tracks, stats: UpdateStats, conditions: tuple[str, ...]
    ) -> HealthStatus:
        return frame_health(
            t_s,
            tracks,
            self._diverged_reason,
            updated_features=stats.used,
            conditions=conditions,
            chi2_rejections=stats.rejected,
            nis_per_dof=stats.nis_per_dof,
            nis_per_dof_all=stats.nis_per_dof_all,
            calibration=self._calibration_drift(),
        )

    def _calibration_drift(self) -> CalibrationDrift | None:
        """Estimated minus given extrinsic and time offset with their sigmas (None when none is estimated)."""
        st = self.state
        if st is None or not (st.has_block(EXTRINSIC_BLOCK) or st.has_block(TIME_OFFSET_BLOCK)):
            return None
        out = {}
        if st.has_block(TIME_OFFSET_BLOCK):
            i = st.block(TIME_OFFSET_BLOCK).offset
            out["time_offset_s"] = st.time_offset_s - self.calib.time_offset_s
            out["time_offset_sigma_s"] = float(np.sqrt(max(st.cov[i, i], 0.0)))
        if st.has_block(EXTRINSIC_BLOCK):
            sl = st.block(EXTRINSIC_BLOCK).indices
            sigma = np.sqrt(np.maximum(np.diag(st.cov[sl, sl]), 0.0))
            out["rotation_BC_rad"] = log_so3(self.calib.R_BC.T @ st.R_BC)
            out["rotation_sigma_rad"] = sigma[:3]
            out["translation_BC_m"] = st.p_BC - self.calib.p_BC
            out["translation_sigma_m"] = sigma[3:]
        return CalibrationDrift(**out)

    def _declare_divergence(self, reason: str) -> None:
        if not self._diverged_reason:
            self._diverged_reason = reason

    def _process(self, frame: CameraFrame, tracks: Tracks) -> None:
        st = self.state
        assert st is not None
        p = self.params
        t_imu = frame.t_s + st.time_offset_s
        if t_imu < st.t_s - 1e-9 or (st.clones and frame.t_s <= next(reversed(st.clones))):
            raise ValueError(
                f"camera frame at t={frame.t_s:.9f} s is not newer than the filter (state at {st.t_s:.9f} s)"
            )
        self.propagator.propagate(st, t_imu)
        self._version += 1
        conditions: list[str] = []
        if self.zero_velocity.allowed() and self._try_zupt(tracks, t_imu):
            conditions.append("zupt")
            self.zupt_count += 1
            stats = UpdateStats()
        elif not self.keyframe_rule.is_keyframe(tracks, *self._rotation_since_keyframe(st)):
            self.keyframe_rule.skip()
            stats = UpdateStats()
        else:
            self.keyframe_rule.accept(tracks)
            self.propagator.propagate_and_clone(st, frame.t_s)
            slam = p.max_slam_features > 0
            if slam:
                n_before = len(st.landmarks)
                lm_obs = marginalize_lost_landmarks(
                    st, landmark_observations(st, tracks, self.database.num_cameras)
                )
                n_lost = n_before - len(lm_obs.ids)
            ids0, xy0, ids1, xy1 = tracks.ids, tracks.xy_norm, tracks.ids_right, tracks.xy_norm_right
            if slam and st.landmarks:  # a landmark's observations go to its own update, not the database
                keep0, keep1 = ~np.isin(ids0, lm_obs.ids), ~np.isin(ids1, lm_obs.ids)
                ids0, xy0, ids1, xy1 = ids0[keep0], xy0[keep0], ids1[keep1], xy1[keep1]
            self.database.add(frame.t_s, ids0, xy0)
            if self.calib_right is not None and len(ids1):
                self.database.add(frame.t_s, ids1, xy1, cam=1)
            if slam:
                new = take_new_landmarks(st, self.database, p, self.calib_right is not None)
            stats = msckf_update(
                st,
                self.database,
                p,
                self.chi2,
                frame.t_s,
                self._focal_px,
                self.calib_right,
                self._focal_right_px,
                use_oldest=self._update_gap_exceeded(frame.t_s),
            )
            if slam:
                self.last_slam_stats = self._slam_step(st, frame.t_s, lm_obs, new, n_lost)
            if len(st.clones) > p.max_clones:
                t_old = marginalize_oldest_clone(st)
                if t_old is not None:
                    self.database.remove_frame(t_old)
        self._prev_frame_t_imu = t_imu
        if stats.used > 0 or "zupt" in conditions:
            self._last_update_t_s = frame.t_s
        self._version += 1
        self._check_divergence(stats)
        self.last_stats = stats
        self._health = self._make_health(frame.t_s, tracks, stats, tuple(conditions))

    def _update_gap_exceeded(self, t_s: float) -> bool:
        """Whether ``MsckfParams.max_update_gap_s`` has passed since the last update (ZUPT or features)."""
        gap = self.params.max_update_gap_s
        last = self._last_update_t_s
        return gap is not None and last is not None and t_s - last > gap

    def _rotation_since_keyframe(self, st: State) -> tuple[np.ndarray | None, float]:
        """``(R_CrCn (3, 3), focal_px)`` for a rotation-compensated keyframe rule, else ``(None, focal_px)``.

        ``R_CrCn`` is the camera's rotation since the newest clone (the rule's reference keyframe), from the
        propagated attitude and the current extrinsic.
        """
        if not self.params.keyframing.rotation_compensated or not st.clones:
            return None, self._focal_px
        ref = st.clones[next(reversed(st.clones))]
        R_BrBn = ref.R_WB.T @ st.imu.R_WB
        return st.R_BC.T @ R_BrBn @ st.R_BC, self._focal_px

    def _slam_step(self, st: State, t_s: float, lm_obs, new, n_lost: int) -> SlamStats:
        """Update the SLAM landmarks at the newest clone, then initialize the new ones (open_vins order)."""
        p = self.params
        n_up, n_rej = update_landmarks(
            st, lm_obs, p, self.chi2, t_s, self._focal_px, self.calib_right, self._focal_right_px
        )
        ids, xy, mask, stereo_views = new
        n_init, n_init_rej = initialize_landmarks(
            st,
            ids,
            xy,
            mask,
            p,
            self.chi2,
            self._focal_px,
            self.calib_right if stereo_views else None,
            self._focal_right_px,
        )
        return SlamStats(len(st.landmarks), n_up, n_rej, n_init, n_init_rej, n_lost)

    def _check_divergence(self, stats: UpdateStats) -> None:
        st = self.state
        assert st is not None
        p = self.params
        if not st.is_finite():
            self._declare_divergence("non-finite value in the state or covariance")
            return
        if not is_psd(st, tol=1e-9):
            self._declare_divergence("covariance is not positive semi-definite")
            return
        pos_sigma = float(np.sqrt(np.max(np.diag(st.cov)[POS : POS + 3])))
        if pos_sigma > p.max_position_sigma_m:
            self._declare_divergence(
                f"position sigma {pos_sigma:.1f} m exceeds max_position_sigma_m={p.max_position_sigma_m}"
            )
            return
        bad = stats.rejected + stats.inconsistent
        gated = stats.used + bad
        if gated >= p.runaway_min_features and bad > p.runaway_reject_ratio * gated:
            self._runaway_count += 1
        elif gated >= p.runaway_min_features:
            self._runaway_count = 0
        if self._runaway_count >= p.runaway_frames:
            self._declare_divergence(
                f"runaway innovation: more than {p.runaway_reject_ratio:.0%} of the features failed the chi2 "
                f"gate or the triangulation reprojection gate in {self._runaway_count} consecutive frames "
                f"(told {p.pixel_sigma_px:g} px: the images do not fit the IMU's motion; usual causes are a "
                "wrong camera-IMU time offset or extrinsic, which online calibration tells apart, or a pixel "
                "noise smaller than the tracks')"
            )

    def _try_zupt(self, tracks: Tracks, t_imu: float) -> bool:
        """Zero-velocity update when features barely move and the IMU agrees (:mod:`.zero_velocity`)."""
        st = self.state
        assert st is not None
        prev, t0 = self._prev_tracks, self._prev_frame_t_imu
        if prev is None or t0 is None:
            return False
        test = self.zero_velocity.detect(
            prev, tracks, t_imu - t0, st.imu, st.cov, lambda: self.propagator.readings(t0, t_imu)[1:]
        )
        if test is None:
            return False
        # All 9 rows test stillness; by default only the gyro and velocity rows update the state. The
        # accelerometer rows would write any small acceleration at the onset of motion (a min-jerk takeoff
        # starts with zero acceleration, below the gate) into the accelerometer bias: measured 0.2 m/s^2,
        # then 0.2-0.3 m of altitude error over a 1.2 s climb.
        rows = np.arange(9) if self.params.zupt_update_accel else np.r_[0:3, 6:9]
        ekf_update(st, test.H[rows], test.r[rows], test.R[np.ix_(rows, rows)])
        return True
