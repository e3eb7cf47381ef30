"""Baseline estimators: IMU-only dead reckoning and a ground-truth pass-through.

``ImuOnlyEstimator`` starts like the MSCKF (an explicit :meth:`initialize` or the shared inertial initializer)
and then only integrates the IMU with :class:`viotb.vio.propagator.Propagator`; its covariance grows without
bound. ``GroundTruthEstimator`` reports the truth it is fed (``feed_truth``), for fast policy training. Both
implement the whole :class:`~viotb.vio.types.Estimator` protocol, the methods that do not apply as documented
no-ops.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.initialization import InertialInitializer, InitParams
from viotb.vio.propagator import Integration, Propagator
from viotb.vio.state import IMU_BLOCK, State, marginal_covariance, read_init_record
from viotb.vio.types import CameraFrame, HealthStatus, ImuNoise, ImuSample, StateEstimate


class ImuOnlyEstimator:
    """Dead reckoning from the initial state (name ``"imu-only"``).

    Args:
        calib: Camera calibration (used only by the initializer).
        noise: IMU noise densities.
        integration: Integration method.
    """

    name = "imu-only"

    def __init__(
        self, calib: CameraCalibration, noise: ImuNoise, integration: Integration = Integration.RK4
    ) -> None:
        """Create an uninitialized dead-reckoning estimator."""
        self.calib = calib
        self.propagator = Propagator(noise, integration, use_fej=False)
        self.initializer = InertialInitializer(calib, noise, InitParams())
        self.state: State | None = None
        self._last_imu: ImuSample | None = None
        self._health = HealthStatus(t_s=0.0, initialized=False)

    def initialize(self, init: object) -> None:
        """Start from an ``InitResult``-like record (as ``MsckfEstimator.initialize``)."""
        t_s, vals, cov = read_init_record(init)
        self.state = State(t_s, vals, cov, self.calib.R_BC, self.calib.p_BC, self.calib.time_offset_s)
        self._health = HealthStatus(t_s=t_s, initialized=True)

    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer and integrate one reading (ValueError on NaN/inf or non-increasing time)."""
        self.propagator.feed_imu(sample)
        self._last_imu = sample
        if self.state is None:
            if self.initializer is not None:
                self.initializer.feed_imu(sample)
            return
        self.propagator.propagate(self.state, float(sample.t_s))

    def feed_camera(self, frame: CameraFrame) -> None:
        """Camera frames only drive the initializer (features are not used otherwise)."""
        if self.state is None and self.initializer is not None:
            init = self.initializer.try_initialize()
            if init is not None:
                self.initialize(init)
        self._health = HealthStatus(t_s=frame.t_s, initialized=self.state is not None)

    def estimate(self) -> StateEstimate | None:
        """The dead-reckoned state at the newest IMU sample, or None before initialization."""
        st = self.state
        if st is None:
            return None
        omega = np.zeros(3)
        if self._last_imu is not None:
            omega = np.asarray(self._last_imu.gyro_B_rad_s, dtype=float) - st.imu.gyro_bias_rad_s
        return StateEstimate(
            t_s=st.t_s,
            R_WB=st.imu.R_WB.copy(),
            p_WB=st.imu.p_WB.copy(),
            v_WB=st.imu.v_WB.copy(),
            gyro_bias_rad_s=st.imu.gyro_bias_rad_s.copy(),
            accel_bias_m_s2=st.imu.accel_bias_m_s2.copy(),
            omega_B_rad_s=omega,
            cov=marginal_covariance(st, [st.block(IMU_BLOCK)]),
        )

    def health(self) -> HealthStatus:
        """Health of the latest frame (never diverges by itself)."""
        return self._health

    def feed_truth(self, truth: StateEstimate) -> None:
        """Truth is not used by dead reckoning (no-op; part of :class:`viotb.vio.types.Estimator`)."""

    def wants_excitation(self) -> bool:
        """Always False: dead reckoning gains nothing from excitation (its bias is never observed)."""
        return False

    def last_tracks_px(self) -> np.ndarray:
        """No front end: always an empty (0, 2) array."""
        return np.zeros((0, 2))


class GroundTruthEstimator:
    """Passes the ground truth through (name ``"ground-truth"``).

    Args:
        calib: Unused; kept for a uniform factory signature.
        noise: Unused.
    """

    name = "ground-truth"

    def __init__(self, calib: CameraCalibration | None = None, noise: ImuNoise | None = None) -> None:
        """Create the pass-through."""
        self._truth: StateEstimate | None = None
        self._health = HealthStatus(t_s=0.0, initialized=False)

    def feed_truth(self, truth: StateEstimate) -> None:
        """Set the state to report."""
        self._truth = truth
        self._health = HealthStatus(t_s=truth.t_s, initialized=True)

    def feed_imu(self, sample: ImuSample) -> None:
        """IMU samples are ignored."""

    def feed_camera(self, frame: CameraFrame) -> None:
        """Camera frames are ignored (health keeps the truth's time)."""

    def estimate(self) -> StateEstimate | None:
        """The last truth fed, or None."""
        return self._truth

    def health(self) -> HealthStatus:
        """Initialized once truth has been fed."""
        return self._health

    def initialize(self, init: object) -> None:
        """No-op: the pass-through reports only the truth it is fed (:meth:`feed_truth`)."""

    def wants_excitation(self) -> bool:
        """Always False: the truth needs no excitation."""
        return False

    def last_tracks_px(self) -> np.ndarray:
        """No front end: always an empty (0, 2) array."""
        return np.zeros((0, 2))
