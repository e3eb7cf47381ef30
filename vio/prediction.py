"""Display pose prediction: the head pose extrapolated to the time the frame reaches the eyes.

A headset renders with the pose at ``t + latency`` (motion-to-photon latency, ~20 ms), from the latest
estimate at ``t``: orientation ``R_WB``, position ``p_WB``, velocity ``v_WB``, the bias-corrected gyro
``omega_B`` and the bias-corrected, gravity-removed acceleration ``a_W = R_WB (f_B - b_a) + g_W``. With
``dt = latency``, two motion models:

* ``"constant-acceleration"`` (default): body angular velocity and *world* acceleration constant::

      R(t + dt) = R Exp(omega_B dt),   p(t + dt) = p + v dt + a_W dt^2 / 2

  exact for that motion (rotation and translation decoupled). With an angular acceleration ``alpha_B``
  (from the recent gyro, :func:`angular_acceleration_from_gyro`), ``omega_B(t) = omega_B + alpha_B t`` and
  the rotation uses the third-order Magnus expansion for ``dR/dt = R [omega_B(t)]x``::

      R(t + dt) = R Exp(omega_B dt + alpha_B dt^2 / 2 + (omega_B x alpha_B) dt^3 / 12)

  (exact when ``alpha_B`` is parallel to ``omega_B``). Without it the rotation errs by ``|alpha| dt^2 / 2``
  to leading order: 0.2 deg for a head turn accelerating at 1000 deg/s^2 over 20 ms.
* ``"constant-twist"``: the body twist ``(v_B, omega_B)`` with ``v_B = R^T v_WB`` is constant, the head moves
  on a helix, and ``T(t + dt) = T Exp(dt (v_B, omega_B))`` (SE(3) exponential) is exact for it; ``a_W`` is
  not used (a constant twist implies ``a_W = R (omega_B x v_B)``). The constant-acceleration model on that
  helix errs by the jerk term ``|omega x (omega x v_B)| dt^3 / 6``: 0.03 mm at 5 rad/s, 1 m/s, 20 ms.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
from viotb.vio.lie import cross, exp_so3, left_jacobian_so3
from viotb.vio.types import GRAVITY_M_S2

MOTION_MODELS = ("constant-acceleration", "constant-twist")
"""Names accepted by :attr:`PredictionParams.motion_model`."""


@dataclass(frozen=True)
class PredictionParams:
    """Settings of the display pose predictor.

    Attributes:
        latency_s: Default prediction horizon, the motion-to-photon latency (s).
        motion_model: One of :data:`MOTION_MODELS`.
        use_angular_acceleration: Extrapolate the rotation with the angular acceleration estimated from the
            recent gyro (constant-acceleration model only).
        alpha_window_s: Length of the gyro history the angular acceleration is fitted on (s).
    """

    latency_s: float = 0.020
    motion_model: str = "constant-acceleration"
    use_angular_acceleration: bool = False
    alpha_window_s: float = 0.030

    def __post_init__(self) -> None:
        """Validate the settings."""
        if not (np.isfinite(self.latency_s) and self.latency_s >= 0.0):
            raise ValueError(f"PredictionParams.latency_s must be finite and >= 0, got {self.latency_s}")
        if self.motion_model not in MOTION_MODELS:
            raise ValueError(
                f"PredictionParams.motion_model must be one of {MOTION_MODELS}, got {self.motion_model!r}"
            )
        if self.use_angular_acceleration and self.motion_model != "constant-acceleration":
            raise ValueError(
                "PredictionParams.use_angular_acceleration needs motion_model='constant-acceleration'"
            )
        if not self.alpha_window_s > 0.0:
            raise ValueError(f"PredictionParams.alpha_window_s must be > 0, got {self.alpha_window_s}")


@dataclass(frozen=True)
class MotionState:
    """The estimate a prediction starts from (bias-corrected).

    Attributes:
        t_s: Time of the estimate (s).
        R_WB: Orientation, shape (3, 3).
        p_WB: Position (m), shape (3,).
        v_WB: Velocity in W (m/s), shape (3,).
        omega_B: Angular velocity in B (rad/s), shape (3,): gyro minus its bias.
        a_W: Acceleration in W (m/s^2), shape (3,): ``R_WB (f_B - b_a) + g_W``, gravity removed.
        alpha_B: Angular acceleration in B (rad/s^2), shape (3,).
    """

    t_s: float
    R_WB: np.ndarray
    p_WB: np.ndarray
    v_WB: np.ndarray
    omega_B: np.ndarray
    a_W: np.ndarray = field(default_factory=lambda: np.zeros(3))
    alpha_B: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class PredictedPose:
    """A predicted pose.

    Attributes:
        t_s: Time the pose is predicted for (s).
        R_WB: Orientation, shape (3, 3).
        p_WB: Position (m), shape (3,).
    """

    t_s: float
    R_WB: np.ndarray
    p_WB: np.ndarray


def gravity_removed_acceleration_W(
    R_WB: np.ndarray, specific_force_B: np.ndarray, gravity_m_s2: float = GRAVITY_M_S2
) -> np.ndarray:
    """World acceleration from a bias-corrected accelerometer sample, ``R_WB f_B + g_W`` (m/s^2), (3,).

    ``g_W = (0, 0, -gravity_m_s2)`` (W is z up).
    """
    return R_WB @ np.asarray(specific_force_B, dtype=float) - np.array([0.0, 0.0, gravity_m_s2])


def angular_acceleration_from_gyro(t_s: np.ndarray, omega_B: np.ndarray) -> np.ndarray:
    """Angular acceleration (rad/s^2), shape (3,): least-squares slope of the gyro over time.

    Args:
        t_s: Sample times (s), shape (N,), N >= 2 and not all equal.
        omega_B: Bias-corrected gyro samples (rad/s), shape (N, 3).

    Raises:
        ValueError: Fewer than 2 samples, mismatched shapes or no time span.
    """
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(omega_B, dtype=float)
    if t.ndim != 1 or w.shape != (len(t), 3) or len(t) < 2:
        raise ValueError(f"need t_s (N,) and omega_B (N, 3) with N >= 2, got {t.shape} and {w.shape}")
    dt = t - t.mean()
    denom = float(dt @ dt)
    if denom <= 0.0:
        raise ValueError("angular_acceleration_from_gyro: the samples span no time")
    return dt @ (w - w.mean(axis=0)) / denom


def predict_pose(
    state: MotionState, params: PredictionParams | None = None, dt_s: float | None = None
) -> PredictedPose:
    """Extrapolate ``state`` by ``dt_s`` (default ``params.latency_s``) with the chosen motion model.

    Args:
        state: The bias-corrected estimate at ``state.t_s``.
        params: Settings (default :class:`PredictionParams`).
        dt_s: Horizon (s); may be negative (back-prediction).

    Returns:
        The pose at ``state.t_s + dt_s``.
    """
    p = params if params is not None else PredictionParams()
    dt = p.latency_s if dt_s is None else float(dt_s)
    R_WB = np.asarray(state.R_WB, dtype=float)
    omega = np.asarray(state.omega_B, dtype=float)
    if p.motion_model == "constant-twist":
        v_B = R_WB.T @ np.asarray(state.v_WB, dtype=float)
        phi = omega * dt
        R_new = R_WB @ exp_so3(phi)
        p_new = state.p_WB + R_WB @ (left_jacobian_so3(phi) @ (v_B * dt))
        return PredictedPose(state.t_s + dt, R_new, p_new)
    phi = omega * dt
    if p.use_angular_acceleration:
        alpha = np.asarray(state.alpha_B, dtype=float)
        phi = phi + 0.5 * alpha * dt**2 + cross(omega, alpha) * (dt**3 / 12.0)
    R_new = R_WB @ exp_so3(phi)
    p_new = state.p_WB + state.v_WB * dt + 0.5 * np.asarray(state.a_W, dtype=float) * dt**2
    return PredictedPose(state.t_s + dt, R_new, p_new)


class DisplayPosePredictor:
    """Keeps the recent gyro to estimate the angular acceleration, and predicts display poses.

    Args:
        params: Settings.
    """

    def __init__(self, params: PredictionParams | None = None) -> None:
        """Create a predictor with an empty gyro history."""
        self.params = params if params is not None else PredictionParams()
        self._gyro: deque[tuple[float, np.ndarray]] = deque()

    def add_gyro(self, t_s: float, omega_B: np.ndarray) -> None:
        """Record a bias-corrected gyro sample (rad/s), shape (3,), at ``t_s``; drops the ones too old."""
        self._gyro.append((float(t_s), np.asarray(omega_B, dtype=float).copy()))
        while self._gyro and self._gyro[0][0] < t_s - self.params.alpha_window_s:
            self._gyro.popleft()

    def angular_acceleration_B(self) -> np.ndarray:
        """Angular acceleration (rad/s^2), shape (3,) from the gyro history; zeros with < 3 samples."""
        if len(self._gyro) < 3:
            return np.zeros(3)
        t = np.array([s[0] for s in self._gyro])
        w = np.array([s[1] for s in self._gyro])
        return angular_acceleration_from_gyro(t, w)

    def predict(self, state: MotionState, dt_s: float | None = None) -> PredictedPose:
        """Pose ``dt_s`` (default: the latency) after ``state``, with ``alpha_B`` from the gyro history."""
        if self.params.use_angular_acceleration:
            state = replace(state, alpha_B=self.angular_acceleration_B())
        return predict_pose(state, self.params, dt_s)
