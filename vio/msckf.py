"""Multi-State Constraint Kalman Filter (Mourikis and Roumeliotis, ICRA 2007; open_vins ``UpdaterMSCKF``).

State: IMU ``[R_WB, p_WB, v_WB, b_g, b_a]``, optional camera-IMU extrinsic and time offset, and a sliding
window of pose clones (:mod:`viotb.vio.state`). Each camera frame: propagate with the IMU to the frame time,
try a zero-velocity update, clone the pose, and update with the features whose tracks ended (or that are
about to lose their oldest clone). Landmarks never enter the state: they are triangulated, linearized and
projected out with the left null space of their Jacobian.

Bad inputs: non-finite IMU values and non-increasing IMU times raise ``ValueError`` naming the value and the
times (they are rejected, not skipped). A frame without image or features is the documented degraded mode:
the filter propagates only and :meth:`MsckfEstimator.health` reports 0 tracked features and the condition
``"no_features"``. Divergence (non-finite state or covariance, non-PSD covariance, runaway innovation,
position sigma beyond a bound) is reported through ``health().diverged`` with a reason; the filter then stops
updating and never raises from numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.frontend import FeatureDatabase, FrontEnd, KltParams, Tracks, make_frontend
from viotb.vio.initialization import InertialInitializer, InitParams
from viotb.vio.lie import log_so3
from viotb.vio.propagator import Integration, Propagator
from viotb.vio.state import (
    BA,
    BG,
    EXTRINSIC_BLOCK,
    IMU_BLOCK,
    POS,
    THETA,
    TIME_OFFSET_BLOCK,
    VEL,
    ImuValues,
    State,
    ekf_update,
    is_psd,
    marginal_covariance,
    marginalize_oldest_clone,
    read_init_record,
)
from viotb.vio.triangulation import TriangulationParams, triangulate
from viotb.vio.types import (
    GRAVITY_M_S2,
    CalibrationDrift,
    CameraFrame,
    HealthStatus,
    ImuNoise,
    ImuSample,
    StateEstimate,
)
from viotb.vio.update_helpers import (
    Chi2Table,
    clone_unobservable_basis,
    feature_jacobian,
    measurement_compress,
    nullspace_project,
    observability_constrain,
)


@dataclass(frozen=True)
class MsckfParams:
    """MSCKF settings (defaults near open_vins' EuRoC configuration).

    Attributes:
        max_clones: Clones in the sliding window (10-15).
        excitation_accel_bias_sigma_m_s2: Above this horizontal accelerometer-bias sigma (m/s^2) the filter
            asks for excitation (:meth:`MsckfEstimator.wants_excitation`).
        keyframe_min_parallax_px: Median feature motion (px) since the last clone that makes a frame a
            clone before ``clone_every_n_frames`` is reached.
        clone_every_n_frames: Clone (and update) at least on every n-th frame; the front end still tracks
            every frame. Spacing the clones widens the window's baseline (keyframing, lesson ch. 8): a
            hovering drone moves millimetres per frame, too little parallax to triangulate within 11
            consecutive frames.
        max_features_per_update: Most features used in one update (longest tracks first).
        min_track_length: Fewest clone observations for a feature to be used.
        pixel_sigma_px: Feature measurement noise (px).
        chi2_multiplier: Multiplier on the 95 % chi-square gate of each feature.
        integration: IMU integration method.
        use_fej: First-estimates Jacobians (FEJ) in the IMU propagation.
        update_linearization: Where the MSCKF update's Jacobians are evaluated. ``"current_oc"`` (default):
            at the current clone estimates (where the residual is), then projected so that they annihilate
            the four unobservable directions at the clones' first estimates (observability-constrained
            update, Hesch et al. TRO 2014). ``"first_estimates"``: at the first estimates (open_vins
            ``do_fej``); measured overconfident here: clones move 1-7 cm and 0.1-0.8 deg from their first
            estimates within the window, and with ~1000 rows per update that Jacobian mismatch exceeds the
            claimed precision. Position ANEES over 20 seeds x 20 s of ``tests/test_msckf.py``'s synthetic
            flight (95 % band [2.02, 4.16], 3 expected): 4.53 first estimates, 3.37 current, 3.21
            current_oc; over 12 seeds x 60 s (band [1.77, 4.53]): 3.97, 4.35 (orientation NEES 10.1: yaw
            becomes spuriously observable) and 3.52. ``"current"``: plain EKF Jacobians. Only used when
            ``use_fej`` is True; otherwise ``"current"``.
        frontend: ``"klt"`` (images) or ``"sim"`` (``frame.features``).
        klt: KLT settings.
        triangulation: Triangulation settings.
        zupt_enabled: Zero-velocity updates while stationary.
        zupt_max_disparity_px: Largest median feature motion (px) between frames to consider a ZUPT.
        zupt_min_features: Fewest common features to measure the disparity.
        zupt_max_velocity_m_s: Largest estimated speed (m/s) to consider a ZUPT.
        zupt_noise_multiplier: Inflation of the IMU noise in the ZUPT measurement (vibration).
        zupt_velocity_sigma_m_s: Noise (m/s) of the zero-velocity rows.
        zupt_update_accel: Let the ZUPT's accelerometer rows update tilt and accelerometer bias (they always
            take part in the stillness test).
        zupt_only_at_beginning: Allow ZUPTs only until the platform first moves (open_vins'
            ``zupt_only_at_beginning``). A hovering drone reads like a still one to the IMU (specific force
            ~ +g z, zero rate) and barely moves its features, so a ZUPT in the air pins a velocity that is not
            zero: measured 10 cm of unseen drift in 3 s of closed-loop hover before this option.
        estimate_extrinsics: Estimate ``R_BC, p_BC`` online.
        extrinsic_sigma_rad: Prior sigma (rad) of the extrinsic rotation.
        extrinsic_sigma_m: Prior sigma (m) of the extrinsic translation.
        estimate_time_offset: Estimate the camera-IMU time offset online.
        time_offset_sigma_s: Prior sigma (s) of the time offset.
        max_position_sigma_m: Position sigma (m) beyond which the filter declares divergence.
        runaway_frames: Consecutive frames with most features failing the gate that declare divergence.
        runaway_min_features: Fewest gated features for a frame to count towards ``runaway_frames``.
        runaway_reject_ratio: Rejected fraction above which a frame counts as runaway.
    """

    max_clones: int = 11
    clone_every_n_frames: int = 6
    keyframe_min_parallax_px: float = 3.0
    excitation_accel_bias_sigma_m_s2: float = 0.02
    max_features_per_update: int = 50
    min_track_length: int = 3
    pixel_sigma_px: float = 1.0
    chi2_multiplier: float = 1.0
    integration: Integration = Integration.RK4
    use_fej: bool = True
    update_linearization: str = "current_oc"
    frontend: str = "klt"
    klt: KltParams = field(default_factory=KltParams)
    triangulation: TriangulationParams = field(default_factory=TriangulationParams)
    zupt_enabled: bool = True
    zupt_max_disparity_px: float = 0.5
    zupt_min_features: int = 10
    zupt_max_velocity_m_s: float = 0.2
    zupt_noise_multiplier: float = 10.0
    zupt_velocity_sigma_m_s: float = 0.01
    zupt_only_at_beginning: bool = True
    zupt_update_accel: bool = False
    estimate_extrinsics: bool = False
    extrinsic_sigma_rad: float = 0.005
    extrinsic_sigma_m: float = 0.005
    estimate_time_offset: bool = False
    time_offset_sigma_s: float = 0.005
    max_position_sigma_m: float = 100.0
    runaway_frames: int = 10
    runaway_min_features: int = 5
    runaway_reject_ratio: float = 0.7

    def with_online_calibration(
        self, time_offset_sigma_s: float = 0.02, extrinsic_sigma_rad: float = 0.05
    ) -> MsckfParams:
        """These settings with the time offset and the extrinsics estimated online (wide priors).

        The fix of the time-sync / extrinsic failure mode; with both on, the calibration that moves names
        the cause (:class:`viotb.vio.health.HealthMonitor`).
        """
        return replace(
            self,
            estimate_time_offset=True,
            time_offset_sigma_s=time_offset_sigma_s,
            estimate_extrinsics=True,
            extrinsic_sigma_rad=extrinsic_sigma_rad,
        )


@dataclass(frozen=True)
class UpdateStats:
    """Bookkeeping of one MSCKF update.

    Attributes:
        candidates: Features considered.
        triangulated: Features that triangulated.
        used: Features that passed the gate and entered the update.
        rejected: Features rejected by the chi-square gate.
        rows: Measurement rows after null-space projection (before compression).
        inconsistent: Features whose views admit no common point (triangulation reprojection error above
            its gate), a divergence symptom when they dominate.
        nis_per_dof: Mean over the features that passed the gate of ``chi2 / dof`` (normalized innovation
            squared per degree of freedom; ~1 when consistent), NaN when none passed.
        nis_per_dof_all: The same mean over every triangulated candidate (rejected ones included).
    """

    candidates: int = 0
    triangulated: int = 0
    used: int = 0
    rejected: int = 0
    rows: int = 0
    inconsistent: int = 0
    nis_per_dof: float = float("nan")
    nis_per_dof_all: float = float("nan")


class MsckfEstimator:
    """The MSCKF estimator (implements :class:`viotb.vio.types.Estimator`).

    Args:
        calib: Camera intrinsics, extrinsics and time offset.
        noise: IMU noise densities.
        params: Settings.
        frontend: Optional front end overriding ``params.frontend``.
    """

    name = "msckf"

    def __init__(
        self,
        calib: CameraCalibration,
        noise: ImuNoise,
        params: MsckfParams | None = None,
        frontend: FrontEnd | None = None,
    ) -> None:
        """Create an uninitialized filter."""
        self.calib = calib
        self.noise = noise
        self.params = params if params is not None else MsckfParams()
        p = self.params
        if not 2 <= p.max_clones <= 60:
            raise ValueError(f"MsckfParams.max_clones must be in 2..60, got {p.max_clones}")
        if p.update_linearization not in ("current_oc", "current", "first_estimates"):
            raise ValueError(
                "MsckfParams.update_linearization must be 'current_oc', 'current' or 'first_estimates', "
                f"got {p.update_linearization!r}"
            )
        if frontend is None:
            frontend = make_frontend(p.frontend, calib.camera, p.klt, "MsckfParams")
        self.frontend = frontend
        self.propagator = Propagator(noise, p.integration, p.use_fej)
        self.database = FeatureDatabase(p.max_clones + 3)
        self.chi2 = Chi2Table(2 * (p.max_clones + 2) + 20)
        self.state: State | None = None
        self.initializer = InertialInitializer(calib, noise, InitParams())
        self._focal_px = 0.5 * (calib.camera.fx + calib.camera.fy)
        self._sigma_norm = p.pixel_sigma_px / self._focal_px
        self._prev_tracks: Tracks | None = None
        self._prev_frame_t_imu: float | None = None
        self._last_imu: ImuSample | None = None
        self._health = HealthStatus(t_s=0.0, initialized=False)
        self._diverged_reason = ""
        self._runaway_count = 0
        self._version = 0
        self._pred_cache: tuple[int, float, ImuValues, np.ndarray, np.ndarray] | None = None
        self.last_stats = UpdateStats()
        self.zupt_count = 0
        self._has_moved = False
        self._frames_since_clone = 0
        self._keyframe_tracks: Tracks | None = None

    # ------------------------------------------------------------------ protocol
    def initialize(self, init: object) -> None:
        """Start the filter from an ``InitResult`` (t_s, R_WB, p_WB, v_WB, biases, cov_diag (15,))."""
        t_s, vals, cov = read_init_record(init)
        p = self.params
        ext_cov = None
        if p.estimate_extrinsics:
            ext_cov = np.diag([p.extrinsic_sigma_rad**2] * 3 + [p.extrinsic_sigma_m**2] * 3)
        td_var = p.time_offset_sigma_s**2 if p.estimate_time_offset else None
        self.state = State(
            t_s, vals, cov, self.calib.R_BC, self.calib.p_BC, self.calib.time_offset_s, ext_cov, td_var
        )
        self._version += 1
        self._health = HealthStatus(t_s=t_s, initialized=True)
        # Only a static initialization proves the platform is at rest; after any other (dynamic, or from an
        # external source such as a perturbed truth in the Gymnasium envs) the ZUPT stays off when
        # ``zupt_only_at_beginning``.
        self._has_moved = getattr(init, "method", "static") != "static"

    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer one IMU reading (ValueError naming value/time on NaN/inf or non-increasing time)."""
        self.propagator.feed_imu(sample)
        self._last_imu = sample
        if self.state is None and self.initializer is not None:
            self.initializer.feed_imu(sample)  # type: ignore[attr-defined]

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
        """Latest state propagated to the newest IMU sample (the filter itself is not changed)."""
        st = self.state
        if st is None:
            return None
        t_new = self._last_imu.t_s if self._last_imu is not None else st.t_s
        cache = self._pred_cache
        if cache is not None and cache[0] == self._version and cache[1] <= t_new:
            _, t0, vals0, phi0, q0 = cache
        else:
            t0, vals0, phi0, q0 = st.t_s, st.imu, np.eye(15), np.zeros((15, 15))
        vals, phi, q = self.propagator.predict(vals0, t0, t_new)
        phi_tot, q_tot = phi @ phi0, phi @ q0 @ phi.T + q
        t_out = max(t_new, t0)
        self._pred_cache = (self._version, t_out, vals, phi_tot, q_tot)
        P = marginal_covariance(st, [st.block(IMU_BLOCK)])
        cov = phi_tot @ P @ phi_tot.T + q_tot
        omega = np.zeros(3)
        if self._last_imu is not None:
            omega = np.asarray(self._last_imu.gyro_B_rad_s, dtype=float) - vals.gyro_bias_rad_s
        return StateEstimate(
            t_s=t_out,
            R_WB=vals.R_WB.copy(),
            p_WB=vals.p_WB.copy(),
            v_WB=vals.v_WB.copy(),
            gyro_bias_rad_s=vals.gyro_bias_rad_s.copy(),
            accel_bias_m_s2=vals.accel_bias_m_s2.copy(),
            omega_B_rad_s=omega,
            cov=0.5 * (cov + cov.T),
        )

    def health(self) -> HealthStatus:
        """Health after the latest camera frame."""
        return self._health

    def last_tracks_px(self) -> np.ndarray:
        """Distorted pixels of the features tracked in the latest frame, shape (M, 2) (for viewers)."""
        tracks = getattr(self, "_prev_tracks", None)
        return np.zeros((0, 2)) if tracks is None else tracks.uv_px

    def wants_excitation(self) -> bool:
        """True while the horizontal accelerometer bias is still poorly known.

        After a static initialization the accelerometer bias along x and y is confounded with roll and
        pitch until the platform rotates and accelerates (lesson ch. 6-8: "design the motion in"); a runner
        answers with an excitation manoeuvre. Threshold: ``params.excitation_accel_bias_sigma_m_s2``.
        """
        st = self.state
        if st is None:
            return False
        P = marginal_covariance(st, [st.block(IMU_BLOCK)])
        sigma_ba_xy = np.sqrt(np.max(np.diag(P)[12:14]))
        return bool(sigma_ba_xy > self.params.excitation_accel_bias_sigma_m_s2)

    # ------------------------------------------------------------------ internals
    def _try_initialize(self, tracks: Tracks) -> None:
        init = None
        if self.initializer is not None:
            if len(tracks):
                self.initializer.feed_features(tracks.t_imu_s, tracks.ids, tracks.xy_norm)  # type: ignore[attr-defined]
            init = self.initializer.try_initialize()  # type: ignore[attr-defined]
        if init is not None:
            self.initialize(init)
        conditions = () if init is not None else ("waiting_for_init",)
        self._health = HealthStatus(
            t_s=tracks.t_cam_s,
            initialized=self.state is not None,
            tracked_features=len(tracks),
            conditions=conditions,
        )

    def _make_health(
        self, t_s: float, tracks: Tracks, stats: UpdateStats, conditions: tuple[str, ...]
    ) -> HealthStatus:
        conds = list(conditions)
        if len(tracks) == 0:
            conds.append("no_features")
        elif len(tracks) < 20:
            conds.append("feature_poverty")
        return HealthStatus(
            t_s=t_s,
            initialized=True,
            tracked_features=len(tracks),
            updated_features=stats.used,
            chi2_rejections=stats.rejected,
            diverged=bool(self._diverged_reason),
            reason=self._diverged_reason,
            conditions=tuple(conds),
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
        zupt_allowed = p.zupt_enabled and not (p.zupt_only_at_beginning and self._has_moved)
        if zupt_allowed and self._try_zupt(tracks, t_imu):
            conditions.append("zupt")
            self.zupt_count += 1
            stats = UpdateStats()
        elif not self._is_keyframe(tracks):
            self._frames_since_clone += 1
            stats = UpdateStats()
        else:
            self._frames_since_clone = 0
            self._keyframe_tracks = tracks
            self.propagator.propagate_and_clone(st, frame.t_s)
            self.database.add(frame.t_s, tracks.ids, tracks.xy_norm)
            stats = self._msckf_update(frame.t_s)
            if len(st.clones) > p.max_clones:
                t_old = marginalize_oldest_clone(st)
                if t_old is not None:
                    self.database.remove_frame(t_old)
        self._prev_frame_t_imu = t_imu
        self._version += 1
        self._check_divergence(stats)
        self.last_stats = stats
        self._health = self._make_health(frame.t_s, tracks, stats, tuple(conditions))

    def _is_keyframe(self, tracks: Tracks) -> bool:
        """Parallax-based keyframe test (VINS-Mono's rule; lesson ch. 8 "keyframe selection").

        A frame becomes a clone when the median pixel motion of the features shared with the last clone
        reaches ``keyframe_min_parallax_px``, when fewer than half of them are still tracked, or after
        ``clone_every_n_frames`` frames at the latest (1 = every frame is a clone).
        """
        p = self.params
        if self._frames_since_clone + 1 >= p.clone_every_n_frames or self._keyframe_tracks is None:
            return True
        ref = self._keyframe_tracks
        _, i_ref, i_now = np.intersect1d(ref.ids, tracks.ids, return_indices=True)
        if len(i_now) < max(0.5 * len(ref.ids), 1):
            return True
        parallax = np.median(np.linalg.norm(tracks.uv_px[i_now] - ref.uv_px[i_ref], axis=1))
        return bool(parallax >= p.keyframe_min_parallax_px)

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
                f"gate or the triangulation reprojection gate in {self._runaway_count} consecutive frames"
            )

    def _try_zupt(self, tracks: Tracks, t_imu: float) -> bool:
        """Zero-velocity update when features barely move and the IMU agrees (open_vins ZUPT idea)."""
        st = self.state
        assert st is not None
        p = self.params
        prev = self._prev_tracks
        if prev is None or self._prev_frame_t_imu is None or len(tracks) == 0 or len(prev) == 0:
            return False
        _, ia, ib = np.intersect1d(tracks.ids, prev.ids, assume_unique=True, return_indices=True)
        if len(ia) < p.zupt_min_features:
            return False
        disparity_px = float(np.median(np.linalg.norm(tracks.uv_px[ia] - prev.uv_px[ib], axis=1)))
        if disparity_px > p.zupt_max_disparity_px or np.linalg.norm(st.imu.v_WB) > p.zupt_max_velocity_m_s:
            self._has_moved = True
            return False
        t0 = self._prev_frame_t_imu
        if t_imu - t0 <= 1e-6:
            return False
        _, g, a = self.propagator.readings(t0, t_imu)
        T = t_imu - t0
        # Rows: mean gyro = b_g, mean accel = R^T (0, 0, g) + b_a, velocity = 0.
        g_up_B = st.imu.R_WB.T @ np.array([0.0, 0.0, GRAVITY_M_S2])
        r = np.concatenate(
            [
                g.mean(axis=0) - st.imu.gyro_bias_rad_s,
                a.mean(axis=0) - g_up_B - st.imu.accel_bias_m_s2,
                -st.imu.v_WB,
            ]
        )
        H = np.zeros((9, st.dim))
        H[0:3, BG : BG + 3] = np.eye(3)
        H[3:6, THETA : THETA + 3] = np.array(
            [[0.0, -g_up_B[2], g_up_B[1]], [g_up_B[2], 0.0, -g_up_B[0]], [-g_up_B[1], g_up_B[0], 0.0]]
        )
        H[3:6, BA : BA + 3] = np.eye(3)
        H[6:9, VEL : VEL + 3] = np.eye(3)
        m2 = p.zupt_noise_multiplier**2
        R = np.diag(
            [m2 * self.noise.gyro_noise_density_rad_s_sqrthz**2 / T] * 3
            + [m2 * self.noise.accel_noise_density_m_s2_sqrthz**2 / T] * 3
            + [p.zupt_velocity_sigma_m_s**2] * 3
        )
        S = H @ st.cov @ H.T + R
        chi2 = float(r @ np.linalg.solve(S, r))
        if chi2 > p.chi2_multiplier * float(self.chi2(9)):
            return False
        # All 9 rows test stillness; by default only the gyro and velocity rows update the state. The
        # accelerometer rows would write any small acceleration at the onset of motion (a min-jerk takeoff
        # starts with zero acceleration, below the gate) into the accelerometer bias: measured 0.2 m/s^2,
        # then 0.2-0.3 m of altitude error over a 1.2 s climb.
        rows = np.arange(9) if p.zupt_update_accel else np.r_[0:3, 6:9]
        ekf_update(st, H[rows], r[rows], R[np.ix_(rows, rows)])
        return True

    def _msckf_update(self, t_now: float) -> UpdateStats:
        """MSCKF update (Mourikis and Roumeliotis 2007, sec. III-D/E; open_vins ``UpdaterMSCKF::update``)."""
        st = self.state
        assert st is not None
        p = self.params
        db = self.database
        # 0. Features whose tracks ended, plus those seen in the oldest clone when it is about to go.
        lost = db.features_lost(t_now)
        cand = lost
        times = st.clone_times
        if len(st.clones) > p.max_clones:
            cand = np.union1d(lost, db.features_seen_at(float(times[0])))
        if len(cand) == 0:
            return UpdateStats()
        # 1. Clean: observations at clone times only (the database is keyed by clone time) and tracks
        #    long enough; the other lost features can never be used.
        lengths = db.track_lengths(cand)
        usable = lengths >= p.min_track_length
        db.remove_features(lost[~np.isin(lost, cand[usable])])
        cand, lengths = cand[usable], lengths[usable]
        if len(cand) == 0:
            return UpdateStats()
        order = np.argsort(-lengths, kind="stable")[: p.max_features_per_update]
        cand = cand[order]
        xy, mask = db.observations(cand, times)
        db.remove_features(cand)
        clones = list(st.clones.values())
        R_WB = np.stack([c.R_WB for c in clones])
        p_WB = np.stack([c.p_WB for c in clones])
        R_WC = R_WB @ st.R_BC
        p_WC = p_WB + R_WB @ st.p_BC
        # 2. Triangulate every feature in the current clone estimates.
        tri = triangulate(R_WC, p_WC, xy, mask, p.triangulation, self._focal_px)
        ok = tri.valid
        n_cand = len(cand)
        n_bad = int(np.sum(tri.rms_error_px >= p.triangulation.max_reprojection_error_px))
        if not np.any(ok):
            return UpdateStats(candidates=n_cand, inconsistent=n_bad)
        xy, mask, p_f = xy[ok], mask[ok], tri.p_W[ok]
        F, K = mask.shape
        # 3. Residuals at the current estimates; Jacobians where ``update_linearization`` says.
        cur = feature_jacobian(R_WB[None], p_WB[None], st.R_BC, st.p_BC, p_f[:, None, :])
        if p.use_fej and p.update_linearization == "first_estimates":
            R_fej = np.stack([c.R_WB_fej for c in clones])
            p_fej = np.stack([c.p_WB_fej for c in clones])
            jac = feature_jacobian(R_fej[None], p_fej[None], st.R_BC, st.p_BC, p_f[:, None, :])
        else:
            jac = cur
        w = mask[..., None].astype(float)
        r = ((xy - cur.z_norm) * w).reshape(F, 2 * K)
        H_f = (jac.H_feature * w[..., None]).reshape(F, 2 * K, 3)
        H_x = np.zeros((F, 2 * K, st.dim))
        H_pose = jac.H_pose * w[..., None]
        for k, t in enumerate(times):
            o = st.clone_block(float(t)).offset
            H_x[:, 2 * k : 2 * k + 2, o : o + 6] = H_pose[:, k]
        if st.has_block(EXTRINSIC_BLOCK):
            o = st.block(EXTRINSIC_BLOCK).offset
            H_x[:, :, o : o + 6] = (jac.H_extrinsic * w[..., None]).reshape(F, 2 * K, 6)
        # 4. Null-space projection removes the feature (padded rows are zero and drop out exactly).
        H_o, r_o = nullspace_project(H_x, H_f, r)
        if p.use_fej and p.update_linearization == "current_oc":
            # 4b. Observability constraint: no information on global position/yaw at the first estimates,
            #     the directions the FEJ propagation keeps unobservable (Hesch et al. TRO 2014, OC-EKF).
            offsets = np.array([st.clone_block(float(t)).offset for t in times])
            R_fej = np.stack([c.R_WB_fej for c in clones])
            p_fej = np.stack([c.p_WB_fej for c in clones])
            U = clone_unobservable_basis(R_fej, p_fej, offsets, st.dim)
            H_o = observability_constrain(H_o, U)
        # 5. Chi-square gate at 95 % per feature with dof = 2 m - 3.
        P = st.cov
        sigma2 = self._sigma_norm**2
        HP = (H_o.reshape(-1, st.dim) @ P).reshape(H_o.shape)
        S = HP @ np.swapaxes(H_o, 1, 2)
        S[:, np.arange(S.shape[1]), np.arange(S.shape[1])] += sigma2
        chi2 = np.einsum("fi,fi->f", r_o, np.linalg.solve(S, r_o[..., None])[..., 0])
        dof = 2 * mask.sum(axis=1) - 3
        passed = chi2 < p.chi2_multiplier * self.chi2(dof)
        n_pass = int(passed.sum())
        nis = chi2 / dof
        stats = UpdateStats(
            n_cand,
            F,
            n_pass,
            int(F - n_pass),
            int(dof[passed].sum()),
            n_bad,
            float(np.mean(nis[passed])) if n_pass else float("nan"),
            float(np.mean(nis)),
        )
        if n_pass == 0:
            return stats
        # 6. Stack, compress (QR) and update.
        H_all = H_o[passed].reshape(-1, st.dim)
        r_all = r_o[passed].reshape(-1)
        H_c, r_c = measurement_compress(H_all, r_all)
        ekf_update(st, H_c, r_c, sigma2)
        # 7. Marginalizing the oldest clone is done by the caller after this update.
        return stats
