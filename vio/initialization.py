"""Inertial (static) and visual-inertial (dynamic) initialization, after open_vins' ``InertialInitializer``.

The estimator needs gravity direction (roll/pitch), velocity, gyro bias and, for a monocular camera, metric
scale before it can start (lesson, Chapter 6). Two paths, chosen from the window:

* Static (open_vins ``StaticInitializer``): a full IMU window whose accelerometer and gyro standard deviations
  are below thresholds, and no image parallax. The mean specific force is "up" in B, giving roll/pitch
  (yaw = 0 is the gauge); the mean gyro is the gyro bias; velocity and position are zero.
* Dynamic (:mod:`viotb.vio.init_dynamic`, open_vins ``DynamicInitializer``): as soon as the frames span
  ``min_dynamic_window_s`` and show parallax, every ``dynamic_try_every_frames``-th frame tries the
  visual-inertial alignment over the frames of the last ``dynamic_window_s`` and accepts it only when the
  window makes the metric scale and the gravity direction observable (their sigmas, image and IMU errors
  counted, below ``max_scale_sigma`` / ``max_tilt_sigma_rad``), not after a fixed accelerometer-excitation
  threshold. A start in motion initializes as soon as the motion determines the scale; a constant-velocity
  start never does (its scale is unobservable), nor does a coordinated turn at constant speed (its scale
  trades with a body-fixed accelerometer bias, known only to its prior). The covariance handed to the
  estimator is the solve's.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.init_dynamic import dynamic_alignment
from viotb.vio.init_preintegration import RunningPreintegration
from viotb.vio.lie import exp_so3, rotz, yaw_from_rotmat
from viotb.vio.types import GRAVITY_M_S2, ImuNoise, ImuSample


@dataclass(frozen=True)
class InitParams:
    """Initializer settings (defaults suit the EuRoC ADIS16448 and 20 Hz cameras).

    Attributes:
        window_s: Length (s) of the IMU/feature window of the static initializer.
        dynamic_window_s: The dynamic solve uses the frames of the last this many seconds (the longer the
            window, the better a gentle motion determines the scale; the test decides when it is enough).
        still_accel_std_m_s2: Static if the accelerometer std (m/s^2, RMS over axes) is below this.
        still_gyro_std_rad_s: Static if the gyro std (rad/s, RMS over axes) is below this.
        still_max_disparity: Static only if the mean feature displacement across the window (normalized
            image coordinates) is below this (open_vins ``init_max_disparity``, ~4.6 px at f = 460 px).
        min_dynamic_window_s: The dynamic solve is tried once the frames span this long (s).
        min_parallax: The dynamic solve is tried only if the mean feature displacement across the window
            (normalized image coordinates) reaches this (without parallax nothing fixes the scale).
        max_scale_sigma: Accept a dynamic solution only if the relative 1-sigma of its metric scale is at
            most this: the larger of those of the window's trajectory length and of the speed at the end,
            counting image noise, the accelerometer-bias prior, IMU noise, bias random walk and the IMU's
            scale/misalignment errors (:func:`~viotb.vio.init_dynamic.dynamic_alignment`, step 7; measured
            errors over seeds follow it like N(0, 1)). 0.0067: a 2 % scale error is 3 sigma.
        max_tilt_sigma_rad: ... and the 1-sigma of the gravity direction at the end at most this (rad; the
            bias prior alone allows ``sigma_accel_bias_m_s2 / 9.81`` = 0.01 rad until rotation separates
            the two).
        dynamic_try_every_frames: Try the dynamic solve on every this many frames (each try costs about
            0.1 s of CPU; successive tries share the preintegration).
        max_refine_iterations: Levenberg-Marquardt iterations of the refinement.
        pixel_sigma_px: Floor of the image noise (px) assumed by the observability test (the measured
            residual RMS when larger).
        track_random_walk_px2_per_px: Variance (px^2) a track's error gains per px the feature moves,
            on top of the white ``pixel_sigma_px``; the dynamic solve whitens each track with it (the
            MSCKF's model, :func:`~viotb.vio.update_helpers.random_walk_whitener`). 0: white errors, as
            simulated features have; KLT: see :func:`init_params_for`.
        min_depth_m: Depth floor (m) of the row weights of the linear solve.
        min_features: Minimum number of features tracked in at least ``min_feature_obs`` frames.
        min_feature_obs: Observations a feature needs to enter the dynamic solve.
        min_frames: Minimum number of camera frames in the window for the dynamic solve.
        max_frames: Frames used by the dynamic solve (evenly subsampled from the window; 30: all frames of
            the first 1.5 s at 20 Hz).
        max_features: Features used by the dynamic solve (the longest tracks).
        max_gravity_norm_error: Reject the dynamic solution if the unconstrained |g| differs from 9.81 by
            more than this fraction.
        max_reprojection_rms: Reject the dynamic solution if the refined RMS reprojection error (normalized
            coordinates) is above this.
        sigma_tilt_rad: Reported 1-sigma of the orientation error at initialization (rad), roll and pitch.
        sigma_position_m: Reported 1-sigma of the position (gauge) (m). The first pose is the origin of the
            world frame, so its error is zero by definition, as the yaw's (below); a sigma there is a floor
            that the position covariance can never lose (unobservable) and that the anchored NEES does not
            see. 1e-4 m (was 1e-3): on 20 s KLT ``hover`` recordings, where the errors are millimetres, the
            1 mm floor made the filter underconfident (MSCKF told 0.03 px and 0.0001 px^2/px, seed 0: position
            NEES 1.43 -> 2.27, 2.29 at 1e-5 m, ATE 4.49 mm in all three); on the moving scenarios it is
            negligible (``viotb regress --full``: every seeded metric within its tolerance).
        sigma_yaw_rad: Reported 1-sigma of the yaw (gauge) (rad). Yaw 0 at the first pose defines the world
            frame, so its error there is zero by definition; with the tilt's 0.01 rad instead, the filter
            carried a yaw uncertainty it could never lose (unobservable), and the lever arm of that yaw
            made its position covariance grow with the distance from the origin while the error in its own
            frame did not (position NEES 0.9 on a 10 s simulated circle; 1.25 with the gauge; ATE
            identical).
        sigma_velocity_static_m_s: Reported 1-sigma of the velocity after static init (m/s).
        sigma_velocity_dynamic_m_s: Floor of the reported velocity 1-sigma after dynamic init (m/s; the
            reported covariance is the dynamic solve's, step 7).
        sigma_gyro_bias_rad_s: Floor of the reported gyro-bias 1-sigma (rad/s).
        sigma_accel_bias_m_s2: Accelerometer-bias 1-sigma (m/s^2): the prior of the dynamic solve and the
            reported sigma (static init observes only its component along gravity).
        imu_scale_sigma: 1-sigma of the IMU's scale-factor errors (both sensors), which the initializer
            does not calibrate: they enter the dynamic solve's uncertainty (0.2 %, the ADIS16448 model's).
        imu_misalignment_sigma_rad: 1-sigma of its axis misalignments (rad; 0.05 deg, the same model's).
    """

    window_s: float = 1.5
    dynamic_window_s: float = 3.0
    still_accel_std_m_s2: float = 1.0
    still_gyro_std_rad_s: float = 0.1
    still_max_disparity: float = 0.01
    min_dynamic_window_s: float = 0.5
    min_parallax: float = 0.01
    max_scale_sigma: float = 0.0067
    max_tilt_sigma_rad: float = 0.03
    dynamic_try_every_frames: int = 2
    max_refine_iterations: int = 15
    pixel_sigma_px: float = 0.5
    track_random_walk_px2_per_px: float = 0.0
    min_depth_m: float = 0.1
    min_features: int = 15
    min_feature_obs: int = 4
    min_frames: int = 5
    max_frames: int = 30
    max_features: int = 200
    max_gravity_norm_error: float = 0.2
    max_reprojection_rms: float = 0.01
    sigma_tilt_rad: float = 0.01
    sigma_position_m: float = 1e-4
    sigma_yaw_rad: float = 1e-4
    sigma_velocity_static_m_s: float = 0.01
    sigma_velocity_dynamic_m_s: float = 0.005
    sigma_gyro_bias_rad_s: float = 1e-3
    sigma_accel_bias_m_s2: float = 0.1
    imu_scale_sigma: float = 2e-3
    imu_misalignment_sigma_rad: float = 8.7e-4


def init_params_for(frontend: str) -> InitParams:
    """The initializer settings an estimator uses with front end ``frontend`` (``"klt"`` or ``"sim"``).

    KLT tracks drift, so the dynamic solve whitens them with a random walk of 0.01 px^2 per px of image
    motion. Measured on 8 KLT ``aggressive`` moving starts (README "moving start"): with it, initialized at
    2.2-2.3 s with scale errors -0.3 to 0.85 % (error / sigma RMS 0.9); white (0): 2.0-2.1 s, errors 0.6-1.9 %
    at up to 3.8 sigma; KLT's own 0.025 is too cautious here (2.9 s). Simulated features are white.
    """
    return InitParams(track_random_walk_px2_per_px=0.01 if frontend == "klt" else 0.0)


@dataclass(frozen=True)
class InitResult:
    """The initial navigation state (world frame: z up, yaw = 0 at the first window pose, origin there).

    Attributes:
        t_s: Time (s, IMU clock) of the state: the newest IMU sample used.
        R_WB: Orientation, shape (3, 3).
        p_WB: Position (m), shape (3,).
        v_WB: Velocity in W (m/s), shape (3,).
        gyro_bias_rad_s: shape (3,).
        accel_bias_m_s2: shape (3,) (static: the component along gravity; dynamic: the estimate under its
            zero-mean prior).
        method: ``"static"`` or ``"dynamic"``.
        cov_diag: Variances of ``[dtheta, dp, dv, dbg, dba]``, shape (15,) (StateEstimate order).
        gravity_norm_m_s2: Measured gravity magnitude (static: mean specific force; dynamic: unconstrained
            least-squares |g|), a health check (lesson Chapter 9: "bad initialization").
        scale_sigma: Dynamic: the relative 1-sigma of the metric scale that passed the observability test
            (the larger of the trajectory length's and the end speed's); NaN for static.
        sigma_yaw_rad: 1-sigma of the rotation about world z (rad) that replaces the ``dtheta`` variances
            in that direction (:func:`viotb.vio.state.read_init_record`): the yaw of the first pose is the
            gauge, defined rather than estimated, like its position. NaN: ``cov_diag`` as given.
    """

    t_s: float
    R_WB: np.ndarray
    p_WB: np.ndarray
    v_WB: np.ndarray
    gyro_bias_rad_s: np.ndarray
    accel_bias_m_s2: np.ndarray
    method: str
    cov_diag: np.ndarray
    gravity_norm_m_s2: float = GRAVITY_M_S2
    scale_sigma: float = float("nan")
    sigma_yaw_rad: float = float("nan")


def rotation_from_gravity(up_B: np.ndarray) -> np.ndarray:
    """``R_WB`` with yaw 0 whose world z axis is ``up_B`` (any length) expressed in B, shape (3, 3).

    Args:
        up_B: The world "up" direction in body coordinates (e.g. mean specific force at rest), shape (3,).
    """
    z = np.asarray(up_B, dtype=float)
    norm = float(np.linalg.norm(z))
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"up_B must be a finite non-zero vector, got {up_B}")
    z = z / norm
    # Minimal rotation taking up_B onto e_z, then remove its yaw.
    axis = np.cross(z, [0.0, 0.0, 1.0])
    s, c = float(np.linalg.norm(axis)), float(z[2])
    if s > 1e-12:
        R0 = exp_so3(axis / s * np.arctan2(s, c))
    else:
        R0 = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return rotz(-yaw_from_rotmat(R0)) @ R0


class InertialInitializer:
    """Chooses static or dynamic initialization from a window of IMU samples and feature tracks.

    Args:
        calib: Camera intrinsics/extrinsics (only ``R_BC``, ``p_BC`` are used: features arrive undistorted).
        noise: IMU noise densities (for preintegration and the reported covariance).
        params: Settings.
    """

    def __init__(
        self, calib: CameraCalibration, noise: ImuNoise | None = None, params: InitParams | None = None
    ) -> None:
        """Create an empty initializer."""
        self.calib = calib
        self.noise = noise if noise is not None else ImuNoise()
        self.params = params if params is not None else InitParams()
        self._imu: deque[ImuSample] = deque()
        self._frames: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self.last_failure: str = "no data yet"
        self._buffer_s = max(self.params.window_s, self.params.dynamic_window_s)
        self.last_result: InitResult | None = None  # the last successful initialization
        self._preintegration = RunningPreintegration(self.noise)  # reused by successive dynamic tries
        self._frames_fed = 0
        self._last_try_frame = -(10**9)
        self.dynamic_tries = 0  # dynamic solves run so far, and their CPU time (s)
        self.dynamic_cpu_s = 0.0

    # ------------------------------------------------------------------ input
    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer one IMU sample (timestamps must increase)."""
        if self._imu and sample.t_s <= self._imu[-1].t_s:
            raise ValueError(f"IMU sample t_s={sample.t_s} is not after the previous {self._imu[-1].t_s}")
        self._imu.append(sample)
        keep_from = sample.t_s - 2.0 * self._buffer_s
        while self._imu and self._imu[0].t_s < keep_from:
            self._imu.popleft()

    def feed_features(self, t_s: float, ids: np.ndarray, xy_norm: np.ndarray) -> None:
        """Buffer the features of one frame.

        Args:
            t_s: Frame time (s) on the IMU clock.
            ids: Feature ids, shape (M,).
            xy_norm: Undistorted normalized image coordinates, shape (M, 2).
        """
        ids = np.asarray(ids).astype(np.int64).ravel()
        xy = np.asarray(xy_norm, dtype=float)
        if xy.shape != (ids.size, 2):
            raise ValueError(f"xy_norm must have shape ({ids.size}, 2) to match ids, got {xy.shape}")
        if self._frames and t_s <= self._frames[-1][0]:
            raise ValueError(f"feature frame t_s={t_s} is not after the previous {self._frames[-1][0]}")
        self._frames.append((float(t_s), ids, xy))
        self._frames_fed += 1
        keep_from = t_s - 2.0 * self._buffer_s
        while self._frames and self._frames[0][0] < keep_from:
            self._frames.popleft()

    # ------------------------------------------------------------- detectors
    def _window_imu(self) -> list[ImuSample]:
        if not self._imu:
            return []
        t_end = self._imu[-1].t_s
        return [s for s in self._imu if s.t_s >= t_end - self.params.window_s]

    def _window_frames(self, window_s: float | None = None) -> list[tuple[float, np.ndarray, np.ndarray]]:
        """Frames of the last ``window_s`` (default: the static window) up to the newest IMU sample."""
        if not self._imu:
            return []
        t_end = self._imu[-1].t_s
        t0 = t_end - (self.params.window_s if window_s is None else window_s)
        return [f for f in self._frames if t0 <= f[0] <= t_end]

    def _has_full_window(self) -> bool:
        return bool(self._imu) and self._imu[-1].t_s - self._imu[0].t_s >= self.params.window_s * 0.999

    def _frames_span_s(self) -> float:
        frames = self._window_frames()
        return frames[-1][0] - frames[0][0] if len(frames) >= 2 else 0.0

    def excitation_m_s2(self) -> float:
        """Accelerometer standard deviation (m/s^2, RMS over axes) over the window; 0 without data."""
        return _spread([s.accel_B_m_s2 for s in self._window_imu()])

    def _gyro_std_rad_s(self) -> float:
        return _spread([s.gyro_B_rad_s for s in self._window_imu()])

    def _disparity(self) -> float:
        """Mean normalized displacement of features common to the first and last frame of the window."""
        frames = self._window_frames()
        if len(frames) < 2:
            return 0.0
        (_, ids0, xy0), (_, ids1, xy1) = frames[0], frames[-1]
        common, i0, i1 = np.intersect1d(ids0, ids1, return_indices=True)
        if common.size == 0:
            return float("inf")
        return float(np.mean(np.linalg.norm(xy1[i1] - xy0[i0], axis=1)))

    def is_still(self) -> bool:
        """True if the window is full, IMU std's are below thresholds and features do not move."""
        p = self.params
        return (
            self._has_full_window()
            and self.excitation_m_s2() < p.still_accel_std_m_s2
            and self._gyro_std_rad_s() < p.still_gyro_std_rad_s
            and self._disparity() < p.still_max_disparity
        )

    # ---------------------------------------------------------------- solve
    def try_initialize(self) -> InitResult | None:
        """Initialize from the current window, or return None and set ``last_failure``."""
        p = self.params
        if self.is_still():
            self.last_result = self._static()
            return self.last_result
        if self._frames_span_s() < p.min_dynamic_window_s:
            self.last_failure = (
                f"waiting for {p.window_s:.2f} s of IMU data or {p.min_dynamic_window_s:.2f} s of frames"
            )
            return None
        parallax = self._disparity()
        if not parallax >= p.min_parallax:
            self.last_failure = (
                f"not still and parallax {parallax:.4f} < {p.min_parallax}: scale unobservable, waiting"
            )
            return None
        if self._frames_fed - self._last_try_frame < p.dynamic_try_every_frames:
            return None  # the next dynamic try is due in a frame or two (last_failure: the last try's)
        self._last_try_frame = self._frames_fed
        t_cpu = time.process_time()
        result = self._dynamic()
        self.dynamic_tries += 1
        self.dynamic_cpu_s += time.process_time() - t_cpu
        if result is not None:
            self.last_result = result
        return result

    def _cov_diag_static(self, n_samples: int) -> np.ndarray:
        """Variances ``[dtheta, dp, dv, dbg, dba]`` (15,) after a static initialization."""
        p = self.params
        rate_hz = n_samples / self.params.window_s
        sigma_bg_mean = self.noise.gyro_noise_density_rad_s_sqrthz * np.sqrt(rate_hz) / np.sqrt(n_samples)
        sig = np.concatenate(
            [
                np.full(3, p.sigma_tilt_rad),
                np.full(3, p.sigma_position_m),
                np.full(3, p.sigma_velocity_static_m_s),
                np.full(3, max(p.sigma_gyro_bias_rad_s, sigma_bg_mean)),
                np.full(3, p.sigma_accel_bias_m_s2),
            ]
        )
        return sig**2

    def _static(self) -> InitResult:
        # 1. Mean specific force = up direction in B (open_vins StaticInitializer); mean gyro = bias.
        # 2. At rest the accelerometer bias along "up" is observable as |mean specific force| - g (the
        #    horizontal part is not: it is confounded with roll and pitch until the platform rotates).
        window = self._window_imu()
        acc_mean = np.mean([s.accel_B_m_s2 for s in window], axis=0)
        gyro_mean = np.mean([s.gyro_B_rad_s for s in window], axis=0)
        up_B = acc_mean / np.linalg.norm(acc_mean)
        accel_bias = (float(np.linalg.norm(acc_mean)) - GRAVITY_M_S2) * up_B
        self.last_failure = ""
        return InitResult(
            t_s=window[-1].t_s,
            R_WB=rotation_from_gravity(acc_mean),
            p_WB=np.zeros(3),
            v_WB=np.zeros(3),
            gyro_bias_rad_s=gyro_mean,
            accel_bias_m_s2=accel_bias,
            method="static",
            cov_diag=self._cov_diag_static(len(window)),
            gravity_norm_m_s2=float(np.linalg.norm(acc_mean)),
            sigma_yaw_rad=self.params.sigma_yaw_rad,
        )

    def _dynamic(self) -> InitResult | None:
        sol, failure = dynamic_alignment(
            list(self._imu),
            self._window_frames(self.params.dynamic_window_s),
            self.calib,
            self.noise,
            self.params,
            self._preintegration,
        )
        if sol is None:
            self.last_failure = failure
            return None
        # World frame: z up from g0, yaw 0, origin at B0; the state at the newest IMU sample. The
        # covariance handed over is the dynamic solve's (step 7), floored by the configured sigmas.
        p = self.params
        v0, g, T = sol["v0"], sol["g"], sol["T"]
        R_WB0 = rotation_from_gravity(-g)
        var_v_W = np.diag(R_WB0 @ sol["cov_v_B0"] @ R_WB0.T)
        sigma_tilt = max(sol["tilt_sigma_rad"], 1e-3)
        cov_diag = np.concatenate(
            [
                np.full(3, sigma_tilt**2),
                np.full(3, p.sigma_position_m**2),
                np.maximum(var_v_W, p.sigma_velocity_dynamic_m_s**2),
                np.maximum(np.diag(sol["cov_bg"]), p.sigma_gyro_bias_rad_s**2),
                np.maximum(np.diag(sol["cov_ba"]), 1e-6),
            ]
        )
        self.last_failure = ""
        return InitResult(
            t_s=sol["t_s"],
            R_WB=R_WB0 @ sol["dR_end"],
            p_WB=R_WB0 @ (v0 * T + 0.5 * g * T * T + sol["dp_end"]),
            v_WB=R_WB0 @ (v0 + g * T + sol["dv_end"]),
            gyro_bias_rad_s=sol["bg"],
            accel_bias_m_s2=sol["ba"],
            method="dynamic",
            cov_diag=cov_diag,
            gravity_norm_m_s2=sol["g_norm"],
            scale_sigma=sol["scale_sigma"],
            sigma_yaw_rad=self.params.sigma_yaw_rad,
        )


def _spread(vectors: list[np.ndarray]) -> float:
    """Standard deviation of 3-vectors about their mean, RMS over the axes; 0 for fewer than two."""
    if len(vectors) < 2:
        return 0.0
    v = np.asarray(vectors)
    return float(np.sqrt(np.mean(np.sum((v - v.mean(axis=0)) ** 2, axis=1))))
