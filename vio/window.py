"""The sliding-window visual-inertial estimator: WindowEstimator and WindowParams (OKVIS / VINS-Mono style).

References: Leutenegger et al., "Keyframe-based visual-inertial odometry using nonlinear optimization",
IJRR 2015 (OKVIS); Qin, Li, Shen, "VINS-Mono", TRO 2018; Forster et al., "On-manifold preintegration",
TRO 2017.

State: a window of keyframes ``x_k = [R_WB, p_WB, v_WB, b_g, b_a]`` and landmarks as 3D points in W
(:mod:`viotb.vio.window_map`). Every keyframe (:mod:`viotb.vio.keyframing`):

1. Preintegrate the IMU from the previous keyframe and predict the new one (Forster eq. 33;
   :mod:`viotb.vio.window_factors`).
2. Triangulate features seen in ``min_track_length`` keyframes that are not landmarks yet (on a stereo rig,
   also those one keyframe sees in both cameras: their depth comes from the baseline, so scale is
   observable from the first keyframe).
3. Minimize by Levenberg-Marquardt the IMU factors, the robust reprojection factors (cam1's with cam1's
   extrinsics on a stereo rig), the zero-velocity factors of still keyframes (:mod:`viotb.vio.zero_velocity`)
   and the linear prior left by marginalization (OKVIS eq. 9), landmarks eliminated by the Schur complement
   (:mod:`viotb.vio.window_solver`, factors batched in :mod:`viotb.vio.window_batch`; a solve unconverged
   after ``keyframe_frame_iterations`` steps takes the rest of its budget on the next frame). Before that, the
   IMU-predicted keyframe's observations of existing landmarks give the NIS per dof of its health record
   (:mod:`viotb.vio.window_nis`; the monitor's time-sync test reads it). Online calibration (off by default):
   the extrinsics and time offset join the variables (:mod:`viotb.vio.window_calib`; health ``calibration``).
4. When the window is full, marginalize the oldest keyframe together with every landmark it observed
   (with all their observations) into a new linear prior (:mod:`viotb.vio.window_marginalize`). Those
   landmarks' later observations start fresh tracks, so no measurement is used twice; the observations in
   the old keyframe of features that are not landmarks yet are dropped.

Bad inputs: non-finite IMU values, non-increasing IMU times, and an unknown front end raise ``ValueError``
naming the value. Divergence (non-finite state, cost blow-up, singular system) is reported through
``health().diverged`` with a reason; the estimator then stops optimizing and never raises from numpy.
"""

from __future__ import annotations

import time

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.frontend import FrontEnd, Tracks, make_frontend
from viotb.vio.frontend_stereo import make_stereo_frontend
from viotb.vio.initialization import InertialInitializer, init_params_for
from viotb.vio.keyframing import KeyframeSelector
from viotb.vio.lifecycle import attempt_initialization, excitation_wanted, frame_health
from viotb.vio.marginalization import LinearPrior
from viotb.vio.propagator import ImuBuffer, select_imu_readings
from viotb.vio.state import read_init_record
from viotb.vio.types import CameraFrame, HealthStatus, ImuNoise, ImuSample, StateEstimate
from viotb.vio.window_batch import integrate_gyro
from viotb.vio.window_calib import CalibValues
from viotb.vio.window_calib_state import OnlineCalibration
from viotb.vio.window_divergence import divergence_reason
from viotb.vio.window_factors import (
    NX,
    boxminus,
    imu_factor,
    keyframe_estimate,
    predict,
    preintegrate,
    reprojection,
    repropagate,
    retract,
    seen_behind,
)
from viotb.vio.window_init import couple_static_tilt_bias
from viotb.vio.window_map import ImuLink, Keyframe, drop_landmark, triangulate_new
from viotb.vio.window_marginalize import marginalize_oldest, solve_factors
from viotb.vio.window_nis import InnovationTest, WindowMarginals, innovation_test
from viotb.vio.window_params import WindowParams, track_noise_q
from viotb.vio.window_reprojection import LandmarkOutlierTest
from viotb.vio.window_solver import (
    FactorWeights,
    LinearSystem,
    SolveState,
    newest_keyframe_covariance,
    solve_steps,
    start_solve,
)
from viotb.vio.window_weights import stereo_weights
from viotb.vio.zero_velocity import ZeroVelocityDetector

__all__ = [
    "NX",
    "WindowEstimator",
    "WindowParams",
    "boxminus",
    "imu_factor",
    "preintegrate",
    "reprojection",
    "retract",
]


class WindowEstimator:
    """The sliding-window optimizer (implements :class:`viotb.vio.types.Estimator`).

    Args:
        calib: Cam0 intrinsics, extrinsics (``R_BC``, ``p_BC``) and time offset.
        noise: IMU noise densities.
        params: Settings.
        frontend: Optional front end overriding ``params.frontend``.
        calib_right: Cam1 of a stereo rig (its own ``R_BC``, ``p_BC``; synchronized with cam0), or None.
    """

    name = "window"

    def __init__(
        self,
        calib: CameraCalibration,
        noise: ImuNoise,
        params: WindowParams | None = None,
        frontend: FrontEnd | None = None,
        calib_right: CameraCalibration | None = None,
    ) -> None:
        """Create an uninitialized estimator."""
        self.calib = calib
        self.calib_right = calib_right
        self.noise = noise
        self.params = params if params is not None else WindowParams()
        p = self.params
        if not 2 <= p.window_size <= 60:
            raise ValueError(f"WindowParams.window_size must be in 2..60, got {p.window_size}")
        if not p.pixel_sigma_px > 0.0:
            raise ValueError(f"WindowParams.pixel_sigma_px must be > 0, got {p.pixel_sigma_px}")
        if frontend is None:
            mono = make_frontend(p.frontend, calib.camera, p.klt, "WindowParams")
            frontend = make_stereo_frontend(mono, calib, calib_right, p.stereo)
        self.frontend = frontend
        self.initializer = InertialInitializer(calib, noise, init_params_for(p.frontend))
        self.buffer = ImuBuffer()
        self._focal_px = 0.5 * (calib.camera.fx + calib.camera.fy)
        self._sigma_norm = p.pixel_sigma_px / self._focal_px
        self._R_BC = np.asarray(calib.R_BC, dtype=float)
        self._p_BC = np.asarray(calib.p_BC, dtype=float)
        self.keyframes: list[Keyframe] = []
        self.links: list[ImuLink] = []
        self.landmarks: dict[int, np.ndarray] = {}
        self.prior: LinearPrior | None = None
        self._next_key = 0
        self._cov_newest = np.zeros((NX, NX))
        self._last_imu: ImuSample | None = None
        self.keyframe_rule = KeyframeSelector(p.keyframing)
        self.zero_velocity = ZeroVelocityDetector(p.zero_velocity, noise, chi2_gate=16.92)
        self._outliers = LandmarkOutlierTest.create(p.outlier_threshold, p.outlier_chi2, p.window_size)
        self._prev_tracks: Tracks | None = None
        self._weights = FactorWeights(
            noise,
            self._R_BC,
            self._p_BC,
            self._sigma_norm,
            p.huber_threshold,
            p.zero_velocity.velocity_sigma_m_s,
            *stereo_weights(calib_right, p.pixel_sigma_px),
            track_q=track_noise_q(p),
            focal_px=self._focal_px,
            focal_px1=1.0 if calib_right is None else 0.5 * (calib_right.camera.fx + calib_right.camera.fy),
        )
        self._last_cost_per_res = 0.0
        self._marginals: WindowMarginals | None = None
        self._solved: tuple[LinearSystem, list[int]] | None = None
        self._solve: tuple[SolveState, list[int], tuple] | None = None  # a solve going on over frames
        self._innovation = InnovationTest()
        self._cal_off = OnlineCalibration.create(p, calib, calib_right)  # None: the files' calibration
        self._cal: OnlineCalibration | None = None  # it, once its variables are in the window
        self._cams = CalibValues.from_files(calib, calib_right).cameras()  # current (R_BC, p_BC) per camera
        self._health = HealthStatus(t_s=0.0, initialized=False)
        self._diverged_reason = ""
        self._blowups = 0
        self._used = 0
        self._n_bad = 0
        self._version = 0
        self._est_cache: tuple[int, float, StateEstimate] | None = None
        self.solve_times_s: list[float] = []  # every solve: keyframes' and their continuations'
        self.keyframes_added = 0
        self.solve_iterations: list[int] = []

    # ---------------------------------------------------------------------------------------- protocol
    def initialize(self, init: object) -> None:
        """Start from an ``InitResult`` (t_s, R_WB, p_WB, v_WB, biases, cov_diag (15,)).

        It becomes the first keyframe, with a prior ``diag(1 / cov_diag)`` (which fixes the gauge: position
        and yaw); after a static initialization its tilt and horizontal accelerometer bias are coupled
        (:mod:`viotb.vio.window_init`, ``WindowParams.static_tilt_bias_sigma_m_s2``).
        """
        t_s, vals, cov = read_init_record(init)
        sigma_i = self.params.static_tilt_bias_sigma_m_s2
        if sigma_i is not None and getattr(init, "method", "") == "static":
            cov = couple_static_tilt_bias(cov, vals.R_WB, sigma_i)
        gyro = np.zeros(3) if self._last_imu is None else np.asarray(self._last_imu.gyro_B_rad_s, dtype=float)
        kf = Keyframe(self._next_key, t_s, vals.copy(), {}, gyro_B_rad_s=gyro)
        self._next_key += 1
        self.keyframes, self.links, self.landmarks = [kf], [], {}
        self.prior = LinearPrior(np.linalg.inv(cov), np.zeros(NX), [kf.key], [vals.copy()])
        self._cal = None
        self._cov_newest = cov
        self._marginals = None
        self._solved, self._solve = None, None
        self.keyframe_rule.forget_reference()
        self._version += 1
        self._health = HealthStatus(t_s=t_s, initialized=True)

    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer one IMU reading (ValueError naming value/time on NaN/inf or non-increasing time)."""
        self.buffer.feed(sample)
        self._last_imu = sample
        if not self.keyframes and self.initializer is not None:
            self.initializer.feed_imu(sample)

    def feed_camera(self, frame: CameraFrame) -> None:
        """Track features; on keyframes add a state, optimize the window and marginalize the oldest."""
        t_imu = float(frame.t_s) + self.calib.time_offset_s
        tracks = self.frontend.process(frame, t_imu)
        if not self.keyframes:
            self._try_initialize(tracks)
            return
        if t_imu <= self.keyframes[-1].t_s:
            raise ValueError(
                f"camera frame at t={frame.t_s:.9f} s (IMU clock {t_imu:.9f} s) is not newer "
                f"than the newest keyframe ({self.keyframes[-1].t_s:.9f} s)"
            )
        still = self._update_stillness(tracks)
        if self._diverged_reason or not self._is_keyframe(tracks):
            self.keyframe_rule.skip()
            if self._solve is not None and not self._diverged_reason:
                self._continue_solve()
            self._health = self._make_health(frame.t_s, tracks)
            return
        self.keyframe_rule.accept(tracks)
        self.keyframes_added += 1
        try:
            self._add_keyframe(tracks, still)
        except (np.linalg.LinAlgError, FloatingPointError) as exc:
            self._diverged_reason = f"numerical failure in the optimization: {exc}"
            self._solve = None
        self._version += 1
        self._health = self._make_health(frame.t_s, tracks, self._innovation)

    def estimate(self) -> StateEstimate | None:
        """Newest keyframe propagated with the IMU to the newest sample.

        The covariance is the inverse of the window's marginal information of that keyframe, propagated
        with the IMU factor's Jacobians.
        """
        if not self.keyframes:
            return None
        kf = self.keyframes[-1]
        t_new = self._last_imu.t_s if self._last_imu is not None else kf.t_s
        if self._est_cache is not None and self._est_cache[:2] == (self._version, t_new):
            return self._est_cache[2]
        readings = self._readings(kf.t_s, t_new) if t_new > kf.t_s + 1e-9 else None
        gyro = None if self._last_imu is None else self._last_imu.gyro_B_rad_s
        args = (self.noise, self.params.midpoint_rotation, gyro, self._intrinsics())
        est = keyframe_estimate(kf.x, self._cov_newest, kf.t_s, readings, *args)
        self._est_cache = (self._version, t_new, est)
        return est

    def health(self) -> HealthStatus:
        """Health after the latest camera frame."""
        return self._health

    def wants_excitation(self) -> bool:
        """True while the newest keyframe's horizontal accelerometer-bias sigma is above its threshold.

        See :func:`viotb.vio.lifecycle.excitation_wanted`; threshold ``excitation_accel_bias_sigma_m_s2``.
        """
        sigma_m_s2 = self.params.excitation_accel_bias_sigma_m_s2
        return bool(self.keyframes) and excitation_wanted(self._cov_newest, sigma_m_s2)

    def feed_truth(self, truth: StateEstimate) -> None:
        """Truth is not used by the optimizer (no-op; part of :class:`viotb.vio.types.Estimator`)."""

    def last_tracks_px(self) -> np.ndarray:
        """Distorted pixels of the features tracked in the latest frame, shape (M, 2) (for viewers)."""
        tracks = self._prev_tracks
        return np.zeros((0, 2)) if tracks is None else tracks.uv_px

    # --------------------------------------------------------------------------------------- internals
    def _try_initialize(self, tracks: Tracks) -> None:
        init, health = attempt_initialization(self.initializer, tracks)
        if init is not None:
            self.initialize(init)
        self._health = health

    def _is_keyframe(self, tracks: Tracks) -> bool:
        """The keyframe rule, given the camera rotation since the newest keyframe when it compensates it.

        The rotation is the gyro, less the newest keyframe's bias, integrated from that keyframe to the frame
        (midpoint readings, the preintegration's rotation without its covariance and Jacobians).
        """
        rule = self.keyframe_rule
        if not rule.params.rotation_compensated:
            return rule.is_keyframe(tracks)
        kf = self.keyframes[-1]
        t, gyro, _ = self._readings(kf.t_s, tracks.t_imu_s)
        R_BrBn = integrate_gyro(t, gyro, kf.x.gyro_bias_rad_s)
        return rule.is_keyframe(tracks, self._R_BC.T @ R_BrBn @ self._R_BC, self._focal_px)

    def _update_stillness(self, tracks: Tracks) -> bool:
        """Whether the interval since the previous frame was still (:mod:`viotb.vio.zero_velocity`).

        The IMU must agree with the features: a slow min-jerk takeoff moves features by less than the
        disparity gate while the IMU already integrates centimetres per second.
        """
        prev, self._prev_tracks = self._prev_tracks, tracks
        if prev is None or not self.zero_velocity.allowed():
            return False
        est = self.estimate()
        if est is None:
            return False
        t0, t1 = prev.t_imu_s, tracks.t_imu_s
        test = self.zero_velocity.detect(
            prev, tracks, t1 - t0, est, est.cov, lambda: self._readings(t0, t1)[1:]
        )
        return test is not None

    def _intrinsics(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The IMU's current correction matrices ``(T_g, T_a)`` when they are estimated (from the start)."""
        return None if self._cal_off is None else self._cal_off.imu_matrices()

    def _readings(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t, g, a = self.buffer.arrays()
        return select_imu_readings(t, g, a, t0, t1)

    def _add_keyframe(self, tracks: Tracks, still: bool = False) -> None:
        p = self.params
        last = self.keyframes[-1]
        t_s = tracks.t_imu_s
        # An unfinished solve ends here; this one takes a next frame's steps now too (keyframes in a row).
        st = None if self._solve is None else self._solve[0]
        cut = st is not None and not st.converged and st.iterations < p.max_iterations
        self._finish_solve()
        self._n_bad = 0
        # 1. Preintegrate and predict the new keyframe (Forster eq. 33).
        readings = self._readings(last.t_s, t_s)
        pre = preintegrate(*readings, last.x, self.noise, p.midpoint_rotation, self._intrinsics())
        x = predict(pre, last.x)
        obs = {int(i): xy for i, xy in zip(tracks.ids.tolist(), tracks.xy_norm, strict=True)}
        self._innovation = InnovationTest()
        if self._marginals is not None:
            cam = (*self._cams[0], self._sigma_norm, p.triangulation.min_depth_m)
            td = None if self._cal is None else (self._cal.values.td_s, readings[1][-1])
            self._innovation = innovation_test(
                self._marginals, pre, last.x, x, self.noise, obs, self.landmarks, cam, td
            )
        obs1 = {}
        if self.calib_right is not None:
            obs1 = {int(i): xy for i, xy in zip(tracks.ids_right.tolist(), tracks.xy_norm_right, strict=True)}
        gyro = readings[1][-1].copy()
        self.keyframes.append(Keyframe(self._next_key, t_s, x, obs, still, obs1, gyro_B_rad_s=gyro))
        self._next_key += 1
        self.links.append(ImuLink(pre, readings))
        # 2. New landmarks, 3. optimize (the rest of the step budget on the next frames), 4. marginalize.
        self._triangulate_new()
        self._start_solve()
        steps = min(p.keyframe_frame_iterations + (p.frame_iterations if cut else 0), p.max_iterations)
        self._solve_steps(steps, True)
        self.buffer.clean_older_than(self.keyframes[0].t_s - 1.0)

    def _triangulate_new(self) -> None:
        p = self.params
        cams = self._cams
        stereo = self.calib_right is not None and p.stereo_landmarks
        limits = (p.min_track_length, p.max_landmarks, stereo)
        tri = (p.triangulation, self._focal_px)
        self._n_bad += triangulate_new(self.keyframes, self.landmarks, limits, cams, *tri)

    def _continue_solve(self) -> None:
        """Take up to ``frame_iterations`` more steps of the keyframe's solve on this (non-keyframe) frame."""
        try:
            self._solve_steps(self.params.frame_iterations, False)
        except (np.linalg.LinAlgError, FloatingPointError) as exc:
            self._diverged_reason = f"numerical failure in the optimization: {exc}"
            self._solve = None
        self._version += 1

    def _start_solve(self) -> None:
        """Levenberg-Marquardt over the window, landmarks eliminated by the Schur complement: its factors.

        The solve (:func:`viotb.vio.window_solver.start_solve`) takes its ``max_iterations`` steps over the
        keyframe's frame (``keyframe_frame_iterations``) and the next frames (``frame_iterations`` each); the
        values it reached are the estimate meanwhile. Taken in parts it makes the same steps as in one go.
        """
        p = self.params
        # 0. Re-integrate preintegrations whose bias moved far from its linearization point (lesson ch. 5).
        tol = (p.repropagate_gyro_bias_rad_s, p.repropagate_accel_bias_m_s2, p.midpoint_rotation)
        repropagate(self.links, [kf.x for kf in self.keyframes], self.noise, *tol, self._intrinsics())
        due = self._cal is None and len(self.keyframes) >= p.calibration_start_keyframes
        if due and self._cal_off is not None:  # the calibration's variables enter the window
            self._cal, self.prior = self._cal_off, self._cal_off.start_prior(self.prior)
        lm_ids, pts, f = solve_factors(self.keyframes, self.links, self.prior, self.landmarks)
        fej = [kf.x_fej for kf in self.keyframes] if p.first_estimate_jacobians else None
        cal = None if self._cal is None else self._cal.values
        f = f if self._cal is None else self._cal.factors(self.keyframes, f)
        st = start_solve([kf.x for kf in self.keyframes], pts, f, self._weights, p.initial_damping, fej, cal)
        self._solve = (st, lm_ids, (f.obs, f.obs_right))

    def _solve_steps(self, steps: int, on_keyframe: bool) -> None:
        """Up to ``steps`` more trial steps of the solve; it finishes at its budget or when it converged.

        A split solve (``keyframe_frame_iterations < max_iterations``) finishes on a later frame, never on
        its keyframe's: the keyframe's frame then reports the newest keyframe's covariance of the system.
        """
        t0 = time.perf_counter()
        p = self.params
        assert self._solve is not None
        st, lm_ids, _ = self._solve
        self.solve_iterations.append(
            solve_steps(
                st, min(steps, p.max_iterations - st.iterations), p.relative_tolerance, p.min_cost_decrease
            )
        )
        for kf, x in zip(self.keyframes, st.xs, strict=True):
            kf.x = x
        for j, fid in enumerate(lm_ids):
            self.landmarks[fid] = st.pts[j]
        if self._cal is not None:
            self._cal.values, self._cams = st.calib, st.calib.cameras()
        done = st.converged or st.iterations >= p.max_iterations
        if done and (not on_keyframe or p.keyframe_frame_iterations >= p.max_iterations):
            self._finish_solve()
        elif on_keyframe:  # the estimate meanwhile: the newest keyframe's covariance at the values reached
            self._cov_newest = newest_keyframe_covariance(st.system)
        self.solve_times_s.append(time.perf_counter() - t0)

    def _finish_solve(self) -> None:
        """End the solve where its steps reached: covariances, outliers, marginalization, divergence."""
        if self._solve is None:
            return
        p = self.params
        st, lm_ids, (obs, obs1) = self._solve
        self._solve = None
        xs, pts, sys = st.xs, st.pts, st.system
        # 5. Covariances: the newest keyframe's (the inverse of its marginal information) and those the next
        #    keyframe's innovation test needs (:mod:`viotb.vio.window_nis`).
        self._marginals = WindowMarginals.from_system(sys, lm_ids)
        self._solved = (sys, lm_ids)
        self._cov_newest = self._marginals.newest_covariance
        if self._cal is not None:
            self._cal.cov = self._marginals.calib_cov
        self._last_cost_per_res = sys.meas_cost / max(sys.n_res, 1)
        self._used = len(lm_ids)
        # 6. Outliers and landmarks behind a camera leave the window with their observations.
        if len(lm_ids):
            cams = [(obs, *self._cams[0])]
            if self.calib_right is not None:
                cams.append((obs1, *self._cams[1]))
            bad = self._outliers(sys) | seen_behind(xs, pts, cams, p.triangulation.min_depth_m)
            for j in np.nonzero(bad)[0]:
                drop_landmark(self.keyframes, self.landmarks, lm_ids[j])
            self._n_bad, self._used = self._n_bad + int(np.sum(bad)), len(lm_ids) - int(np.sum(bad))
        self._marginalize_full()
        self._check_divergence()

    def _marginalize_full(self) -> None:
        """Fold the oldest keyframe and the landmarks it saw into a new linear prior (Schur complement).

        Only when the window holds more than ``window_size`` keyframes.
        """
        if len(self.keyframes) <= self.params.window_size:
            return
        self.prior, self.keyframes, self.links = marginalize_oldest(
            self.keyframes,
            self.links,
            self.landmarks,
            self.prior,
            self._weights,
            self.params.first_estimate_jacobians,
            self._solved,
            self._cal,
        )
        self._solved = None

    def _check_divergence(self) -> None:
        if self._diverged_reason:
            return
        self._diverged_reason, self._blowups = divergence_reason(
            self.keyframes[-1].x,
            self._cov_newest,
            self.params,
            self._last_cost_per_res,
            self._used,
            self._n_bad,
            self._blowups,
        )

    def _make_health(
        self, t_s: float, tracks: Tracks, innovation: InnovationTest | None = None
    ) -> HealthStatus:
        """Health of a frame; a keyframe's has the NIS of its observations (:mod:`viotb.vio.window_nis`)."""
        inn = innovation if innovation is not None else InnovationTest()
        return frame_health(
            t_s,
            tracks,
            self._diverged_reason,
            updated_features=self._used,
            chi2_rejections=inn.rejected,
            nis_per_dof=inn.nis_per_dof,
            nis_per_dof_all=inn.nis_per_dof_all,
            calibration=None if self._cal is None else self._cal.drift(),
        )
