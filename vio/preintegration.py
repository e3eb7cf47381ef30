"""On-manifold IMU preintegration (Forster, Carlone, Dellaert, Scaramuzza, TRO 2017).

Between keyframes i and j the bias-corrected samples ``w_k = gyro_k - b_g`` and ``a_k = accel_k - b_a``
(body frame B, held constant over each step ``dt``) are collapsed into relative increments that do not
depend on the state at i (eqs. 35-37, iterative form eq. 49 / appendix A)::

    dR_{k+1} = dR_k Exp(w_k dt)
    dv_{k+1} = dv_k + dR_k a_k dt
    dp_{k+1} = dp_k + dv_k dt + 1/2 dR_k a_k dt^2

The error state ``[dtheta, dv, dp]`` (9,) with ``dR_true = dR Exp(dtheta)`` is propagated with the
linear recursion of eqs. 59-63 (``cov_{k+1} = A cov_k A^T + B cov_eta B^T``) where the discrete noise of the
Kalibr densities is ``density^2 / dt`` (white noise). Bias Jacobians follow appendix B (eq. 69-70), the
first-order bias update is eq. 44 and the prediction of the state at j is eq. 33 (with eq. 38's noise-free
form).
"""

from __future__ import annotations

import numpy as np
from viotb.vio.lie import exp_so3, right_jacobian_so3, skew
from viotb.vio.types import ImuNoise


def _as_vec3(value: np.ndarray, name: str) -> np.ndarray:
    """Return ``value`` as a finite float array of shape (3,), or raise a ValueError naming it."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


class ImuPreintegration:
    """Preintegrated IMU measurements between two keyframes (gtsam ``PreintegratedImuMeasurements`` shape).

    Args:
        gyro_bias_rad_s: Gyro bias linearization point, shape (3,), rad/s.
        accel_bias_m_s2: Accelerometer bias linearization point, shape (3,), m/s^2.
        noise: Continuous-time noise densities (Kalibr convention); only the white-noise densities enter the
            preintegrated covariance (bias random walk belongs to the bias factor).
    """

    def __init__(
        self, gyro_bias_rad_s: np.ndarray, accel_bias_m_s2: np.ndarray, noise: ImuNoise | None = None
    ) -> None:
        """Start an empty preintegration at the given bias linearization point."""
        self._bg = _as_vec3(gyro_bias_rad_s, "gyro_bias_rad_s")
        self._ba = _as_vec3(accel_bias_m_s2, "accel_bias_m_s2")
        self._noise = noise if noise is not None else ImuNoise()
        self._dR = np.eye(3)
        self._dv = np.zeros(3)
        self._dp = np.zeros(3)
        self._dt_s = 0.0
        self._cov = np.zeros((9, 9))
        self._dR_dbg = np.zeros((3, 3))
        self._dv_dbg = np.zeros((3, 3))
        self._dv_dba = np.zeros((3, 3))
        self._dp_dbg = np.zeros((3, 3))
        self._dp_dba = np.zeros((3, 3))

    def integrate(
        self, accel_B_m_s2: np.ndarray, gyro_B_rad_s: np.ndarray, dt_s: float, rotate_midpoint: bool = False
    ) -> None:
        """Add one IMU sample held constant for ``dt_s`` seconds.

        Args:
            accel_B_m_s2: Raw specific force in B (m/s^2), shape (3,).
            gyro_B_rad_s: Raw angular rate in B (rad/s), shape (3,).
            dt_s: Sample duration (s), > 0.
            rotate_midpoint: The reading is the interval's midpoint value: its bias-corrected specific force
                is turned by half the step's rotation before it is applied at the step's start attitude
                (otherwise a body-frame error of ``1/2 [w dt]x a`` per step; the window's batch form is
                :class:`viotb.vio.window_batch.BatchPreintegration` with the same flag).
        """
        accel = _as_vec3(accel_B_m_s2, "accel_B_m_s2")
        gyro = _as_vec3(gyro_B_rad_s, "gyro_B_rad_s")
        if not (np.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f"dt_s must be a positive finite number of seconds, got {dt_s}")
        a = accel - self._ba
        w_dt = (gyro - self._bg) * dt_s
        half, G_half = np.eye(3), np.zeros((3, 3))
        if rotate_midpoint:
            # The turned force moves with the step's rate: d(half a) / dw = -half [a]x Jr(w dt / 2) dt / 2.
            half = exp_so3(0.5 * w_dt)
            G_half = -half @ skew(a) @ right_jacobian_so3(0.5 * w_dt) * (0.5 * dt_s)
            a = half @ a
        dR_step = exp_so3(w_dt)
        jr_step = right_jacobian_so3(w_dt)
        dR_a_skew = self._dR @ skew(a)
        dt2 = dt_s * dt_s

        # 1. Covariance (Forster eqs. 59-63): A and B of the [dtheta, dv, dp] error recursion.
        A = np.eye(9)
        A[0:3, 0:3] = dR_step.T
        A[3:6, 0:3] = -dR_a_skew * dt_s
        A[6:9, 0:3] = -0.5 * dR_a_skew * dt2
        A[6:9, 3:6] = np.eye(3) * dt_s
        B_g = np.zeros((9, 3))
        B_g[0:3] = jr_step * dt_s
        B_a = np.zeros((9, 3))
        B_a[3:6] = self._dR * dt_s
        B_a[6:9] = 0.5 * self._dR * dt2
        var_g = self._noise.gyro_noise_density_rad_s_sqrthz**2 / dt_s
        var_a = self._noise.accel_noise_density_m_s2_sqrthz**2 / dt_s
        cov = A @ self._cov @ A.T + var_g * (B_g @ B_g.T) + var_a * (B_a @ B_a.T)
        self._cov = 0.5 * (cov + cov.T)

        # 2. Bias Jacobians (Forster appendix B, eqs. 69-70); position and velocity use the old dR, dR_dbg.
        #    The step's force in the start frame, dR a, moves with the rotation and (midpoint) the rate.
        dRa_dbg = -dR_a_skew @ self._dR_dbg - self._dR @ G_half
        dRa_dba = -self._dR @ half
        self._dp_dba += self._dv_dba * dt_s + 0.5 * dRa_dba * dt2
        self._dp_dbg += self._dv_dbg * dt_s + 0.5 * dRa_dbg * dt2
        self._dv_dba += dRa_dba * dt_s
        self._dv_dbg += dRa_dbg * dt_s
        self._dR_dbg = dR_step.T @ self._dR_dbg - jr_step * dt_s

        # 3. Increments (Forster eq. 49 / appendix A).
        self._dp = self._dp + self._dv * dt_s + 0.5 * self._dR @ a * dt2
        self._dv = self._dv + self._dR @ a * dt_s
        self._dR = self._dR @ dR_step
        self._dt_s += dt_s

    @property
    def gyro_bias_rad_s(self) -> np.ndarray:
        """Gyro bias linearization point (rad/s), shape (3,)."""
        return self._bg.copy()

    @property
    def accel_bias_m_s2(self) -> np.ndarray:
        """Accelerometer bias linearization point (m/s^2), shape (3,)."""
        return self._ba.copy()

    @property
    def delta_R(self) -> np.ndarray:
        """Preintegrated rotation ``R_BiBj`` at the bias linearization point, shape (3, 3)."""
        return self._dR.copy()

    @property
    def delta_v(self) -> np.ndarray:
        """Preintegrated velocity increment in frame B_i (m/s), shape (3,)."""
        return self._dv.copy()

    @property
    def delta_p(self) -> np.ndarray:
        """Preintegrated position increment in frame B_i (m), shape (3,)."""
        return self._dp.copy()

    @property
    def dt_s(self) -> float:
        """Total integrated time (s)."""
        return self._dt_s

    @property
    def cov(self) -> np.ndarray:
        """Covariance of the increments' error ``[dtheta, dv, dp]``, shape (9, 9), rad^2 / (m/s)^2 / m^2."""
        return self._cov.copy()

    @property
    def d_R_d_bg(self) -> np.ndarray:
        """``d Log(dR_bar^T dR(bg)) / d bg``, shape (3, 3) (right perturbation, eq. 44)."""
        return self._dR_dbg.copy()

    @property
    def d_v_d_bg(self) -> np.ndarray:
        """``d dv / d bg``, shape (3, 3)."""
        return self._dv_dbg.copy()

    @property
    def d_v_d_ba(self) -> np.ndarray:
        """``d dv / d ba``, shape (3, 3)."""
        return self._dv_dba.copy()

    @property
    def d_p_d_bg(self) -> np.ndarray:
        """``d dp / d bg``, shape (3, 3)."""
        return self._dp_dbg.copy()

    @property
    def d_p_d_ba(self) -> np.ndarray:
        """``d dp / d ba``, shape (3, 3)."""
        return self._dp_dba.copy()

    def corrected(
        self, gyro_bias_rad_s: np.ndarray, accel_bias_m_s2: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First-order bias-corrected increments (Forster eq. 44), without re-integration.

        Args:
            gyro_bias_rad_s: New gyro bias (rad/s), shape (3,).
            accel_bias_m_s2: New accelerometer bias (m/s^2), shape (3,).

        Returns:
            ``(delta_R (3, 3), delta_v (3,), delta_p (3,))`` at the new bias.
        """
        dbg = _as_vec3(gyro_bias_rad_s, "gyro_bias_rad_s") - self._bg
        dba = _as_vec3(accel_bias_m_s2, "accel_bias_m_s2") - self._ba
        delta_R = self._dR @ exp_so3(self._dR_dbg @ dbg)
        delta_v = self._dv + self._dv_dbg @ dbg + self._dv_dba @ dba
        delta_p = self._dp + self._dp_dbg @ dbg + self._dp_dba @ dba
        return delta_R, delta_v, delta_p

    def predict(
        self,
        R_WB_i: np.ndarray,
        p_WB_i: np.ndarray,
        v_WB_i: np.ndarray,
        gravity_W: np.ndarray,
        gyro_bias_rad_s: np.ndarray | None = None,
        accel_bias_m_s2: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predict the state at j from the state at i (Forster eq. 33; noise-free eq. 38).

        ``R_j = R_i dR``, ``v_j = v_i + g dt + R_i dv``, ``p_j = p_i + v_i dt + 1/2 g dt^2 + R_i dp``.

        Args:
            R_WB_i: Orientation at i, shape (3, 3).
            p_WB_i: Position at i (m), shape (3,).
            v_WB_i: Velocity at i in W (m/s), shape (3,).
            gravity_W: Gravity in W (m/s^2), shape (3,), e.g. ``gravity_W()``.
            gyro_bias_rad_s: Optional bias for the first-order correction (default: linearization point).
            accel_bias_m_s2: Optional bias for the first-order correction (default: linearization point).

        Returns:
            ``(R_WB_j (3, 3), p_WB_j (3,), v_WB_j (3,))``.
        """
        bg = self._bg if gyro_bias_rad_s is None else gyro_bias_rad_s
        ba = self._ba if accel_bias_m_s2 is None else accel_bias_m_s2
        delta_R, delta_v, delta_p = self.corrected(bg, ba)
        R_i = np.asarray(R_WB_i, dtype=float)
        if R_i.shape != (3, 3):
            raise ValueError(f"R_WB_i must have shape (3, 3), got {R_i.shape}")
        p_i = _as_vec3(p_WB_i, "p_WB_i")
        v_i = _as_vec3(v_WB_i, "v_WB_i")
        g = _as_vec3(gravity_W, "gravity_W")
        t = self._dt_s
        R_j = R_i @ delta_R
        v_j = v_i + g * t + R_i @ delta_v
        p_j = p_i + v_i * t + 0.5 * g * t * t + R_i @ delta_p
        return R_j, p_j, v_j
