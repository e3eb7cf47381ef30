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
    ) -> None:
        """Integrate the midpoints of consecutive readings (as :func:`window_factors.preintegrate`)."""
        super().__init__(gyro_bias_rad_s, accel_bias_m_s2, noise)
        dt = np.diff(np.asarray(t_s, dtype=float))
        keep = dt > 0.0
        dt = dt[keep]
        w = (0.5 * (gyro[1:] + gyro[:-1]))[keep] - self._bg
        a = (0.5 * (accel[1:] + accel[:-1]))[keep] - self._ba
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(a)) and np.all(np.isfinite(dt))):
            raise ValueError("BatchPreintegration: readings and times must be finite")
        n = len(dt)
        if n == 0:
            return
        # With rotate_midpoint the midpoint of two readings, the specific force at mid-step, is turned by
        # half the step's rotation into the step's start frame (VINS-Mono's midpoint integration rotates
        # each reading by its own attitude). Applied with the start rotation it leaves a body-frame error
        # of 1/2 [w dt]x a per step, a velocity drift of |w||a| dt / 2 per second (1.5 cm/s at 2 rad/s,
        # 3 m/s^2, 200 Hz; tests/test_window_batch.py).
        if rotate_midpoint:
            a = np.einsum("kij,kj->ki", exp_so3_batch(0.5 * w * dt[:, None]), a)
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
        dv_dbg = csum(-dRa_skew @ dR_dbg[:n] * dt3)
        dv_dba = csum(-dR[:n] * dt3)
        dp_dba = csum(dv_dba[:n] * dt3 - 0.5 * dR[:n] * dt3**2)
        dp_dbg = csum(dv_dbg[:n] * dt3 - 0.5 * dRa_skew @ dR_dbg[:n] * dt3**2)
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
        )


def imu_factors(
    s: ImuFactorStack, R: np.ndarray, rest: np.ndarray, jacobians: bool = True
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Residuals and Jacobians of the stacked IMU factors (:func:`window_factors.imu_factor`, batched).

    Args:
        s: The factors.
        R: Keyframe orientations ``R_WB``, shape (N, 3, 3).
        rest: Keyframe ``[p_WB, v_WB, b_g, b_a]``, shape (N, 12) (:func:`stack_values`).
        jacobians: Also the Jacobians (else None for both).

    Returns:
        ``(r (K, 15), J_i (K, 15, 15), J_j (K, 15, 15))``, not whitened.
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

    # 1. First-order bias correction (Forster eq. 44).
    phi_b = mv(dR_dbg, dbg)
    dRc = s.dR @ exp_so3_batch(phi_b)
    dvc = s.dv + mv(dv_dbg, dbg) + mv(dv_dba, dba)
    dpc = s.dp + mv(dp_dbg, dbg) + mv(dp_dba, dba)
    # 2. Residuals (Forster eq. 45).
    Ri_T = np.swapaxes(Ri, 1, 2)
    u_v = mv(Ri_T, vj - vi - g * dt)
    u_p = mv(Ri_T, pj - pi - vi * dt - 0.5 * g * dt * dt)
    r_R = log_so3_batch(np.swapaxes(dRc, 1, 2) @ Ri_T @ Rj)
    r = np.concatenate([r_R, u_v - dvc, u_p - dpc, bgj - bgi, baj - bai], axis=1)
    if not jacobians:
        return r, None, None
    # 3. Jacobians w.r.t. [dtheta, dp, dv, dbg, dba] of i and j.
    Jr_inv = right_jacobian_inv_batch(r_R)
    J_i = np.zeros((K, NX, NX))
    J_j = np.zeros((K, NX, NX))
    J_i[:, 0:3, 0:3] = -Jr_inv @ np.swapaxes(Rj, 1, 2) @ Ri
    J_j[:, 0:3, 0:3] = Jr_inv
    J_i[:, 0:3, 9:12] = -Jr_inv @ np.swapaxes(exp_so3_batch(r_R), 1, 2) @ right_jacobian_batch(phi_b) @ dR_dbg
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
    return r, J_i, J_j
