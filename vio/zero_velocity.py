"""Stillness detection for zero-velocity updates, shared by the MSCKF (a ZUPT) and the window (a factor).

The idea of open_vins' ``UpdaterZeroVelocity``: between two frames the platform is still when its features
barely move (median disparity below ``max_disparity_px`` over at least ``min_features`` shared features)
*and* the IMU agrees. The IMU test stacks 9 rows over the interval ``T``::

    r = [mean gyro - b_g,  mean accel - R_WB^T g_up - b_a,  -v_WB]

with ``g_up = (0, 0, 9.81)`` in W, Jacobian rows on ``[dbg; dtheta, dba; dv]`` of the error state
``[dtheta, dp, dv, dbg, dba]`` (:mod:`viotb.vio.state` offsets), noise ``(m sigma_white)^2 / T`` for the
IMU rows (white-noise densities inflated ``m = noise_multiplier`` times for vibration) and
``velocity_sigma_m_s^2`` for the velocity rows, and passes while ``r^T (H P H^T + R)^-1 r`` stays within
the chi-square gate. A slow min-jerk takeoff moves features by less than the disparity gate while the IMU
already integrates centimetres per second (measured: 14.7 cm ATE on a recorded hover with the disparity test
alone).

With ``only_at_beginning`` the detection stops for good once the platform has moved (open_vins'
``zupt_only_at_beginning``): a hovering drone reads like a still one to the IMU (specific force ~ +g z, zero
rate) and barely moves its features, so a zero velocity in the air pins a velocity that is not zero
(measured: 10 cm of unseen drift in 3 s of closed-loop hover before this option).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from viotb.vio.frontend import Tracks
from viotb.vio.keyframing import shared_motion_px
from viotb.vio.lie import skew
from viotb.vio.state import BA, BG, THETA, VEL
from viotb.vio.types import GRAVITY_M_S2, ImuNoise


class NavValues(Protocol):
    """What the test reads of a state (``ImuValues`` and ``StateEstimate`` both qualify)."""

    R_WB: np.ndarray  # (3, 3)
    v_WB: np.ndarray  # (3,) m/s in W
    gyro_bias_rad_s: np.ndarray  # (3,)
    accel_bias_m_s2: np.ndarray  # (3,)


@dataclass(frozen=True)
class ZeroVelocityParams:
    """Stillness-detection settings (defaults: the MSCKF's; the window's differences are noted).

    Attributes:
        enabled: Detect stillness at all.
        max_disparity_px: Largest median feature motion (px) between frames for the platform to be still
            (a larger one means it moves; 0 leaves only exactly still features).
        min_features: Fewest features shared by the two frames to measure the disparity.
        max_speed_m_s: Largest estimated speed (m/s) for the platform to be still (a larger one means it
            moves). The MSCKF uses 0.2; the window does not gate on its speed (``inf``).
        noise_multiplier: Inflation of the IMU white-noise densities in the IMU test (vibration).
        velocity_sigma_m_s: Noise (m/s) of the zero-velocity rows (and of the window's factor).
        chi2_gate: Chi-square threshold of the 9-row IMU test; None (the MSCKF) for the estimator's 95 %
            quantile of chi-square(9) times its ``chi2_multiplier``; the window uses 16.92.
        imu_failures_to_move: Consecutive failed IMU tests that mean the platform moves (one failure alone
            is a vibration burst: measured chi2 19 once in 4.7 s at rest on EuRoC V1_01). The window uses 2;
            0 (the MSCKF) means a failed IMU test never marks the platform as moving.
        only_at_beginning: Detect stillness only until the platform first moves (module docstring).
    """

    enabled: bool = True
    max_disparity_px: float = 0.5
    min_features: int = 10
    max_speed_m_s: float = 0.2
    noise_multiplier: float = 10.0
    velocity_sigma_m_s: float = 0.01
    chi2_gate: float | None = None
    imu_failures_to_move: int = 0
    only_at_beginning: bool = True


@dataclass(frozen=True)
class StillnessTest:
    """The 9-row IMU stillness test of one interval (module docstring).

    Attributes:
        r: Residual ``[gyro (rad/s), accel (m/s^2), velocity (m/s)]``, shape (9,).
        H: Jacobian w.r.t. the error state, shape (9, D).
        R: Measurement noise, shape (9, 9).
        chi2: ``r^T (H P H^T + R)^-1 r``.
    """

    r: np.ndarray
    H: np.ndarray
    R: np.ndarray
    chi2: float


def stillness_test(
    gyro_B_rad_s: np.ndarray,
    accel_B_m_s2: np.ndarray,
    x: NavValues,
    cov: np.ndarray,
    noise: ImuNoise,
    dt_s: float,
    params: ZeroVelocityParams,
) -> StillnessTest:
    """The IMU half of the stillness test over one interval.

    Args:
        gyro_B_rad_s: Gyro readings of the interval (rad/s, B), shape (n, 3).
        accel_B_m_s2: Accelerometer readings of the interval (m/s^2, B), shape (n, 3).
        x: The state at the end of the interval.
        cov: Error-state covariance, shape (D, D), D >= 15, IMU block first in ``[dtheta, dp, dv, dbg,
            dba]`` order.
        noise: IMU noise densities.
        dt_s: Interval length ``T`` (s), > 0.
        params: Settings.
    """
    g_up_B = x.R_WB.T @ np.array([0.0, 0.0, GRAVITY_M_S2])
    r = np.concatenate(
        [
            gyro_B_rad_s.mean(axis=0) - x.gyro_bias_rad_s,
            accel_B_m_s2.mean(axis=0) - g_up_B - x.accel_bias_m_s2,
            -x.v_WB,
        ]
    )
    H = np.zeros((9, cov.shape[0]))
    H[0:3, BG : BG + 3] = np.eye(3)
    H[3:6, THETA : THETA + 3] = skew(g_up_B)
    H[3:6, BA : BA + 3] = np.eye(3)
    H[6:9, VEL : VEL + 3] = np.eye(3)
    m2 = params.noise_multiplier**2
    R = np.diag(
        [m2 * noise.gyro_noise_density_rad_s_sqrthz**2 / dt_s] * 3
        + [m2 * noise.accel_noise_density_m_s2_sqrthz**2 / dt_s] * 3
        + [params.velocity_sigma_m_s**2] * 3
    )
    S = H @ cov @ H.T + R
    chi2 = float(r @ np.linalg.solve(S, r))
    return StillnessTest(r, H, R, chi2)


class ZeroVelocityDetector:
    """Decides frame by frame whether the platform is still, and remembers whether it has moved.

    Args:
        params: Settings.
        noise: IMU noise densities.
        chi2_gate: The 9-row test's threshold when ``params.chi2_gate`` is None.
    """

    def __init__(self, params: ZeroVelocityParams, noise: ImuNoise, chi2_gate: float) -> None:
        """Start as not moved."""
        self.params = params
        self.noise = noise
        self.chi2_gate = params.chi2_gate if params.chi2_gate is not None else chi2_gate
        self.has_moved = False
        self._imu_failures = 0

    def allowed(self) -> bool:
        """Whether stillness may be detected now (enabled, and not after the first motion if so set)."""
        p = self.params
        return p.enabled and not (p.only_at_beginning and self.has_moved)

    def detect(
        self,
        prev: Tracks,
        now: Tracks,
        dt_s: float,
        x: NavValues,
        cov: np.ndarray,
        readings: Callable[[], tuple[np.ndarray, np.ndarray]],
    ) -> StillnessTest | None:
        """Test the interval between two frames; the passed test when still, else None.

        Call only while :meth:`allowed`. Features moving or the speed beyond its gate mark the platform as
        moving; so do ``imu_failures_to_move`` failed IMU tests in a row.

        Args:
            prev: Tracks of the earlier frame.
            now: Tracks of the later frame.
            dt_s: Interval (s) on the IMU clock.
            x: State at the later frame (see :func:`stillness_test`).
            cov: Its error-state covariance, shape (D, D).
            readings: Returns the interval's ``(gyro_B_rad_s (n, 3), accel_B_m_s2 (n, 3))``.
        """
        p = self.params
        motion_px = shared_motion_px(prev, now)
        if len(motion_px) < p.min_features or dt_s <= 1e-6:
            return None
        disparity_px = float(np.median(motion_px))
        speed_m_s = float(np.linalg.norm(x.v_WB))
        if disparity_px > p.max_disparity_px or speed_m_s > p.max_speed_m_s:
            self.has_moved = True
            return None
        gyro, accel = readings()
        test = stillness_test(gyro, accel, x, cov, self.noise, dt_s, p)
        imu_ok = test.chi2 <= self.chi2_gate
        self._imu_failures = 0 if imu_ok else self._imu_failures + 1
        if p.imu_failures_to_move and self._imu_failures >= p.imu_failures_to_move:
            self.has_moved = True
        return test if imu_ok else None
