"""Inertial (static) and visual-inertial (dynamic) initialization, after open_vins' ``InertialInitializer``.

The estimator needs gravity direction (roll/pitch), velocity, gyro bias and, for a monocular camera, metric
scale before it can start (lesson, Chapter 6). Two paths, chosen from the IMU window:

* Static (open_vins ``StaticInitializer``): accelerometer and gyro standard deviations below thresholds and
  no image parallax. The mean specific force is "up" in B, giving roll/pitch (yaw = 0 is the gauge); the mean
  gyro is the gyro bias; velocity and position are zero.
* Dynamic (open_vins ``DynamicInitializer``; Dong-Si & Mourikis, "Estimator initialization in
  vision-aided inertial navigation with unknown camera-IMU calibration", IROS 2012; Kaiser, Martinelli et al.,
  "Simultaneous state initialization and gyroscope bias calibration in visual inertial aided navigation",
  RA-L 2017). With gyro-preintegrated rotations, the position of body frame k in the first body frame B0 is
  ``p_k = v0 t_k + 1/2 g0 t_k^2 + dp_0k`` (Forster 2017 eq. 33 written in B0), so each bearing
  ``(x, y)`` of feature f in camera k gives two equations linear in ``(v0, g0, p_f)``::

      [[1, 0, -x], [0, 1, -y]] R_CkB0 (p_f - v0 t_k - 1/2 g0 t_k^2) = [[1, 0, -x], [0, 1, -y]] R_CkB0 c_k

  with ``c_k = dp_0k + dR_0k p_BC``. Least squares gives a first solution, ``|g0|`` is set to 9.81, and a
  Gauss-Newton (``scipy.optimize.least_squares``) refinement of the normalized reprojection errors over
  ``(v0, gravity direction, gyro bias, p_f)`` follows, the gyro bias entering through the preintegration bias
  Jacobians (Forster eq. 44).
"""

from __future__ import annotations

import copy
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from viotb.vio.camera import CameraCalibration
from viotb.vio.lie import exp_so3, rotz, yaw_from_rotmat
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.types import GRAVITY_M_S2, ImuNoise, ImuSample


@dataclass(frozen=True)
class InitParams:
    """Initializer settings (defaults suit the EuRoC ADIS16448 and 20 Hz cameras).

    Attributes:
        window_s: Length (s) of the IMU/feature window used for both initializers.
        still_accel_std_m_s2: Static if the accelerometer std (m/s^2, RMS over axes) is below this.
        still_gyro_std_rad_s: Static if the gyro std (rad/s, RMS over axes) is below this.
        still_max_disparity: Static only if the mean feature displacement across the window (normalized
            image coordinates) is below this (open_vins ``init_max_disparity``, ~4.6 px at f = 460 px).
        excitation_min_m_s2: Dynamic initialization needs an accelerometer std (m/s^2) at least this large.
        min_features: Minimum number of features tracked in at least ``min_feature_obs`` frames.
        min_feature_obs: Observations a feature needs to enter the dynamic solve.
        min_frames: Minimum number of camera frames in the window for the dynamic solve.
        max_frames: Frames used by the dynamic solve (evenly subsampled from the window).
        max_features: Features used by the dynamic solve (the longest tracks).
        max_gravity_norm_error: Reject the dynamic solution if the unconstrained |g| differs from 9.81 by
            more than this fraction.
        max_reprojection_rms: Reject the dynamic solution if the refined RMS reprojection error (normalized
            coordinates) is above this.
        sigma_tilt_rad: Reported 1-sigma of the orientation error at initialization (rad).
        sigma_position_m: Reported 1-sigma of the position (gauge) (m).
        sigma_velocity_static_m_s: Reported 1-sigma of the velocity after static init (m/s).
        sigma_velocity_dynamic_m_s: Reported 1-sigma of the velocity after dynamic init (m/s).
        sigma_gyro_bias_rad_s: Floor of the reported gyro-bias 1-sigma (rad/s).
        sigma_accel_bias_m_s2: Reported accelerometer-bias 1-sigma (m/s^2) (not estimated here).
    """

    window_s: float = 1.5
    still_accel_std_m_s2: float = 1.0
    still_gyro_std_rad_s: float = 0.1
    still_max_disparity: float = 0.01
    excitation_min_m_s2: float = 1.0
    min_features: int = 15
    min_feature_obs: int = 4
    min_frames: int = 5
    max_frames: int = 12
    max_features: int = 80
    max_gravity_norm_error: float = 0.2
    max_reprojection_rms: float = 0.01
    sigma_tilt_rad: float = 0.01
    sigma_position_m: float = 1e-3
    sigma_velocity_static_m_s: float = 0.01
    sigma_velocity_dynamic_m_s: float = 0.05
    sigma_gyro_bias_rad_s: float = 1e-3
    sigma_accel_bias_m_s2: float = 0.1


@dataclass(frozen=True)
class InitResult:
    """The initial navigation state (world frame: z up, yaw = 0 at the first window pose, origin there).

    Attributes:
        t_s: Time (s, IMU clock) of the state: the newest IMU sample used.
        R_WB: Orientation, shape (3, 3).
        p_WB: Position (m), shape (3,).
        v_WB: Velocity in W (m/s), shape (3,).
        gyro_bias_rad_s: shape (3,).
        accel_bias_m_s2: shape (3,) (zeros: not separable from tilt over a short window).
        method: ``"static"`` or ``"dynamic"``.
        cov_diag: Variances of ``[dtheta, dp, dv, dbg, dba]``, shape (15,) (StateEstimate order).
        gravity_norm_m_s2: Measured gravity magnitude (static: mean specific force; dynamic: unconstrained
            least-squares |g|), a health check (lesson Chapter 9: "bad initialization").
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

    # ------------------------------------------------------------------ input
    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer one IMU sample (timestamps must increase)."""
        if self._imu and sample.t_s <= self._imu[-1].t_s:
            raise ValueError(f"IMU sample t_s={sample.t_s} is not after the previous {self._imu[-1].t_s}")
        self._imu.append(sample)
        keep_from = sample.t_s - 2.0 * self.params.window_s
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
        keep_from = t_s - 2.0 * self.params.window_s
        while self._frames and self._frames[0][0] < keep_from:
            self._frames.popleft()

    # ------------------------------------------------------------- detectors
    def _window_imu(self) -> list[ImuSample]:
        if not self._imu:
            return []
        t_end = self._imu[-1].t_s
        return [s for s in self._imu if s.t_s >= t_end - self.params.window_s]

    def _window_frames(self) -> list[tuple[float, np.ndarray, np.ndarray]]:
        if not self._imu:
            return []
        t_end = self._imu[-1].t_s
        t0 = t_end - self.params.window_s
        return [f for f in self._frames if t0 <= f[0] <= t_end]

    def _has_full_window(self) -> bool:
        return bool(self._imu) and self._imu[-1].t_s - self._imu[0].t_s >= self.params.window_s * 0.999

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
        if not self._has_full_window():
            self.last_failure = f"waiting for {self.params.window_s:.2f} s of IMU data"
            return None
        if self.is_still():
            return self._static()
        excitation = self.excitation_m_s2()
        if excitation < self.params.excitation_min_m_s2:
            self.last_failure = (
                f"not still (parallax {self._disparity():.4f}) and excitation {excitation:.3f} m/s^2 "
                f"< {self.params.excitation_min_m_s2} m/s^2"
            )
            return None
        return self._dynamic()

    def _cov_diag(self, method: str, n_samples: int) -> np.ndarray:
        p = self.params
        rate_hz = n_samples / self.params.window_s
        sigma_bg_mean = self.noise.gyro_noise_density_rad_s_sqrthz * np.sqrt(rate_hz) / np.sqrt(n_samples)
        sigma_v = p.sigma_velocity_static_m_s if method == "static" else p.sigma_velocity_dynamic_m_s
        sig = np.concatenate(
            [
                np.full(3, p.sigma_tilt_rad),
                np.full(3, p.sigma_position_m),
                np.full(3, sigma_v),
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
            cov_diag=self._cov_diag("static", len(window)),
            gravity_norm_m_s2=float(np.linalg.norm(acc_mean)),
        )

    def _preintegrate_to(
        self, times: list[float], t_end: float
    ) -> tuple[list[ImuPreintegration], ImuPreintegration]:
        """Preintegrate (zero bias) from ``times[0]`` to each time and to ``t_end``, zero-order hold."""
        samples = list(self._imu)
        targets = sorted(set([*times, t_end]))
        pim = ImuPreintegration(np.zeros(3), np.zeros(3), self.noise)
        snapshots: dict[float, ImuPreintegration] = {targets[0]: copy.deepcopy(pim)}
        t = targets[0]
        ti = 1
        for k, s in enumerate(samples):
            t_next = samples[k + 1].t_s if k + 1 < len(samples) else t_end
            if t_next <= t:
                continue
            start = max(s.t_s, t)
            while ti < len(targets) and targets[ti] <= t_next:
                if targets[ti] > start:
                    pim.integrate(s.accel_B_m_s2, s.gyro_B_rad_s, targets[ti] - start)
                    start = targets[ti]
                snapshots[targets[ti]] = copy.deepcopy(pim)
                ti += 1
            if t_next > start and ti < len(targets):
                pim.integrate(s.accel_B_m_s2, s.gyro_B_rad_s, t_next - start)
            t = t_next
            if ti >= len(targets):
                break
        if ti < len(targets):
            raise ValueError(f"IMU data does not cover t={targets[ti]:.3f} s")
        return [snapshots[tk] for tk in times], snapshots[t_end]

    def _select_tracks(self):
        """Frames (subsampled) and feature tracks for the dynamic solve: (times, {id: [(frame, xy)]})."""
        p = self.params
        frames = self._window_frames()
        if len(frames) > p.max_frames:
            idx = np.round(np.linspace(0, len(frames) - 1, p.max_frames)).astype(int)
            frames = [frames[i] for i in idx]
        tracks: dict[int, list[tuple[int, np.ndarray]]] = {}
        for k, (_, ids, xy) in enumerate(frames):
            for fid, obs in zip(ids, xy, strict=True):
                tracks.setdefault(int(fid), []).append((k, obs))
        tracks = {fid: obs for fid, obs in tracks.items() if len(obs) >= p.min_feature_obs}
        longest = sorted(tracks, key=lambda f: -len(tracks[f]))[: p.max_features]
        return [f[0] for f in frames], {fid: tracks[fid] for fid in sorted(longest)}

    def _dynamic(self) -> InitResult | None:
        p = self.params
        # 1. Frames and tracks.
        times, tracks = self._select_tracks()
        if len(times) < p.min_frames or len(tracks) < p.min_features:
            self.last_failure = (
                f"dynamic init needs {p.min_frames} frames and {p.min_features} features seen "
                f"{p.min_feature_obs} times; have {len(times)} frames, {len(tracks)} features"
            )
            return None
        t_end = self._imu[-1].t_s
        pims, pim_end = self._preintegrate_to(times, t_end)
        R_BC, p_BC = np.asarray(self.calib.R_BC, float), np.asarray(self.calib.p_BC, float)
        fids = list(tracks)
        n_f = len(fids)
        obs_frame = np.array([k for fid in fids for k, _ in tracks[fid]])
        obs_feat = np.array([j for j, fid in enumerate(fids) for _ in tracks[fid]])
        obs_xy = np.array([xy for fid in fids for _, xy in tracks[fid]])
        dts = np.array([times[k] - times[0] for k in range(len(times))])

        # 2. Linear system in x = [v0 (3), g0 (3), p_f (3 n_f)] (Dong-Si & Mourikis 2012 / Kaiser 2017).
        n_obs = obs_xy.shape[0]
        A = np.zeros((2 * n_obs, 6 + 3 * n_f))
        b = np.zeros(2 * n_obs)
        for o in range(n_obs):
            k, j, (x, y) = obs_frame[o], obs_feat[o], obs_xy[o]
            dR = pims[k].delta_R
            M = np.array([[1.0, 0.0, -x], [0.0, 1.0, -y]]) @ (dR @ R_BC).T
            t = dts[k]
            A[2 * o : 2 * o + 2, 0:3] = -M * t
            A[2 * o : 2 * o + 2, 3:6] = -0.5 * M * t * t
            A[2 * o : 2 * o + 2, 6 + 3 * j : 9 + 3 * j] = M
            b[2 * o : 2 * o + 2] = M @ (pims[k].delta_p + dR @ p_BC)
        x_lin, *_ = np.linalg.lstsq(A, b, rcond=None)
        g_norm = float(np.linalg.norm(x_lin[3:6]))
        if not np.isfinite(g_norm) or abs(g_norm / GRAVITY_M_S2 - 1.0) > p.max_gravity_norm_error:
            self.last_failure = f"linear alignment gave |g| = {g_norm:.3f} m/s^2 (weak excitation?)"
            return None
        # 3. Enforce |g| = 9.81 and re-solve v0, p_f with gravity fixed.
        g_dir0 = x_lin[3:6] / g_norm
        g0 = GRAVITY_M_S2 * g_dir0
        keep = np.r_[0:3, 6 : 6 + 3 * n_f]
        x_fix, *_ = np.linalg.lstsq(A[:, keep], b - A[:, 3:6] @ g0, rcond=None)

        # 4. Gauss-Newton over [v0, dg (2, tangent of the gravity direction), bg, p_f] on reprojection errors.
        R_g = rotation_from_gravity(g_dir0).T  # maps e_z onto g_dir0
        dR0 = np.stack([pm.delta_R for pm in pims])
        dp0 = np.stack([pm.delta_p for pm in pims])
        JR = np.stack([pm.d_R_d_bg for pm in pims])
        Jp = np.stack([pm.d_p_d_bg for pm in pims])

        def unpack(z):
            v0, dg, bg, pf = z[0:3], z[3:5], z[5:8], z[8:].reshape(n_f, 3)
            g_dir = R_g @ np.array([dg[0], dg[1], 1.0])
            return v0, GRAVITY_M_S2 * g_dir / np.linalg.norm(g_dir), bg, pf

        def residuals(z):
            v0, g, bg, pf = unpack(z)
            R_k = np.stack([dR0[k] @ exp_so3(JR[k] @ bg) for k in range(len(times))])
            p_k = v0 * dts[:, None] + 0.5 * g * dts[:, None] ** 2 + dp0 + Jp @ bg
            p_C = np.einsum(
                "nji,nj->ni", R_k[obs_frame] @ R_BC, pf[obs_feat] - p_k[obs_frame] - R_k[obs_frame] @ p_BC
            )
            depth = np.where(np.abs(p_C[:, 2]) < 1e-6, 1e-6, p_C[:, 2])
            return (p_C[:, :2] / depth[:, None] - obs_xy).ravel()

        sparsity = lil_matrix((2 * n_obs, 8 + 3 * n_f), dtype=int)
        sparsity[:, 0:8] = 1
        for o in range(n_obs):
            j = obs_feat[o]
            sparsity[2 * o : 2 * o + 2, 8 + 3 * j : 11 + 3 * j] = 1
        z0 = np.concatenate([x_fix[0:3], np.zeros(2), np.zeros(3), x_fix[3:]])
        sol = least_squares(residuals, z0, jac_sparsity=sparsity, method="trf", x_scale="jac", max_nfev=50)
        v0, g, bg, _ = unpack(sol.x)
        rms = float(np.sqrt(np.mean(sol.fun**2)))
        if not np.isfinite(rms) or rms > p.max_reprojection_rms:
            self.last_failure = f"refinement reprojection RMS {rms:.4f} > {p.max_reprojection_rms}"
            return None

        # 5. World frame: z up from g0, yaw 0, origin at B0; propagate to the newest IMU sample.
        R_WB0 = rotation_from_gravity(-g)
        dR_end, dv_end, dp_end = pim_end.corrected(bg, np.zeros(3))
        T = pim_end.dt_s
        n_window = len(self._window_imu())
        self.last_failure = ""
        return InitResult(
            t_s=t_end,
            R_WB=R_WB0 @ dR_end,
            p_WB=R_WB0 @ (v0 * T + 0.5 * g * T * T + dp_end),
            v_WB=R_WB0 @ (v0 + g * T + dv_end),
            gyro_bias_rad_s=bg,
            accel_bias_m_s2=np.zeros(3),
            method="dynamic",
            cov_diag=self._cov_diag("dynamic", n_window),
            gravity_norm_m_s2=g_norm,
        )


def _spread(vectors: list[np.ndarray]) -> float:
    """Standard deviation of 3-vectors about their mean, RMS over the axes; 0 for fewer than two."""
    if len(vectors) < 2:
        return 0.0
    v = np.asarray(vectors)
    return float(np.sqrt(np.mean(np.sum((v - v.mean(axis=0)) ** 2, axis=1))))
