"""The per-frame steps every feature-based estimator shares: the initialization attempt and the health record.

Before it has a state, an estimator feeds each frame's tracks to its inertial initializer and tries to
initialize (:func:`attempt_initialization`); afterwards it reports a :class:`~viotb.vio.types.HealthStatus`
per frame (:func:`frame_health`) with the front-end conditions ``no_features`` and ``feature_poverty``
(:func:`track_conditions`), and asks for excitation while its accelerometer bias is poorly known
(:func:`excitation_wanted`).
"""

from __future__ import annotations

import numpy as np
from viotb.vio.frontend import Tracks
from viotb.vio.initialization import InertialInitializer, InitResult
from viotb.vio.state import BA
from viotb.vio.types import CalibrationDrift, HealthStatus


def attempt_initialization(
    initializer: InertialInitializer | None, tracks: Tracks
) -> tuple[InitResult | None, HealthStatus]:
    """Feed a frame's tracks to the initializer and try to initialize.

    Args:
        initializer: The inertial initializer (None: never initializes from frames).
        tracks: The frame's tracks (times on the camera and IMU clocks).

    Returns:
        ``(init, health)``: the initial state or None, and the health to report for this frame
        (``waiting_for_init`` until an initial state exists).
    """
    init = None
    if initializer is not None:
        if len(tracks):
            initializer.feed_features(tracks.t_imu_s, tracks.ids, tracks.xy_norm)
        init = initializer.try_initialize()
    health = HealthStatus(
        t_s=tracks.t_cam_s,
        initialized=init is not None,
        tracked_features=len(tracks),
        conditions=() if init is not None else ("waiting_for_init",),
    )
    return init, health


def track_conditions(n_tracked: int, min_tracked_features: int = 20) -> tuple[str, ...]:
    """Front-end conditions: ``no_features`` without tracks, ``feature_poverty`` below the minimum."""
    if n_tracked == 0:
        return ("no_features",)
    if n_tracked < min_tracked_features:
        return ("feature_poverty",)
    return ()


def frame_health(
    t_s: float,
    tracks: Tracks,
    diverged_reason: str,
    *,
    updated_features: int,
    conditions: tuple[str, ...] = (),
    chi2_rejections: int = 0,
    nis_per_dof: float = float("nan"),
    nis_per_dof_all: float = float("nan"),
    calibration: CalibrationDrift | None = None,
) -> HealthStatus:
    """The health of an initialized estimator after one frame.

    Args:
        t_s: Frame time (s, camera clock).
        tracks: The frame's tracks.
        diverged_reason: Why the estimator diverged, or ``""``.
        updated_features: Features used in the frame's update.
        conditions: The estimator's own conditions; :func:`track_conditions` are appended.
        chi2_rejections: Features rejected by the chi-square gate.
        nis_per_dof: Mean NIS per dof of the features that passed the gate.
        nis_per_dof_all: The same over every triangulated candidate.
        calibration: Online-calibration drift, or None.
    """
    return HealthStatus(
        t_s=t_s,
        initialized=True,
        tracked_features=len(tracks),
        updated_features=updated_features,
        chi2_rejections=chi2_rejections,
        diverged=bool(diverged_reason),
        reason=diverged_reason,
        conditions=tuple(conditions) + track_conditions(len(tracks)),
        nis_per_dof=nis_per_dof,
        nis_per_dof_all=nis_per_dof_all,
        calibration=calibration,
    )


def excitation_wanted(cov_imu: np.ndarray, max_accel_bias_sigma_m_s2: float) -> bool:
    """True while the horizontal accelerometer-bias sigma exceeds ``max_accel_bias_sigma_m_s2`` (m/s^2).

    After a static initialization the accelerometer bias along x and y is confounded with roll and pitch until
    the platform rotates and accelerates (lesson ch. 6-8: "design the motion in"); a runner answers with an
    excitation manoeuvre.

    Args:
        cov_imu: Covariance of the IMU error state ``[dtheta, dp, dv, dbg, dba]``, shape (15, 15).
        max_accel_bias_sigma_m_s2: Threshold (m/s^2).
    """
    return bool(np.sqrt(np.max(np.diag(cov_imu)[BA : BA + 2])) > max_accel_bias_sigma_m_s2)
