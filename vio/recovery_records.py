"""The records and settings of recovery in flight (:mod:`viotb.vio.recovery`).

:class:`RecoveryParams` (the settings of :class:`~viotb.vio.recovery.RecoveringEstimator`), the MSCKF
settings of a re-initialized filter, and what a recovery reports: :class:`RecoveryEvent` per loss of
tracking, :class:`OdometryReset` per jump of the published odometry.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from viotb.vio.msckf_params import MsckfParams

RECOVERABLE_ESTIMATORS = ("msckf", "window")
"""Estimator names :class:`RecoveringEstimator` can wrap (those with a front end and an initializer)."""


@dataclass(frozen=True)
class RecoveryParams:
    """Settings of :class:`~viotb.vio.recovery.RecoveringEstimator` (units in the names).

    Attributes:
        feature_loss_s: Tracking is lost after frames with no tracked feature for this long (s).
        return_min_features: A frame with at least this many tracked features counts as "features back"
            (the health monitor's ``feature_poverty`` bound).
        return_frames: Consecutive such frames before the hand-over.
        history_s: IMU history kept (s) to start the coaster and the fresh estimator from a past state.
        cov_inflation: Factor on the coasted variances of the observable states given to the new estimator.
        sigma_position_m: Gauge prior (m) of the re-anchored position.
        min_sigma_tilt_rad: Floor of the seeded attitude sigma (rad).
        min_sigma_velocity_m_s: Floor of the seeded velocity sigma (m/s).
        min_sigma_gyro_bias_rad_s: Floor of the seeded gyro-bias sigma (rad/s).
        min_sigma_accel_bias_m_s2: Floor of the seeded accelerometer-bias sigma (m/s^2).
    """

    feature_loss_s: float = 0.5
    return_min_features: int = 20
    return_frames: int = 3
    history_s: float = 3.0
    cov_inflation: float = 2.0
    sigma_position_m: float = 1e-3
    min_sigma_tilt_rad: float = 1e-3
    min_sigma_velocity_m_s: float = 0.02
    min_sigma_gyro_bias_rad_s: float = 1e-4
    min_sigma_accel_bias_m_s2: float = 0.01

    def __post_init__(self) -> None:
        """Validate the fields (message names the field and value)."""
        for name in ("feature_loss_s", "history_s", "cov_inflation", "sigma_position_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f"RecoveryParams.{name} must be positive and finite, got {value}")
        for name in ("return_min_features", "return_frames"):
            value = getattr(self, name)
            if not (isinstance(value, int | np.integer) and value >= 1):
                raise ValueError(f"RecoveryParams.{name} must be an integer >= 1, got {value!r}")


def cold_start_msckf_params(params: MsckfParams) -> MsckfParams:
    """MSCKF settings for a re-initialized filter (``make_reinit``): a pose clone at every frame.

    The MSCKF updates a feature when its track ends or its oldest clone leaves the window. After a total
    loss every track starts at once and, in a hover, clones come only every ``every_n_frames`` (6) frames:
    the first update waits until the window is full (11 clones, 3.3 s), by which time the coasted velocity
    error (measured up to 8 cm/s after 4 s of darkness) has made the clone poses disagree with the tracks,
    and the triangulation gate rejects every candidate (measured: 50 of 50): the filter never recovers. A
    clone per frame fills the window in 0.55 s. Measured on ``fly-lights-out`` (4 s dark), excursion after
    the light returns: 111 -> 38 cm (seed 1), 70 -> 27 (5), 62 -> 21 (6) with simulated features; 108 -> 34
    (1), 74 -> 61 cm (3) with KLT.
    """
    return replace(params, keyframing=replace(params.keyframing, every_n_frames=1))


@dataclass
class RecoveryEvent:
    """One loss of tracking and its recovery.

    Attributes:
        t_lost_s: When tracking was declared lost (s, IMU clock).
        reason: Why.
        t_coast_start_s: Time (s) of the state the coast started from (the last good estimate).
        t_reinit_s: When the fresh estimator took over (s), None while still coasting.
        coast_position_sigma_m: Largest position sigma (m) of the coasted state at the hand-over: how far the
            re-anchored frame may be from the old one.
    """

    t_lost_s: float
    reason: str
    t_coast_start_s: float
    t_reinit_s: float | None = None
    coast_position_sigma_m: float = float("nan")


@dataclass(frozen=True)
class OdometryReset:
    """A jump of the published odometry at one instant: the pose just before and just after it.

    A velocity fix is an EKF update of the coasted state: through the coasted correlations it moves the
    position too (measured up to 21 cm after 4 s dark, ``fly-lights-out``); the hand-over replaces the
    estimator (the pose is continuous, the odometry is another one). A consumer that keeps a correction of
    the odometry (the loop closer's ``T_map_odom``) must carry it over (``LoopCloser.notify_odometry_reset``).

    Attributes:
        t_s: Time of both poses (s, IMU clock).
        reason: ``"velocity fix"`` or ``"hand-over"``.
        R_WB_before: Attitude before, shape (3, 3).
        p_WB_before: Position before (m), shape (3,).
        R_WB_after: Attitude after, shape (3, 3).
        p_WB_after: Position after (m), shape (3,).
    """

    t_s: float
    reason: str
    R_WB_before: np.ndarray
    p_WB_before: np.ndarray
    R_WB_after: np.ndarray
    p_WB_after: np.ndarray
