"""The window estimator's online calibration: current values, prior, covariance and image velocities.

:class:`OnlineCalibration` is what :class:`viotb.vio.window.WindowEstimator` holds when
``WindowParams.estimate_extrinsics`` or ``estimate_time_offset`` is on (the variables and their Jacobians:
:mod:`viotb.vio.window_calib`; their part of the system: :mod:`viotb.vio.window_calib_system`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from viotb.vio.camera import CameraCalibration
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
        self.layout = CalibLayout(n_cams, params.estimate_extrinsics, params.estimate_time_offset)
        sig = [params.extrinsic_sigma_rad] * 3 + [params.extrinsic_sigma_m] * 3
        self._prior_sigma = np.array(sig * n_cams + [params.time_offset_sigma_s])[self.layout.active]
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
            ValueError: With ``params.track_noise`` (the correlated-noise factors take no more variables), or
                a ``calibration_start_keyframes`` the window never holds (over ``window_size``).
        """
        if not (params.estimate_extrinsics or params.estimate_time_offset):
            return None
        if params.track_noise:
            raise ValueError("WindowParams: online calibration needs track_noise=False (white track noise)")
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

    def drift(self) -> CalibrationDrift:
        """Cam0's estimated minus given calibration with its sigmas (for the health monitor)."""
        return calibration_drift(self.values, self.layout, self.cov, self.given)
