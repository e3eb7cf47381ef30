"""The nominal values of the filter state's blocks (:mod:`viotb.vio.state` owns them and the covariance).

``ImuValues`` (the IMU block), ``ClonePose`` (a pose clone) and ``SlamLandmark`` (a persistent landmark);
:mod:`viotb.vio.state` re-exports them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ImuValues:
    """Nominal IMU state (mutable arrays, written only by this module and the propagator).

    Attributes:
        R_WB: Orientation, shape (3, 3).
        p_WB: Position (m) in W, shape (3,).
        v_WB: Velocity (m/s) in W, shape (3,).
        gyro_bias_rad_s: shape (3,).
        accel_bias_m_s2: shape (3,).
    """

    R_WB: np.ndarray
    p_WB: np.ndarray
    v_WB: np.ndarray
    gyro_bias_rad_s: np.ndarray
    accel_bias_m_s2: np.ndarray

    def copy(self) -> ImuValues:
        """Deep copy."""
        return ImuValues(
            self.R_WB.copy(),
            self.p_WB.copy(),
            self.v_WB.copy(),
            self.gyro_bias_rad_s.copy(),
            self.accel_bias_m_s2.copy(),
        )


@dataclass
class ClonePose:
    """A stochastic clone of the IMU pose at a camera time.

    Attributes:
        t_s: Camera timestamp (s) of the clone (its key).
        R_WB: Current estimate, shape (3, 3).
        p_WB: Current estimate (m), shape (3,).
        R_WB_fej: First estimate (value when cloned), shape (3, 3).
        p_WB_fej: First estimate (m), shape (3,).
    """

    t_s: float
    R_WB: np.ndarray
    p_WB: np.ndarray
    R_WB_fej: np.ndarray
    p_WB_fej: np.ndarray


@dataclass
class SlamLandmark:
    """A persistent landmark: block ``[dp_f (3), db (2 B)]`` (:mod:`viotb.vio.slam_features`).

    Attributes:
        feature_id: Track id of the front end (its key).
        p_W: Current estimate (m) in W, shape (3,).
        p_W_fej: First estimate (m), the value it was initialized with, shape (3,).
        track_bias: Walk of the track error per camera (normalized coordinates; KLT), shape (B, 2).
        last_xy: Each camera's latest observation (normalized; NaN: unseen), shape (B, 2).
        gate_failures: Consecutive frames its observation failed the chi-square gate.
    """

    feature_id: int
    p_W: np.ndarray
    p_W_fej: np.ndarray
    track_bias: np.ndarray
    last_xy: np.ndarray
    gate_failures: int = 0
