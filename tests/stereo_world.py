"""A synthetic stereo head (shared by the stereo tests): look around in place inside a ring of landmarks.

Everything is analytic. The head yaws +-57 deg (0.9 rad/s peak) and pitches +-9 deg while its position
sways by 1 cm, so a single camera sees almost no parallax; the two cameras sit 10 cm apart along body y,
both looking along body +x (cam1 right of cam0, toed out by 2 deg), a 320x240 70-deg-fovy pinhole each.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.camera import CameraCalibration, PinholeCamera
from viotb.vio.initialization import InitResult
from viotb.vio.lie import exp_so3
from viotb.vio.types import CameraFrame, FeatureObservations, ImuNoise, ImuSample, gravity_W

# Camera looks along body +x: camera x = -body y, camera y = -body z, camera z = body x.
R_BC_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
BASELINE_M = 0.10


def _axis(i: int, a: float) -> np.ndarray:
    v = np.zeros(3)
    v[i] = a
    return exp_so3(v)


class LookAroundWorld:
    """Head looking around in place; landmarks on a ring 2-4 m away, 0-3 m high."""

    def __init__(self, rng: np.random.Generator, n_landmarks: int = 900) -> None:
        """Landmarks and the two calibrations."""
        ang = rng.uniform(0, 2 * np.pi, n_landmarks)
        rad = rng.uniform(2.0, 4.0, n_landmarks)
        z = rng.uniform(0.0, 3.0, n_landmarks)
        self.landmarks = np.stack([rad * np.cos(ang), rad * np.sin(ang), z], 1)
        self.camera = PinholeCamera.from_fovy(320, 240, 70.0)
        half = 0.5 * BASELINE_M
        self.calib0 = CameraCalibration(self.camera, R_BC_FORWARD, np.array([0.06, half, 0.03]), 0.0, 20.0)
        self.calib1 = CameraCalibration(
            self.camera, R_BC_FORWARD @ _axis(1, np.deg2rad(2.0)), np.array([0.06, -half, 0.03]), 0.0, 20.0
        )

    @staticmethod
    def pose(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Truth at t: R_WB, p_WB (m), v_WB (m/s), omega_B (rad/s), specific force f_B (m/s^2).

        ``R = Rz(psi) Ry(theta)``, ``omega_B = Ry^T e_z psi' + e_y theta'``, ``f_B = R^T (p'' - g)``.
        """
        psi, dpsi = 1.0 * np.sin(0.9 * t), 0.9 * np.cos(0.9 * t)
        th, dth = 0.15 * np.sin(1.3 * t), 0.195 * np.cos(1.3 * t)
        Ry = _axis(1, th)
        R = _axis(2, psi) @ Ry
        omega = Ry.T @ np.array([0.0, 0.0, dpsi]) + np.array([0.0, dth, 0.0])
        w = np.array([0.7, 0.5, 1.1])
        amp = np.array([0.01, 0.01, 0.005])
        p = np.array([0.0, 0.0, 1.6]) + amp * np.sin(w * t)
        v = amp * w * np.cos(w * t)
        a = -amp * w * w * np.sin(w * t)
        return R, p, v, omega, R.T @ (a - gravity_W())

    def _observe(self, calib: CameraCalibration, t: float, rng: np.random.Generator, sigma_px: float):
        R, p, *_ = self.pose(t)
        R_WC = R @ calib.R_BC
        p_C = (self.landmarks - (p + R @ calib.p_BC)) @ R_WC
        front = np.nonzero(p_C[:, 2] > 0.3)[0]
        uv = calib.camera.project(p_C[front]) + rng.normal(0.0, sigma_px, (len(front), 2))
        ok = calib.camera.in_image(uv)
        return FeatureObservations(front[ok].astype(np.int64), uv[ok])

    def frame(self, t: float, rng: np.random.Generator, sigma_px: float, stereo: bool) -> CameraFrame:
        """The simulated-feature frame at t (cam1's features only when ``stereo``)."""
        left = self._observe(self.calib0, t, rng, sigma_px)
        right = self._observe(self.calib1, t, rng, sigma_px) if stereo else None
        return CameraFrame(t_s=t, features=left, features_right=right)


def run_look_around(
    estimator, world: LookAroundWorld, seed: int, seconds: float, stereo: bool, sigma_px=0.5, frame_of=None
):
    """Feed a noisy IMU (200 Hz, biases with random walk) and 20 Hz frames; returns (t, p_err (m)) rows.

    The estimator starts from the truth perturbed by its stated covariance. ``frame_of(t)`` (default: the
    world's simulated features) makes the camera frame at t.
    """
    rng = np.random.default_rng(seed)
    noise = ImuNoise()
    imu_dt, cam_every = 1.0 / 200.0, 10
    bg = rng.normal(0.0, 0.002, 3)
    ba = rng.normal(0.0, 0.02, 3)
    R0, p0, v0, _, _ = world.pose(0.0)
    cov_diag = np.array([1e-4] * 3 + [1e-6] * 3 + [1e-4] * 3 + [0.002**2] * 3 + [0.02**2] * 3)
    d = rng.normal(0.0, np.sqrt(cov_diag))
    estimator.initialize(
        InitResult(
            0.0,
            R0 @ exp_so3(d[0:3]),
            p0 + d[3:6],
            v0 + d[6:9],
            bg + d[9:12],
            ba + d[12:15],
            "truth",
            cov_diag,
        )
    )
    rows = []
    for k in range(1, int(seconds / imu_dt) + 1):
        t = k * imu_dt
        R, p, _, omega, f = world.pose(t)
        bg = bg + rng.normal(0.0, noise.gyro_random_walk_rad_s2_sqrthz * np.sqrt(imu_dt), 3)
        ba = ba + rng.normal(0.0, noise.accel_random_walk_m_s3_sqrthz * np.sqrt(imu_dt), 3)
        gyro = omega + bg + rng.normal(0.0, noise.gyro_noise_density_rad_s_sqrthz / np.sqrt(imu_dt), 3)
        acc = f + ba + rng.normal(0.0, noise.accel_noise_density_m_s2_sqrthz / np.sqrt(imu_dt), 3)
        estimator.feed_imu(ImuSample(t, gyro, acc))
        if k % cam_every == 0:
            frame = world.frame(t, rng, sigma_px, stereo) if frame_of is None else frame_of(t)
            estimator.feed_camera(frame)
            e = estimator.estimate()
            rows.append((t, e.p_WB - p))
    return rows
