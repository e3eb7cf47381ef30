"""The window estimator's online calibration: current values, prior, covariance and image velocities.

:class:`OnlineCalibration` is what :class:`viotb.vio.window.WindowEstimator` holds when
``WindowParams.estimate_extrinsics``, ``estimate_time_offset`` or ``imu_intrinsics`` is on (the variables
and their Jacobians: :mod:`viotb.vio.window_calib`; their part of the system:
:mod:`viotb.vio.window_calib_system`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.imu_intrinsics import INTRINSICS_CHOICES
from viotb.vio.marginalization import LinearPrior
from viotb.vio.types import CalibrationDrift
from viotb.vio.window_calib import CalibLayout, CalibValues, calibration_drift
from viotb.vio.window_calib_system import CalibFactors
from viotb.vio.window_map import Keyframe
from viotb.vio.window_params import WindowParams
from viotb.vio.window_solver import Factors


class OnlineCalibration:
    """Online camera-IMU calibration of the window (extrinsics per camera, one time offset).

    Attributes:
        layout: The estimated entries (C).
        values: Current calibration.
        x0: The linear prior's linearization point of the calibration.
        cov: Covariance of the estimated entries after the latest solve, shape (C, C).
        given: Cam0's file calibration (the reference of :meth:`drift`).
    """

    def __init__(
        self, params: WindowParams, calib: CameraCalibration, calib_right: CameraCalibration | None
    ) -> None:
        """Start at the files' calibration with the prior sigmas of ``params``."""
        n_cams = 1 if calib_right is None else 2
        gyro, accel = params.imu_intrinsics in ("gyro", "gyro+accel"), params.imu_intrinsics == "gyro+accel"
        self.layout = CalibLayout(
            n_cams, params.estimate_extrinsics, params.estimate_time_offset, gyro, accel
        )
        sig = [params.extrinsic_sigma_rad] * 3 + [params.extrinsic_sigma_m] * 3
        sig = sig * n_cams + [params.time_offset_sigma_s] + [params.imu_intrinsic_sigma] * 18
        self._prior_sigma = np.array(sig)[self.layout.active]
        self.values = CalibValues.from_files(calib, calib_right)
        self.x0 = self.values
        self.cov = np.diag(self._prior_sigma**2)
        self.given = calib

    @classmethod
    def create(
        cls, params: WindowParams, calib: CameraCalibration, calib_right: CameraCalibration | None
    ) -> OnlineCalibration | None:
        """An online calibration when ``params`` asks for one, else None.

        Raises:
            ValueError: An unknown ``params.imu_intrinsics``; the extrinsics or time offset with
                ``params.track_noise`` (the correlated-noise factors take no more variables; the IMU
                intrinsics alone do not touch them); or a ``calibration_start_keyframes`` the window never
                holds (over ``window_size``).
        """
        if params.imu_intrinsics not in INTRINSICS_CHOICES:
            raise ValueError(
                f"WindowParams.imu_intrinsics must be one of {INTRINSICS_CHOICES}, "
                f"got {params.imu_intrinsics!r}"
            )
        camera_terms = params.estimate_extrinsics or params.estimate_time_offset
        if not (camera_terms or params.imu_intrinsics != "none"):
            return None
        if params.track_noise and camera_terms:
            raise ValueError("WindowParams: online calibration needs track_noise=False (white track noise)")
        if not params.imu_intrinsic_sigma > 0.0:
            raise ValueError(
                f"WindowParams.imu_intrinsic_sigma must be > 0, got {params.imu_intrinsic_sigma}"
            )
        if not 1 <= params.calibration_start_keyframes <= params.window_size:
            raise ValueError(
                f"WindowParams.calibration_start_keyframes must be in 1..window_size ({params.window_size}), "
                f"got {params.calibration_start_keyframes}"
            )
        return cls(params, calib, calib_right)

    def start_prior(self, prior: LinearPrior) -> LinearPrior:
        """``prior`` with the calibration's (its sigmas, independent) after it, at the current values."""
        self.x0 = self.values
        m, C = len(prior.g), self.layout.dim
        H = np.zeros((m + C, m + C))
        H[:m, :m], H[m:, m:] = prior.H, np.diag(1.0 / self._prior_sigma**2)
        return LinearPrior(H, np.concatenate([prior.g, np.zeros(C)]), prior.keys, prior.x0)

    def factors(self, keyframes: list[Keyframe], f: Factors) -> Factors:
        """``f`` (over ``keyframes``) with the calibration's factors (prior point, keyframes' gyro)."""
        gyro = np.stack([kf.gyro_B_rad_s for kf in keyframes])
        return replace(f, calib=CalibFactors(self.layout, self.x0, gyro))

    def imu_matrices(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The current ``(T_g, T_a)`` when the intrinsics are estimated (the preintegrations' input)."""
        return self.values.imu_matrices() if self.layout.imu_terms else None

    def drift(self) -> CalibrationDrift:
        """Cam0's estimated minus given calibration with its sigmas (for the health monitor)."""
        return calibration_drift(self.values, self.layout, self.cov, self.given)
