"""Headset-grade tracking metrics: jitter, world lock, prediction error at display latency, pose rate, drift.

All take estimated and true poses sampled at the same times ``t_s`` (N,), in the same world frame W: the
headset estimator starts from the true pose, so no alignment is applied (any alignment would hide the
world-lock error a user sees). Errors are expressed in W::

    e_p = p_est - p_true (m),   e_R = Log(R_est R_true^T) (rad, world-frame rotation error)

* **Jitter**: the RMS of the high-pass part of the error: a zero-phase Butterworth high-pass (order 2,
  applied forward and backward with ``scipy.signal.sosfiltfilt``, so the magnitude response is squared) at
  ``jitter_cutoff_hz = 1 Hz`` by default. Below ~1 Hz an error reads as the world slowly swimming or
  drifting (counted by world lock and drift); above it, as the world shaking. A sinusoidal error of
  amplitude ``A`` well above the cutoff gives ``A / sqrt(2)``; a constant offset or a slow drift gives ~0.
  Unevenly sampled series are first interpolated onto a uniform grid at the median sample period.
* **World lock**: ATE (RMS of ``|e_p|``) and the maximum ``|e_p|`` (mm).
* **Prediction error**: the 95th percentile of the position (mm) and rotation (deg) error of poses predicted
  to display time, over the samples where the head turns faster than ``fast_turn_deg_s = 150 deg/s``
  (where prediction matters; slow samples would dilute it).
* **Pose rate** (Hz): poses per second from the timestamps.
* **Drift** (%): final position error over the true path length.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.interpolate import interp1d
from scipy.signal import butter, sosfiltfilt
from scipy.spatial.transform import Rotation, Slerp


@dataclass(frozen=True)
class HeadsetMetricParams:
    """Settings of the headset metrics.

    Attributes:
        jitter_cutoff_hz: High-pass cutoff separating jitter from drift (Hz).
        jitter_filter_order: Butterworth order of the high-pass (applied twice: zero phase).
        fast_turn_deg_s: Head angular speed above which prediction errors are counted (deg/s).
        prediction_percentile: Percentile reported for the prediction errors.
    """

    jitter_cutoff_hz: float = 1.0
    jitter_filter_order: int = 2
    fast_turn_deg_s: float = 150.0
    prediction_percentile: float = 95.0

    def __post_init__(self) -> None:
        """Validate the settings."""
        if not self.jitter_cutoff_hz > 0.0:
            raise ValueError(f"HeadsetMetricParams.jitter_cutoff_hz must be > 0, got {self.jitter_cutoff_hz}")
        if self.jitter_filter_order < 1:
            raise ValueError(
                f"HeadsetMetricParams.jitter_filter_order must be >= 1, got {self.jitter_filter_order}"
            )
        if not 0.0 <= self.prediction_percentile <= 100.0:
            raise ValueError(
                "HeadsetMetricParams.prediction_percentile must be in [0, 100], "
                f"got {self.prediction_percentile}"
            )


def _check_times(t_s: np.ndarray, n_min: int = 2) -> np.ndarray:
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or len(t) < n_min or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0.0):
        raise ValueError(
            f"t_s must be a strictly increasing finite (N,) array with N >= {n_min}, got shape {t.shape}"
        )
    return t


def position_errors_W(p_est: np.ndarray, p_true: np.ndarray) -> np.ndarray:
    """Position errors ``p_est - p_true`` (m), shape (N, 3) from two (N, 3) arrays."""
    return np.asarray(p_est, dtype=float) - np.asarray(p_true, dtype=float)


def rotation_errors_W(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """World-frame rotation errors ``Log(R_est R_true^T)`` (rad), shape (N, 3) from two (N, 3, 3) arrays."""
    R_err = np.asarray(R_est, dtype=float) @ np.swapaxes(np.asarray(R_true, dtype=float), -1, -2)
    return Rotation.from_matrix(R_err).as_rotvec()


def interpolate_poses(
    t_query_s: np.ndarray, t_s: np.ndarray, R_WB: np.ndarray, p_WB: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``t_query_s`` (M,) within ``[t_s[0], t_s[-1]]``: slerp and linear interpolation.

    Args:
        t_query_s: Query times (s), shape (M,).
        t_s: Sample times (s), shape (N,), strictly increasing.
        R_WB: Orientations, shape (N, 3, 3).
        p_WB: Positions (m), shape (N, 3).

    Returns:
        ``(R_WB (M, 3, 3), p_WB (M, 3))``.
    """
    t = _check_times(t_s)
    R = Slerp(t, Rotation.from_matrix(R_WB))(np.asarray(t_query_s, dtype=float)).as_matrix()
    p = interp1d(t, np.asarray(p_WB, dtype=float), axis=0)(t_query_s)
    return R, p


def highpass(
    t_s: np.ndarray, x: np.ndarray, cutoff_hz: float = 1.0, order: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Zero-phase Butterworth high-pass of a sampled signal.

    Args:
        t_s: Sample times (s), shape (N,), strictly increasing.
        x: Signal, shape (N, K).
        cutoff_hz: Cutoff (Hz); must be below the Nyquist frequency.
        order: Butterworth order (applied forward and backward).

    Returns:
        ``(t_uniform_s (M,), x_highpass (M, K))`` on a uniform grid at the median period (the input grid
        itself when it is uniform to 1 %).

    Raises:
        ValueError: Bad times, or a cutoff at or above the Nyquist frequency.
    """
    t = _check_times(t_s, n_min=3)
    x = np.asarray(x, dtype=float).reshape(len(t), -1)
    dt = float(np.median(np.diff(t)))
    if np.max(np.abs(np.diff(t) - dt)) > 0.01 * dt:
        t_uniform = np.arange(t[0], t[-1] + 0.5 * dt, dt)
        t_uniform = t_uniform[t_uniform <= t[-1]]
        x = interp1d(t, x, axis=0)(t_uniform)
        t = t_uniform
    fs = 1.0 / dt
    if not cutoff_hz < 0.5 * fs:
        raise ValueError(f"cutoff {cutoff_hz} Hz must be below the Nyquist frequency {0.5 * fs:.3g} Hz")
    sos = butter(order, cutoff_hz, btype="highpass", fs=fs, output="sos")
    padlen = min(len(t) - 1, int(round(3.0 * fs / cutoff_hz)))  # ~3 time constants of the filter
    return t, sosfiltfilt(sos, x, axis=0, padtype="odd", padlen=padlen)


def jitter_rms(t_s: np.ndarray, err: np.ndarray, params: HeadsetMetricParams | None = None) -> float:
    """RMS norm of the high-pass part of an error series, in the error's unit.

    Args:
        t_s: Sample times (s), shape (N,).
        err: Errors, shape (N, K) (e.g. position m or rotation rad, K = 3).
        params: Cutoff and order.
    """
    p = params if params is not None else HeadsetMetricParams()
    _, hp = highpass(t_s, err, p.jitter_cutoff_hz, p.jitter_filter_order)
    return float(np.sqrt(np.mean(np.sum(hp * hp, axis=1))))


def pose_rate_hz(t_s: np.ndarray) -> float:
    """Poses per second, ``(N - 1) / (t[-1] - t[0])`` (Hz)."""
    t = _check_times(t_s)
    return float((len(t) - 1) / (t[-1] - t[0]))


def drift_pct(p_est: np.ndarray, p_true: np.ndarray) -> float | None:
    """Final position error over the true path length (%); None when the path length is zero."""
    p_true = np.asarray(p_true, dtype=float)
    length_m = float(np.sum(np.linalg.norm(np.diff(p_true, axis=0), axis=1)))
    if length_m <= 0.0:
        return None
    return float(100.0 * np.linalg.norm(np.asarray(p_est, dtype=float)[-1] - p_true[-1]) / length_m)


@dataclass(frozen=True)
class PredictionErrorStats:
    """Percentiles of the display-prediction errors during fast head turns.

    Attributes:
        pos_mm: Position error percentile (mm); None without fast samples.
        rot_deg: Rotation error percentile (deg); None without fast samples.
        n_fast: Samples faster than the threshold.
        n_total: All samples.
    """

    pos_mm: float | None
    rot_deg: float | None
    n_fast: int
    n_total: int


def prediction_errors(
    R_pred: np.ndarray,
    p_pred: np.ndarray,
    R_true: np.ndarray,
    p_true: np.ndarray,
    head_speed_rad_s: np.ndarray,
    params: HeadsetMetricParams | None = None,
) -> PredictionErrorStats:
    """Prediction error percentiles over the samples where the head turns fast.

    Args:
        R_pred: Predicted orientations at display time, shape (N, 3, 3).
        p_pred: Predicted positions (m), shape (N, 3).
        R_true: True orientations at the same display times, shape (N, 3, 3).
        p_true: True positions (m), shape (N, 3).
        head_speed_rad_s: True head angular speed ``|omega|`` (rad/s) when each prediction is made, (N,).
        params: Threshold and percentile.
    """
    p = params if params is not None else HeadsetMetricParams()
    fast = np.asarray(head_speed_rad_s, dtype=float) > np.deg2rad(p.fast_turn_deg_s)
    n = len(fast)
    if not np.any(fast):
        return PredictionErrorStats(None, None, 0, n)
    e_p_mm = 1e3 * np.linalg.norm(position_errors_W(p_pred, p_true)[fast], axis=1)
    e_r_deg = np.rad2deg(np.linalg.norm(rotation_errors_W(R_pred[fast], R_true[fast]), axis=1))
    q = p.prediction_percentile
    return PredictionErrorStats(
        float(np.percentile(e_p_mm, q)), float(np.percentile(e_r_deg, q)), int(fast.sum()), n
    )


@dataclass(frozen=True)
class HeadsetMetrics:
    """The headset metrics of one run (keys of ``viotb headset --json``).

    Attributes:
        jitter_pos_mm: High-pass position error RMS (mm).
        jitter_rot_deg: High-pass rotation error RMS (deg).
        world_lock_ate_mm: RMS position error, no alignment (mm).
        max_err_mm: Largest position error (mm).
        pred_err_pos_mm_p95: Prediction position error percentile in fast turns (mm), or None.
        pred_err_rot_deg_p95: Prediction rotation error percentile in fast turns (deg), or None.
        pose_rate_hz: Estimated poses per second (Hz).
        drift_pct: Final position error over path length (%), or None.
        notes: Reasons for the None values, by key.
    """

    jitter_pos_mm: float
    jitter_rot_deg: float
    world_lock_ate_mm: float
    max_err_mm: float
    pred_err_pos_mm_p95: float | None
    pred_err_rot_deg_p95: float | None
    pose_rate_hz: float
    drift_pct: float | None
    notes: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Plain dict (JSON-ready: floats, None and the notes)."""
        return asdict(self)


def headset_metrics(
    t_s: np.ndarray,
    R_est: np.ndarray,
    p_est: np.ndarray,
    R_true: np.ndarray,
    p_true: np.ndarray,
    prediction: PredictionErrorStats | None = None,
    params: HeadsetMetricParams | None = None,
) -> HeadsetMetrics:
    """All headset metrics of estimated vs true poses sampled at ``t_s``.

    Args:
        t_s: Pose times (s), shape (N,), strictly increasing.
        R_est: Estimated orientations, shape (N, 3, 3).
        p_est: Estimated positions (m), shape (N, 3).
        R_true: True orientations at ``t_s``, shape (N, 3, 3).
        p_true: True positions (m) at ``t_s``, shape (N, 3).
        prediction: Display-prediction statistics from :func:`prediction_errors` (None: not measured).
        params: Settings.
    """
    p = params if params is not None else HeadsetMetricParams()
    e_p = position_errors_W(p_est, p_true)
    e_r = rotation_errors_W(R_est, R_true)
    norms_mm = 1e3 * np.linalg.norm(e_p, axis=1)
    notes: dict[str, str] = {}
    if prediction is None or prediction.pos_mm is None:
        reason = (
            "no prediction measured"
            if prediction is None
            else f"no sample faster than {p.fast_turn_deg_s} deg/s"
        )
        notes["pred_err_pos_mm_p95"] = notes["pred_err_rot_deg_p95"] = reason
    drift = drift_pct(p_est, p_true)
    if drift is None:
        notes["drift_pct"] = "zero path length"
    return HeadsetMetrics(
        jitter_pos_mm=1e3 * jitter_rms(t_s, e_p, p),
        jitter_rot_deg=float(np.rad2deg(jitter_rms(t_s, e_r, p))),
        world_lock_ate_mm=float(np.sqrt(np.mean(norms_mm**2))),
        max_err_mm=float(norms_mm.max()),
        pred_err_pos_mm_p95=None if prediction is None else prediction.pos_mm,
        pred_err_rot_deg_p95=None if prediction is None else prediction.rot_deg,
        pose_rate_hz=pose_rate_hz(t_s),
        drift_pct=drift,
        notes=notes,
    )
