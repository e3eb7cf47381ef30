"""Vectorized factors of the sliding-window optimizer: SO(3) maps, IMU factors and prior residuals in batches.

:func:`viotb.vio.window_factors.imu_factor` evaluates one IMU factor with a few dozen 3x3 NumPy calls; a
window linearizes ``N - 1`` of them in every Levenberg-Marquardt trial, and those small calls dominated the
solve (profile of the 10 s simulated circle: 42 % of ``linearize``). Here the same equations (Forster et al.,
TRO 2017, eqs. 44-45 with the bias random walk) run on stacked arrays, one NumPy call per step for every
factor at once; :class:`ImuFactorStack` also keeps each factor's square-root information, which depends only
on the preintegration, so it is factored once per solve instead of once per trial. The SO(3) maps are those of
:mod:`viotb.vio.lie` (Rodrigues, the logarithm, the right Jacobian and its inverse, Forster eqs. 3-9) on
arrays of shape (K, 3) / (K, 3, 3); tests compare every function with its one-at-a-time twin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.vio.imu_intrinsics import input_jacobian
from viotb.vio.lie import log_so3, skew_batch
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.state import ImuValues
from viotb.vio.types import ImuNoise, gravity_W

NX = 15
"""Error-state size of one keyframe ``[dtheta, dp, dv, dbg, dba]`` (as :data:`window_factors.NX`)."""


def _series(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(angle (K,), skew (K, 3, 3), skew^2 (K, 3, 3))`` of K rotation vectors."""
    angle = np.linalg.norm(phi, axis=1)
    k = skew_batch(phi)
    return angle, k, k @ k


def exp_so3_batch(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for K rotation vectors (rad), (K, 3) -> (K, 3, 3) (as :func:`lie.exp_so3`)."""
    angle, k, k2 = _series(phi)
    small = angle < 1e-8
    a = np.where(small, 1.0, angle)
    c1 = np.where(small, 1.0, np.sin(a) / a)
    c2 = np.where(small, 0.5, (1.0 - np.cos(a)) / a**2)
    return np.eye(3) + c1[:, None, None] * k + c2[:, None, None] * k2


def log_so3_batch(R: np.ndarray) -> np.ndarray:
    """Logarithm of K rotations, (K, 3, 3) -> (K, 3), angle in [0, pi] (as :func:`lie.log_so3`).

    Rotations within 1e-4 rad of pi take :func:`lie.log_so3`'s axis-from-symmetric-part branch one by one.
    """
    A = 0.5 * (R - np.swapaxes(R, 1, 2))
    sin_axis = (
        np.stack([A[:, 2, 1] - A[:, 1, 2], A[:, 0, 2] - A[:, 2, 0], A[:, 1, 0] - A[:, 0, 1]], axis=1) * 0.5
    )
    cos_angle = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) * 0.5, -1.0, 1.0)
    angle = np.arctan2(np.linalg.norm(sin_axis, axis=1), cos_angle)
    small = angle < 1e-6
    scale = np.where(small, 1.0 + angle**2 / 6.0, angle / np.where(small, 1.0, np.sin(angle)))
    out = sin_axis * scale[:, None]
    for i in np.nonzero(np.pi - angle < 1e-4)[0]:
        out[i] = log_so3(R[i])
    return out


def right_jacobian_batch(phi: np.ndarray) -> np.ndarray:
    """Right Jacobians ``Jr(phi)`` of K rotation vectors, (K, 3) -> (K, 3, 3) (Forster eq. 8)."""
    angle, k, k2 = _series(phi)
    small = angle < 1e-6
    a = np.where(small, 1.0, angle)
    c1 = np.where(small, 0.5, (1.0 - np.cos(a)) / a**2)
    c2 = np.where(small, 1.0 / 6.0, (a - np.sin(a)) / a**3)
    return np.eye(3) - c1[:, None, None] * k + c2[:, None, None] * k2


def right_jacobian_inv_batch(phi: np.ndarray) -> np.ndarray:
    """Inverse right Jacobians of K rotation vectors, (K, 3) -> (K, 3, 3) (Forster eq. 9)."""
    angle, k, k2 = _series(phi)
    small = angle < 1e-6
    a = np.where(small, 1.0, angle)
    c2 = np.where(small, 1.0 / 12.0, 1.0 / a**2 - (1.0 + np.cos(a)) / (2.0 * a * np.sin(a)))
    return np.eye(3) + 0.5 * k + c2[:, None, None] * k2


def integrate_gyro(t_s: np.ndarray, gyro: np.ndarray, gyro_bias_rad_s: np.ndarray) -> np.ndarray:
    """Rotation ``R_B0Bn`` (3, 3) over readings ``t (n,) s, gyro (n, 3) rad/s`` less a bias (midpoints)."""
    steps = exp_so3_batch((0.5 * (gyro[1:] + gyro[:-1]) - gyro_bias_rad_s) * np.diff(t_s)[:, None])
    R = np.eye(3)
    for step in steps:
        R = R @ step
    return R


def retract_batch(xs: list[ImuValues], dx: np.ndarray) -> list[ImuValues]:
    """``x_k [+] dx_k`` of N keyframes at once, ``dx`` stacked ``[dtheta, dp, dv, dbg, dba]`` (15 N,).

    As :func:`window_factors.retract` one by one (``R = R Exp(dtheta)``).
    """
    d = np.asarray(dx, dtype=float).reshape(len(xs), NX)
    R, rest = stack_values(xs)
    R_new = R @ exp_so3_batch(d[:, 0:3])
    rest_new = rest + d[:, 3:]
    return [ImuValues(R_new[k], *(rest_new[k, 3 * c : 3 * c + 3] for c in range(4))) for k in range(len(xs))]


class BatchPreintegration(ImuPreintegration):
    """An :class:`ImuPreintegration` of many readings at once (same increments, Jacobians and covariance).

    The sample-by-sample recursion (Forster et al. eqs. 35-37, 59-63 and appendix B) is a few dozen 3x3
    NumPy calls per reading, the larger part of a keyframe's preintegration time; here only the rotation
    product runs per reading and the rest are cumulative sums of its closed form. With ``dR_k, dv_k, dp_k``
    the increments after ``k`` readings, ``a_k, w_k`` the bias-corrected readings and ``T_k`` the
    integrated time::

        dR_dbg_k = -dR_k^T sum_{i<k} dR_{i+1} Jr(w_i dt_i) dt_i
        dv_dbg_{k+1} = dv_dbg_k - dR_k [a_k]x dR_dbg_k dt_k    (cumulative sums, as dv_dba, dp_dba, dp_dbg)
        cov_n = sum_k Phi(n, k+1) B_k diag(var_g, var_a) B_k^T Phi(n, k+1)^T

    where ``Phi(n, m)``, the product of the recursion's transition matrices from reading ``m`` to ``n``, is
    ``[[dR_n^T dR_m, 0, 0], [-[dv_n - dv_m]x dR_m, I, 0], [-[dp_n - dp_m - dv_m (T_n - T_m)]x dR_m,
    (T_n - T_m) I, I]]`` and ``B_k`` the recursion's noise input. Later :meth:`integrate` calls continue it.

    Args:
        t_s: Reading times (s), shape (n,); readings with no time step are skipped.
        gyro: Angular rates in B (rad/s), shape (n, 3).
        accel: Specific forces in B (m/s^2), shape (n, 3).
        gyro_bias_rad_s: Gyro bias linearization point (rad/s), shape (3,).
        accel_bias_m_s2: Accelerometer bias linearization point (m/s^2), shape (3,).
        noise: Noise densities.
        rotate_midpoint: Turn each midpoint specific force by half its step's rotation before applying it
            at the step's start attitude (``WindowParams.midpoint_rotation``).
        intrinsics: ``(T_g, T_a)``, each (3, 3): integrate the corrected readings ``T_g (w_m - b_g)``,
            ``T_a (a_m - b_a)`` (:mod:`viotb.vio.imu_intrinsics`) and keep the first-order Jacobians of the
            increments w.r.t. both matrices (:attr:`J_intrinsics`); None: the plain readings.

    Attributes:
        intrinsics0: ``[vec(T_g), vec(T_a)]`` (18,) the readings were corrected with, or None.
        J_intrinsics: ``[dR/dT_g, dv/dT_g, dv/dT_a, dp/dT_g, dp/dT_a]`` (5, 3, 9) w.r.t. the row-major
            entries (the rotation's as a right perturbation, like ``d_R_d_bg``), or None.
    """

    def __init__(
        self,
        t_s: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        gyro_bias_rad_s: np.ndarray,
        accel_bias_m_s2: np.ndarray,
        noise: ImuNoise,
        rotate_midpoint: bool = False,
        intrinsics: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """Integrate the midpoints of consecutive readings (as :func:`window_factors.preintegrate`)."""
        super().__init__(gyro_bias_rad_s, accel_bias_m_s2, noise)
        self.intrinsics0: np.ndarray | None = None
        self.J_intrinsics: np.ndarray | None = None
        dt = np.diff(np.asarray(t_s, dtype=float))
        keep = dt > 0.0
        dt = dt[keep]
        u_g = (0.5 * (gyro[1:] + gyro[:-1]))[keep] - self._bg
        u_a = (0.5 * (accel[1:] + accel[:-1]))[keep] - self._ba
        if not (np.all(np.isfinite(u_g)) and np.all(np.isfinite(u_a)) and np.all(np.isfinite(dt))):
            raise ValueError("BatchPreintegration: readings and times must be finite")
        T_g, T_a = (np.eye(3), np.eye(3)) if intrinsics is None else intrinsics
        w, a = (u_g, u_a) if intrinsics is None else (u_g @ T_g.T, u_a @ T_a.T)
        if intrinsics is not None:
            self.intrinsics0 = np.concatenate([T_g.ravel(), T_a.ravel()])
            self.J_intrinsics = np.zeros((5, 3, 9))
        n = len(dt)
        if n == 0:
            return
        # With rotate_midpoint the midpoint of two readings, the specific force at mid-step, is turned by
        # half the step's rotation into the step's start frame (VINS-Mono's midpoint integration rotates
        # each reading by its own attitude). Applied with the start rotation it leaves a body-frame error
        # of 1/2 [w dt]x a per step, a velocity drift of |w||a| dt / 2 per second (1.5 cm/s at 2 rad/s,
        # 3 m/s^2, 200 Hz; tests/test_window_batch.py).
        half = G_half = None
        if rotate_midpoint:
            half = exp_so3_batch(0.5 * w * dt[:, None])
            # The turned force moves with the step's rate: d(half a) / dw = -half [a]x Jr(w dt / 2) dt / 2.
            G_half = (
                -half
                @ skew_batch(a)
                @ right_jacobian_batch(0.5 * w * dt[:, None])
                * (0.5 * dt)[:, None, None]
            )
            a = np.einsum("kij,kj->ki", half, a)
        # 1. Rotations dR_0..dR_n (the only per-reading loop), increments by cumulative sums.
        steps = exp_so3_batch(w * dt[:, None])
        Jr_dt = right_jacobian_batch(w * dt[:, None]) * dt[:, None, None]
        dR = np.empty((n + 1, 3, 3))
        dR[0] = np.eye(3)
        for k in range(n):
            dR[k + 1] = dR[k] @ steps[k]
        dRa_dt = np.einsum("kij,kj->ki", dR[:n], a) * dt[:, None]
        dv = np.concatenate([np.zeros((1, 3)), np.cumsum(dRa_dt, axis=0)])
        dp = np.concatenate(
            [np.zeros((1, 3)), np.cumsum(dv[:n] * dt[:, None] + 0.5 * dRa_dt * dt[:, None], 0)]
        )
        T = np.concatenate([[0.0], np.cumsum(dt)])

        def csum(x: np.ndarray) -> np.ndarray:
            return np.concatenate([np.zeros((1, 3, 3)), np.cumsum(x, axis=0)])

        # 2. Bias Jacobians (Forster appendix B) after each reading.
        dR_dbg = -np.swapaxes(dR, 1, 2) @ csum(dR[1:] @ Jr_dt)
        dt3 = dt[:, None, None]
        dRa_skew = dR[:n] @ skew_batch(a)
        # Each step's force in the start frame: dR_k a_k, perturbed by the rotation and (midpoint) the rate.
        dRa_dbg = -dRa_skew @ dR_dbg[:n] - (0.0 if G_half is None else dR[:n] @ G_half)
        dRa_dba = -dR[:n] if half is None else -dR[:n] @ half
        dv_dbg = csum(dRa_dbg * dt3)
        dv_dba = csum(dRa_dba * dt3)
        dp_dba = csum(dv_dba[:n] * dt3 + 0.5 * dRa_dba * dt3**2)
        dp_dbg = csum(dv_dbg[:n] * dt3 + 0.5 * dRa_dbg * dt3**2)
        # 3. Covariance: each reading's noise carried to the end by Phi(n, k + 1).
        R1 = dR[1:]
        sg = noise.gyro_noise_density_rad_s_sqrthz / np.sqrt(dt)[:, None, None]
        sa = noise.accel_noise_density_m_s2_sqrthz / np.sqrt(dt)[:, None, None]
        G_g = R1 @ Jr_dt * sg  # the rotation error this reading's gyro noise leaves at reading k + 1
        G = np.zeros((n, 9, 6))
        G[:, 0:3, 0:3] = dR[n].T @ G_g
        G[:, 3:6, 0:3] = -skew_batch(dv[n] - dv[1:]) @ G_g
        G[:, 6:9, 0:3] = -skew_batch(dp[n] - dp[1:] - dv[1:] * (T[n] - T[1:])[:, None]) @ G_g
        G[:, 3:6, 3:6] = dR[:n] * dt3 * sa
        G[:, 6:9, 3:6] = dR[:n] * ((T[n] - T[1:])[:, None, None] * dt3 + 0.5 * dt3**2) * sa
        cov = np.einsum("kia,kja->ij", G, G)
        self._cov = 0.5 * (cov + cov.T)
        self._dR, self._dv, self._dp, self._dt_s = dR[n], dv[n], dp[n], float(T[n])
        self._dR_dbg, self._dv_dbg, self._dv_dba = dR_dbg[n], dv_dbg[n], dv_dba[n]
        self._dp_dbg, self._dp_dba = dp_dbg[n], dp_dba[n]
        if intrinsics is not None:
            # A bias moves the corrected reading by -T db: the bias Jacobians above are w.r.t. the reading.
            self._dR_dbg, self._dv_dbg, self._dp_dbg = (J @ T_g for J in (dR_dbg[n], dv_dbg[n], dp_dbg[n]))
            self._dv_dba, self._dp_dba = dv_dba[n] @ T_a, dp_dba[n] @ T_a
            self.J_intrinsics = _intrinsics_jacobians(dR, Jr_dt, dRa_skew, dt, u_g, u_a, half, G_half)

    def integrate(
        self, accel_B_m_s2: np.ndarray, gyro_B_rad_s: np.ndarray, dt_s: float, rotate_midpoint: bool = False
    ) -> None:
        """Continue with one more sample (:meth:`ImuPreintegration.integrate`); not with intrinsics."""
        if self.J_intrinsics is not None:
            raise ValueError("BatchPreintegration: a preintegration with intrinsics cannot be continued")
        super().integrate(accel_B_m_s2, gyro_B_rad_s, dt_s, rotate_midpoint)


def _intrinsics_jacobians(
    dR: np.ndarray,
    Jr_dt: np.ndarray,
    dRa_skew: np.ndarray,
    dt: np.ndarray,
    u_g: np.ndarray,
    u_a: np.ndarray,
    half: np.ndarray | None,
    G_half: np.ndarray | None,
) -> np.ndarray:
    """First-order Jacobians of the increments w.r.t. the correction matrices, shape (5, 3, 9).

    A change ``dT_g`` moves reading ``k``'s corrected rate by ``dw_k = U_k vec(dT_g)``, ``U_k = kron(I_3,
    u_k^T)`` (``u_k = w_m,k - b_g``; :func:`viotb.vio.imu_intrinsics.input_jacobian`): the bias Jacobians'
    recursion (Forster appendix B) with a per-reading input ``U_k`` in place of the bias's constant ``-I``.
    Where the readings were turned by the step's half rotation (``rotate_midpoint``), the accelerometer's
    ``U_k`` is turned too, and the rate's change turns the force by ``G_half U_k``.

    Args:
        dR: Rotations ``dR_0..dR_n``, shape (n + 1, 3, 3).
        Jr_dt: ``Jr(w_k dt_k) dt_k``, shape (n, 3, 3).
        dRa_skew: ``dR_k [a_k]x``, shape (n, 3, 3).
        dt: Step lengths (s), shape (n,).
        u_g: Unbiased gyro readings (rad/s), shape (n, 3).
        u_a: Unbiased accelerometer readings (m/s^2), shape (n, 3).
        half: The half-step rotations, shape (n, 3, 3), or None.
        G_half: The turned force's Jacobian w.r.t. the step's rate, shape (n, 3, 3), or None.
    """
    n, dt3 = len(dt), dt[:, None, None]
    U_g, U_a = input_jacobian(u_g), input_jacobian(u_a)
    if half is not None:
        U_a = half @ U_a

    def csum(x: np.ndarray) -> np.ndarray:
        return np.concatenate([np.zeros((1, 3, 9)), np.cumsum(x, axis=0)])

    dR_dT = np.swapaxes(dR, 1, 2) @ csum(dR[1:] @ Jr_dt @ U_g)
    dRa_dT = -dRa_skew @ dR_dT[:n] + (0.0 if G_half is None else dR[:n] @ G_half @ U_g)
    dv_dT = csum(dRa_dT * dt3)
    dp_dT = csum(dv_dT[:n] * dt3 + 0.5 * dRa_dT * dt3**2)
    dRU = dR[:n] @ U_a
    dv_dTa = csum(dRU * dt3)
    dp_dTa = csum(dv_dTa[:n] * dt3 + 0.5 * dRU * dt3**2)
    return np.stack([dR_dT[n], dv_dT[n], dv_dTa[n], dp_dT[n], dp_dTa[n]])


def stack_values(xs: list[ImuValues]) -> tuple[np.ndarray, np.ndarray]:
    """``(R_WB (N, 3, 3), [p_WB, v_WB, b_g, b_a] (N, 12))`` of N keyframe values."""
    R = np.stack([x.R_WB for x in xs])
    rest = np.stack([np.concatenate([x.p_WB, x.v_WB, x.gyro_bias_rad_s, x.accel_bias_m_s2]) for x in xs])
    return R, rest


def boxminus_batch(R: np.ndarray, rest: np.ndarray, R0: np.ndarray, rest0: np.ndarray) -> np.ndarray:
    """``x [-] x0`` of K stacked values (:func:`stack_values`), shape (K, 15) (as :func:`boxminus`)."""
    return np.concatenate([log_so3_batch(np.swapaxes(R0, 1, 2) @ R), rest - rest0], axis=1)


@dataclass(frozen=True)
class ImuFactorStack:
    """K IMU factors between keyframes ``k`` and ``k + 1``: their preintegrations stacked.

    Attributes:
        k: Window index of each factor's first keyframe, shape (K,).
        dt_s: Integrated time (s), shape (K,).
        bg0: Gyro-bias linearization point (rad/s), shape (K, 3).
        ba0: Accelerometer-bias linearization point (m/s^2), shape (K, 3).
        dR: Preintegrated rotation, shape (K, 3, 3).
        dv: Preintegrated velocity (m/s), shape (K, 3).
        dp: Preintegrated position (m), shape (K, 3).
        J_bias: ``[dR/dbg, dv/dbg, dv/dba, dp/dbg, dp/dba]``, shape (5, K, 3, 3).
        sqrt_info: Upper factor ``W`` with ``W^T W = C^-1`` of each residual covariance, shape (K, 15, 15).
        intrinsics0: The IMU correction matrices ``[vec(T_g), vec(T_a)]`` each was integrated with, shape
            (K, 18), or None (plain readings).
        J_intrinsics: ``[dR/dT_g, dv/dT_g, dv/dT_a, dp/dT_g, dp/dT_a]``, shape (5, K, 3, 9), or None.
    """

    k: np.ndarray
    dt_s: np.ndarray
    bg0: np.ndarray
    ba0: np.ndarray
    dR: np.ndarray
    dv: np.ndarray
    dp: np.ndarray
    J_bias: np.ndarray
    sqrt_info: np.ndarray
    intrinsics0: np.ndarray | None = None
    J_intrinsics: np.ndarray | None = None

    @classmethod
    def build(cls, imu: list[tuple[int, ImuPreintegration]], noise: ImuNoise) -> ImuFactorStack:
        """Stack ``(k, preintegration)`` factors; the covariance is :func:`imu_factor`'s (random walk too)."""
        K = len(imu)
        dt = np.array([pre.dt_s for _, pre in imu], dtype=float)
        C = np.zeros((K, NX, NX))
        for i, (_, pre) in enumerate(imu):
            C[i, 0:9, 0:9] = pre.cov
        C[:, 9:12, 9:12] = np.eye(3) * (noise.gyro_random_walk_rad_s2_sqrthz**2 * dt)[:, None, None]
        C[:, 12:15, 12:15] = np.eye(3) * (noise.accel_random_walk_m_s3_sqrthz**2 * dt)[:, None, None]
        sqrt_info = np.swapaxes(np.linalg.cholesky(np.linalg.inv(C)), 1, 2) if K else C

        def st(attr: str) -> np.ndarray:
            return np.array([getattr(pre, attr) for _, pre in imu], dtype=float).reshape(K, 3)

        J_bias = np.array(
            [
                [getattr(pre, a) for _, pre in imu]
                for a in ("d_R_d_bg", "d_v_d_bg", "d_v_d_ba", "d_p_d_bg", "d_p_d_ba")
            ],
            dtype=float,
        ).reshape(5, K, 3, 3)
        dR = np.array([pre.delta_R for _, pre in imu], dtype=float).reshape(K, 3, 3)
        intr = [getattr(pre, "J_intrinsics", None) for _, pre in imu]
        T0 = J_T = None
        if K and all(J is not None for J in intr):
            T0 = np.array([pre.intrinsics0 for _, pre in imu], dtype=float)
            J_T = np.swapaxes(np.array(intr, dtype=float), 0, 1)
        return cls(
            np.array([k for k, _ in imu], dtype=np.int64),
            dt,
            st("gyro_bias_rad_s"),
            st("accel_bias_m_s2"),
            dR,
            st("delta_v"),
            st("delta_p"),
            J_bias,
            sqrt_info,
            T0,
            J_T,
        )


def imu_factors(
    s: ImuFactorStack,
    R: np.ndarray,
    rest: np.ndarray,
    jacobians: bool = True,
    intrinsics: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Residuals and Jacobians of the stacked IMU factors (:func:`window_factors.imu_factor`, batched).

    With ``intrinsics`` the increments are also corrected to first order for the change of the IMU's
    correction matrices since their integration (as eq. 44 does for the biases; :class:`BatchPreintegration`
    holds the Jacobians).

    Args:
        s: The factors.
        R: Keyframe orientations ``R_WB``, shape (N, 3, 3).
        rest: Keyframe ``[p_WB, v_WB, b_g, b_a]``, shape (N, 12) (:func:`stack_values`).
        jacobians: Also the Jacobians (else None for all three).
        intrinsics: Current ``[vec(T_g), vec(T_a)]`` (18,), or None (no intrinsics correction).

    Returns:
        ``(r (K, 15), J_i (K, 15, 15), J_j (K, 15, 15), J_T (K, 15, 18))``, not whitened; ``J_T`` (w.r.t.
        the correction matrices' entries) is None without ``intrinsics``.

    Raises:
        ValueError: ``intrinsics`` for factors integrated without them.
    """
    K = len(s.k)
    g = gravity_W()
    dt = s.dt_s[:, None]
    Ri, Rj = R[s.k], R[s.k + 1]
    pi, vi, bgi, bai = (rest[s.k, 3 * c : 3 * c + 3] for c in range(4))
    pj, vj, bgj, baj = (rest[s.k + 1, 3 * c : 3 * c + 3] for c in range(4))
    dR_dbg, dv_dbg, dv_dba, dp_dbg, dp_dba = s.J_bias
    dbg, dba = bgi - s.bg0, bai - s.ba0

    def mv(M: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.einsum("kij,kj->ki", M, v)

    # 1. First-order bias correction (Forster eq. 44), and of the correction matrices.
    phi_b = mv(dR_dbg, dbg)
    dvc = s.dv + mv(dv_dbg, dbg) + mv(dv_dba, dba)
    dpc = s.dp + mv(dp_dbg, dbg) + mv(dp_dba, dba)
    if intrinsics is not None:
        if s.J_intrinsics is None or s.intrinsics0 is None:
            raise ValueError("imu_factors: intrinsics given for factors integrated without them")
        dT = np.asarray(intrinsics, dtype=float)[None, :] - s.intrinsics0
        dR_dTg, dv_dTg, dv_dTa, dp_dTg, dp_dTa = s.J_intrinsics
        phi_b = phi_b + mv(dR_dTg, dT[:, :9])
        dvc = dvc + mv(dv_dTg, dT[:, :9]) + mv(dv_dTa, dT[:, 9:])
        dpc = dpc + mv(dp_dTg, dT[:, :9]) + mv(dp_dTa, dT[:, 9:])
    dRc = s.dR @ exp_so3_batch(phi_b)
    # 2. Residuals (Forster eq. 45).
    Ri_T = np.swapaxes(Ri, 1, 2)
    u_v = mv(Ri_T, vj - vi - g * dt)
    u_p = mv(Ri_T, pj - pi - vi * dt - 0.5 * g * dt * dt)
    r_R = log_so3_batch(np.swapaxes(dRc, 1, 2) @ Ri_T @ Rj)
    r = np.concatenate([r_R, u_v - dvc, u_p - dpc, bgj - bgi, baj - bai], axis=1)
    if not jacobians:
        return r, None, None, None
    # 3. Jacobians w.r.t. [dtheta, dp, dv, dbg, dba] of i and j.
    Jr_inv = right_jacobian_inv_batch(r_R)
    J_i = np.zeros((K, NX, NX))
    J_j = np.zeros((K, NX, NX))
    J_i[:, 0:3, 0:3] = -Jr_inv @ np.swapaxes(Rj, 1, 2) @ Ri
    J_j[:, 0:3, 0:3] = Jr_inv
    rot_b = -Jr_inv @ np.swapaxes(exp_so3_batch(r_R), 1, 2) @ right_jacobian_batch(phi_b)
    J_i[:, 0:3, 9:12] = rot_b @ dR_dbg
    J_i[:, 3:6, 0:3] = skew_batch(u_v)
    J_i[:, 3:6, 6:9] = -Ri_T
    J_j[:, 3:6, 6:9] = Ri_T
    J_i[:, 3:6, 9:12] = -dv_dbg
    J_i[:, 3:6, 12:15] = -dv_dba
    J_i[:, 6:9, 0:3] = skew_batch(u_p)
    J_i[:, 6:9, 3:6] = -Ri_T
    J_j[:, 6:9, 3:6] = Ri_T
    J_i[:, 6:9, 6:9] = -Ri_T * dt[:, :, None]
    J_i[:, 6:9, 9:12] = -dp_dbg
    J_i[:, 6:9, 12:15] = -dp_dba
    J_i[:, 9:15, 9:15] = -np.eye(6)
    J_j[:, 9:15, 9:15] = np.eye(6)
    J_T = None
    if intrinsics is not None:
        J_T = np.zeros((K, NX, 18))
        J_T[:, 0:3, :9] = rot_b @ dR_dTg
        J_T[:, 3:6, :9], J_T[:, 3:6, 9:] = -dv_dTg, -dv_dTa
        J_T[:, 6:9, :9], J_T[:, 6:9, 9:] = -dp_dTg, -dp_dTa
    return r, J_i, J_j, J_T
