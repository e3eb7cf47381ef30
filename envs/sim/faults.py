"""Sensor and calibration faults a scenario injects: what the estimator is fed or told, never the truth.

One :class:`SensorFaults` value travels with an open-loop recording
(:class:`viotb.envs.scenarios.registry.Scenario`, written into the dataset's readings and calibration files),
a closed-loop rig (:class:`viotb.envs.run.closed_loop.RigConfig`) and an in-memory failure stream
(:class:`viotb.envs.scenarios.failures.StreamConfig`), so a failure mode means the same thing in all three.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from viotb.vio.camera import CameraCalibration, with_extrinsic_rotation_error


@dataclass(frozen=True)
class SensorFaults:
    """Calibration and IMU errors.

    Attributes:
        assumed_time_offset_s: Camera-IMU time offset (s, ``t_imu = t_cam + offset``) in the calibration the
            estimator reads; None = the true one.
        extrinsic_error_rad: Rotation error (rad) of ``R_BC`` in that calibration
            (:func:`~viotb.vio.camera.with_extrinsic_rotation_error`).
        extra_gyro_bias_rad_s: Constant bias (rad/s) added to every gyro axis on top of the IMU model's.
        accel_scale_error: Accelerometer scale-factor error (fraction) on every axis.
    """

    assumed_time_offset_s: float | None = None
    extrinsic_error_rad: float = 0.0
    extra_gyro_bias_rad_s: float = 0.0
    accel_scale_error: float = 0.0

    def __post_init__(self) -> None:
        """Reject non-finite values, naming the field."""
        for name in ("extrinsic_error_rad", "extra_gyro_bias_rad_s", "accel_scale_error"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"SensorFaults.{name} must be finite, got {getattr(self, name)}")
        if self.assumed_time_offset_s is not None and not math.isfinite(self.assumed_time_offset_s):
            raise ValueError(
                f"SensorFaults.assumed_time_offset_s must be finite, got {self.assumed_time_offset_s}"
            )

    def told_calibration(self, calib_true: CameraCalibration) -> CameraCalibration:
        """The calibration the estimator is given, from the true one."""
        told = with_extrinsic_rotation_error(calib_true, self.extrinsic_error_rad)
        if self.assumed_time_offset_s is not None:
            told = replace(told, time_offset_s=float(self.assumed_time_offset_s))
        return told

    def imu_input(self, omega_B_rad_s: np.ndarray, f_B_m_s2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True angular rate and specific force as the faulty IMU senses them (before its noise and biases).

        Args:
            omega_B_rad_s: True angular rate (rad/s), shape (..., 3).
            f_B_m_s2: True specific force (m/s^2), shape (..., 3).
        """
        omega = np.asarray(omega_B_rad_s, dtype=float) + self.extra_gyro_bias_rad_s
        return omega, np.asarray(f_B_m_s2, dtype=float) * (1.0 + self.accel_scale_error)
