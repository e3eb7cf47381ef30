"""Small frozen records that cross room boundaries (sensors -> estimator -> controller).

Frames: ``W`` world (z up, gravity ``-9.81 z``), ``B`` body = IMU, ``C`` camera (OpenCV: x right, y down,
z forward). Times in seconds (float64). Quaternions are Hamilton, ``quat_wxyz``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

GRAVITY_M_S2 = 9.81
"""Magnitude of gravity (m/s^2); the world gravity vector is ``(0, 0, -GRAVITY_M_S2)``."""


def gravity_W() -> np.ndarray:
    """World gravity vector (m/s^2), shape (3,): ``(0, 0, -9.81)``."""
    return np.array([0.0, 0.0, -GRAVITY_M_S2])


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise densities in Kalibr's convention.

    Discrete white-noise sigma = density / sqrt(dt); random-walk sigma per step = density * sqrt(dt).
    Defaults are the EuRoC ADIS16448 values from its ``imu0/sensor.yaml``.
    """

    gyro_noise_density_rad_s_sqrthz: float = 1.6968e-4
    gyro_random_walk_rad_s2_sqrthz: float = 1.9393e-5
    accel_noise_density_m_s2_sqrthz: float = 2.0e-3
    accel_random_walk_m_s3_sqrthz: float = 3.0e-3


@dataclass(frozen=True)
class ImuSample:
    """One IMU reading in the body (IMU) frame B.

    Attributes:
        t_s: Timestamp (s) on the IMU clock.
        gyro_B_rad_s: Angular rate of B w.r.t. W, in B (rad/s), shape (3,).
        accel_B_m_s2: Specific force ``R_WB^T (a_W - g_W)`` in B (m/s^2), shape (3,); reads +9.81 z
            when level and still.
        saturated: True if any axis was clipped at the sensor's range.
    """

    t_s: float
    gyro_B_rad_s: np.ndarray
    accel_B_m_s2: np.ndarray
    saturated: bool = False


@dataclass(frozen=True)
class ImuSeries:
    """A batch of IMU readings (N samples), the array form of :class:`ImuSample`.

    Attributes:
        t_s: Timestamps (s), shape (N,), strictly increasing.
        gyro_B_rad_s: shape (N, 3).
        accel_B_m_s2: shape (N, 3).
        saturated: shape (N,), bool.
    """

    t_s: np.ndarray
    gyro_B_rad_s: np.ndarray
    accel_B_m_s2: np.ndarray
    saturated: np.ndarray

    def __len__(self) -> int:
        """Number of samples."""
        return int(self.t_s.shape[0])

    def sample(self, i: int) -> ImuSample:
        """The i-th reading as an :class:`ImuSample`."""
        return ImuSample(
            float(self.t_s[i]), self.gyro_B_rad_s[i], self.accel_B_m_s2[i], bool(self.saturated[i])
        )


@dataclass(frozen=True)
class FeatureObservations:
    """Simulated-feature measurements of one frame (fast mode, no image processing).

    Attributes:
        ids: Landmark ids, shape (M,), int64.
        uv_px: Distorted pixel coordinates (OpenCV convention, pixel centres at integers), shape (M, 2).
    """

    ids: np.ndarray
    uv_px: np.ndarray


@dataclass(frozen=True)
class CameraFrame:
    """One camera frame: a grayscale image and/or simulated feature observations.

    Mono rigs leave the ``*_right`` fields None; a stereo rig fills them with its second camera (cam1),
    triggered with cam0 (synchronized global shutter, same timestamp).

    Attributes:
        t_s: Timestamp (s) on the camera clock (``t_imu = t_s + time_offset_s`` of the rig calibration).
        image: Grayscale uint8 image of cam0, shape (H, W), or None in simulated-feature mode.
        features: Simulated observations of cam0, or None for real images.
        image_right: Grayscale uint8 image of cam1 at the same timestamp, shape (H1, W1), or None.
        features_right: Simulated observations of cam1 (the same landmark ids as ``features`` where a
            landmark is seen by both), or None.
    """

    t_s: float
    image: np.ndarray | None = None
    features: FeatureObservations | None = None
    image_right: np.ndarray | None = None
    features_right: FeatureObservations | None = None


@dataclass(frozen=True)
class TrajectoryArrays:
    """A timed pose trajectory of B in W (ground truth or estimate).

    Attributes:
        t_s: shape (N,).
        p_WB: Positions (m), shape (N, 3).
        quat_wxyz_WB: Orientations ``R_WB`` as Hamilton quaternions, shape (N, 4).
        v_WB: Optional velocities (m/s) in W, shape (N, 3).
    """

    t_s: np.ndarray
    p_WB: np.ndarray
    quat_wxyz_WB: np.ndarray
    v_WB: np.ndarray | None = None

    def __len__(self) -> int:
        """Number of poses."""
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class StateEstimate:
    """The navigation state an estimator reports.

    Attributes:
        t_s: Time (s) of the estimate, on the IMU clock.
        R_WB: Orientation, shape (3, 3).
        p_WB: Position (m), shape (3,).
        v_WB: Velocity (m/s) in W, shape (3,).
        gyro_bias_rad_s: shape (3,).
        accel_bias_m_s2: shape (3,).
        omega_B_rad_s: Bias-corrected angular rate in B (rad/s) of the latest IMU sample, shape (3,).
        cov: Error-state covariance of ``[dtheta, dp, dv, dbg, dba]``, shape (15, 15), where
            ``R_WB = R_hat Exp(dtheta)`` (body-frame / right perturbation) and the rest are additive.
    """

    t_s: float
    R_WB: np.ndarray
    p_WB: np.ndarray
    v_WB: np.ndarray
    gyro_bias_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega_B_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cov: np.ndarray = field(default_factory=lambda: np.zeros((15, 15)))

    @property
    def cov_orientation_rad2(self) -> np.ndarray:
        """Covariance of the orientation error ``dtheta`` (rad^2, in B: ``R = R_hat Exp(dtheta)``), (3, 3)."""
        return self.cov[0:3, 0:3]

    @property
    def cov_position_W_m2(self) -> np.ndarray:
        """Covariance of ``p_WB`` (m^2, world frame W), shape (3, 3)."""
        return self.cov[3:6, 3:6]

    @property
    def cov_velocity_W_m2_s2(self) -> np.ndarray:
        """Covariance of ``v_WB`` (m^2/s^2, world frame W), shape (3, 3)."""
        return self.cov[6:9, 6:9]

    @property
    def cov_gyro_bias_rad2_s2(self) -> np.ndarray:
        """Covariance of the gyro bias (rad^2/s^2, body frame B), shape (3, 3)."""
        return self.cov[9:12, 9:12]

    @property
    def cov_accel_bias_m2_s4(self) -> np.ndarray:
        """Covariance of the accelerometer bias (m^2/s^4, body frame B), shape (3, 3)."""
        return self.cov[12:15, 12:15]

    @property
    def position_sigma_W_m(self) -> np.ndarray:
        """Standard deviations of ``p_WB`` along the W axes (m), shape (3,) (negative variances read 0)."""
        return np.sqrt(np.maximum(np.diag(self.cov_position_W_m2), 0.0))


@dataclass(frozen=True)
class CalibrationDrift:
    """How far online calibration has moved the camera-IMU calibration from the one the estimator was given.

    Each field is NaN where that quantity is not estimated.

    Attributes:
        time_offset_s: Estimated minus given time offset (s, ``t_imu = t_cam + offset``).
        time_offset_sigma_s: Its standard deviation (s).
        rotation_BC_rad: ``log(R_BC,given^T R_BC,est)`` (rad, camera frame), shape (3,).
        rotation_sigma_rad: Standard deviations of its three components (rad), shape (3,).
        translation_BC_m: Estimated minus given ``p_BC`` (m, body frame), shape (3,).
        translation_sigma_m: Standard deviations (m), shape (3,).
    """

    time_offset_s: float = float("nan")
    time_offset_sigma_s: float = float("nan")
    rotation_BC_rad: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    rotation_sigma_rad: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    translation_BC_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    translation_sigma_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))


@dataclass(frozen=True)
class HealthStatus:
    """Estimator health after the latest camera frame.

    Attributes:
        t_s: Time (s) of the frame.
        initialized: Whether the estimator has a state yet.
        tracked_features: Features tracked in the latest frame.
        updated_features: Features used in the latest update.
        chi2_rejections: Features rejected by the chi-square gate in the latest update.
        diverged: True once the estimator has detected its own divergence (it then stops updating).
        reason: Human-readable explanation when ``diverged`` (NaN, non-PSD covariance, runaway innovation).
        conditions: Named conditions raised by the health monitor (e.g. ``"feature_poverty"``).
        nis_per_dof: Mean normalized innovation squared per degree of freedom of the features that passed
            the gate in the latest update (about 1 for a consistent filter; NaN when there was no update).
        nis_per_dof_all: The same over every triangulated candidate, rejected ones included (NaN if none).
        calibration: Drift of the online camera-IMU calibration from the given one, or None when the
            estimator calibrates nothing online.
    """

    t_s: float
    initialized: bool
    tracked_features: int = 0
    updated_features: int = 0
    chi2_rejections: int = 0
    diverged: bool = False
    reason: str = ""
    conditions: tuple[str, ...] = ()
    nis_per_dof: float = float("nan")
    nis_per_dof_all: float = float("nan")
    calibration: CalibrationDrift | None = None


class EstimatorDiverged(RuntimeError):
    """Raised (or reported) when an estimator detects that its state is no longer trustworthy."""


@runtime_checkable
class Estimator(Protocol):
    """The interface every estimator (``msckf``, ``window``, ``imu-only``, ``ground-truth``) implements.

    Samples are fed in timestamp order on the IMU clock (camera frames carry camera-clock stamps; the
    estimator applies its time offset). Every method applies to every estimator; where one does not (truth
    for a VIO estimator, an initial state for the pass-through) it is a documented no-op, so callers never
    need ``getattr``.
    """

    name: str

    def feed_imu(self, sample: ImuSample) -> None:
        """Consume one IMU reading."""

    def feed_camera(self, frame: CameraFrame) -> None:
        """Consume one camera frame (runs the front end and the update)."""

    def estimate(self) -> StateEstimate | None:
        """Latest state, propagated to the newest IMU sample; None before initialization."""

    def health(self) -> HealthStatus:
        """Health of the latest frame."""

    def initialize(self, init: object) -> None:
        """Start from an external initial state instead of the estimator's own initializer.

        Args:
            init: An ``InitResult``-like record (``t_s``, ``R_WB`` (3, 3), ``p_WB`` (3,) m, ``v_WB`` (3,)
                m/s in W, ``gyro_bias_rad_s`` (3,), ``accel_bias_m_s2`` (3,), ``cov_diag`` (15,) in the
                :class:`StateEstimate` error order). Estimators that take no initial state ignore it.
        """

    def feed_truth(self, truth: StateEstimate) -> None:
        """Consume the true state at the latest frame (``ground-truth`` reports it; the others ignore it)."""

    def wants_excitation(self) -> bool:
        """True while the estimator asks for an excitation manoeuvre (a poorly known accelerometer bias)."""

    def last_tracks_px(self) -> np.ndarray:
        """Distorted pixels of the features tracked in the latest frame, shape (M, 2) (M may be 0)."""
