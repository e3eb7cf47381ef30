"""Factors of the sliding-window optimizer: the keyframe manifold, IMU preintegration factors, reprojection.

A keyframe's values ``x = [R_WB, p_WB, v_WB, b_g, b_a]`` (:class:`~viotb.vio.state.ImuValues`) live on a
manifold with the error state ``[dtheta, dp, dv, dbg, dba]`` (``NX = 15``; ``R = R_hat Exp(dtheta)``, the
:class:`~viotb.vio.types.StateEstimate` order): :func:`retract` and :func:`boxminus`. The IMU factor
between two keyframes is Forster et al.'s (TRO 2017, eqs. 44-45, with the bias random walk) on a
preintegration (:func:`preintegrate`), which also predicts a keyframe forward (:func:`predict`); the
reprojection factor projects landmarks in W into the camera of a keyframe (:func:`reprojection`). Every
factor returns analytic Jacobians.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.lie import exp_so3, log_so3, right_jacobian_inv_so3, right_jacobian_so3, skew
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.state import ImuValues
from viotb.vio.types import ImuNoise, StateEstimate, gravity_W
from viotb.vio.window_batch import BatchPreintegration
from viotb.vio.window_map import ImuLink

NX = 15
"""Error-state size of one keyframe ``[dtheta, dp, dv, dbg, dba]``."""


def retract(x: ImuValues, dx: np.ndarray) -> ImuValues:
    """``x [+] dx`` with ``dx = [dtheta, dp, dv, dbg, dba]`` (15,), ``R = R Exp(dtheta)``."""
    return ImuValues(
        x.R_WB @ exp_so3(dx[0:3]),
        x.p_WB + dx[3:6],
        x.v_WB + dx[6:9],
        x.gyro_bias_rad_s + dx[9:12],
        x.accel_bias_m_s2 + dx[12:15],
    )


def boxminus(x: ImuValues, x0: ImuValues) -> np.ndarray:
    """``x [-] x0`` (15,), the inverse of :func:`retract`."""
    return np.concatenate(
        [
            log_so3(x0.R_WB.T @ x.R_WB),
            x.p_WB - x0.p_WB,
            x.v_WB - x0.v_WB,
            x.gyro_bias_rad_s - x0.gyro_bias_rad_s,
            x.accel_bias_m_s2 - x0.accel_bias_m_s2,
        ]
    )


def preintegrate(
    t_s: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    x: ImuValues,
    noise: ImuNoise,
    rotate_midpoint: bool = False,
    intrinsics: tuple[np.ndarray, np.ndarray] | None = None,
) -> ImuPreintegration:
    """Preintegrate readings ``(t (n,), gyro (n, 3), accel (n, 3))`` at the biases of ``x`` (midpoints).

    All readings at once (:class:`viotb.vio.window_batch.BatchPreintegration`; the sample-by-sample
    :meth:`ImuPreintegration.integrate` gives the same to round-off); with ``intrinsics`` ``(T_g, T_a)``
    the readings are corrected by the IMU's matrices and their Jacobians kept.
    """
    bg, ba = x.gyro_bias_rad_s, x.accel_bias_m_s2
    return BatchPreintegration(t_s, gyro, accel, bg, ba, noise, rotate_midpoint, intrinsics)


def repropagate(
    links: list[ImuLink],
    xs: list[ImuValues],
    noise: ImuNoise,
    gyro_tol_rad_s: float,
    accel_tol_m_s2: float,
    rotate_midpoint: bool = False,
    intrinsics: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Re-integrate (in place) the links whose start keyframe's bias moved far from their linearization point.

    Link ``k`` (from keyframe ``xs[k]``) is re-integrated when its gyro bias moved more than
    ``gyro_tol_rad_s``
    or its accelerometer bias more than ``accel_tol_m_s2``; otherwise the first-order correction of Forster
    eq. 44 serves. A re-integrated link takes the current IMU correction matrices ``intrinsics``.
    """
    for link, xi in zip(links, xs, strict=False):
        if (
            np.linalg.norm(xi.gyro_bias_rad_s - link.pre.gyro_bias_rad_s) > gyro_tol_rad_s
            or np.linalg.norm(xi.accel_bias_m_s2 - link.pre.accel_bias_m_s2) > accel_tol_m_s2
        ):
            link.pre = preintegrate(*link.readings, xi, noise, rotate_midpoint, intrinsics)


def predict(pre: ImuPreintegration, x: ImuValues) -> ImuValues:
    """Values at the end of ``pre`` from ``x`` at its start (Forster eq. 33; biases held)."""
    R, p, v = pre.predict(x.R_WB, x.p_WB, x.v_WB, gravity_W())
    return ImuValues(R, p, v, x.gyro_bias_rad_s.copy(), x.accel_bias_m_s2.copy())


def predict_covariance(
    pre: ImuPreintegration, xi: ImuValues, xj: ImuValues, P_i: np.ndarray, noise: ImuNoise
) -> np.ndarray:
    """Covariance (NX, NX) of ``xj = predict(pre, xi)``: ``P_j = J_j^-1 (J_i P_i J_i^T + C) J_j^-T``.

    ``J_i, J_j, C`` are :func:`imu_factor`'s Jacobians and covariance; ``P_i`` is ``xi``'s, shape (NX, NX).
    """
    _, J_i, J_j, C = imu_factor(pre, xi, xj, noise)
    Jj_inv = np.linalg.inv(J_j)
    return Jj_inv @ (J_i @ P_i @ J_i.T + C) @ Jj_inv.T


def keyframe_estimate(
    x: ImuValues,
    P: np.ndarray,
    t_s: float,
    readings: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    noise: ImuNoise,
    rotate_midpoint: bool,
    gyro_B_rad_s: np.ndarray | None,
    intrinsics: tuple[np.ndarray, np.ndarray] | None = None,
) -> StateEstimate:
    """A keyframe's values ``x`` and covariance ``P`` (NX, NX) at ``t_s``, propagated through ``readings``.

    Forster eq. 33 and the factor's Jacobians (:func:`predict`, :func:`predict_covariance`) to the end of
    ``readings`` (``(t_s (n,), gyro (n, 3), accel (n, 3))`` from the keyframe on), or at ``t_s`` when None;
    the angular rate is ``gyro_B_rad_s`` (the newest reading) less the gyro bias (zero when None), both
    corrected by the IMU matrices ``intrinsics`` ``(T_g, T_a)`` when given.
    """
    if readings is not None:
        pre = preintegrate(*readings, x, noise, rotate_midpoint, intrinsics)
        xj = predict(pre, x)
        x, P, t_s = xj, predict_covariance(pre, x, xj, P, noise), readings[0][-1]
    omega = np.zeros(3)
    if gyro_B_rad_s is not None:
        omega = np.asarray(gyro_B_rad_s, dtype=float) - x.gyro_bias_rad_s
        omega = omega if intrinsics is None else intrinsics[0] @ omega
    return StateEstimate(
        t_s=t_s,
        R_WB=x.R_WB.copy(),
        p_WB=x.p_WB.copy(),
        v_WB=x.v_WB.copy(),
        gyro_bias_rad_s=x.gyro_bias_rad_s.copy(),
        accel_bias_m_s2=x.accel_bias_m_s2.copy(),
        omega_B_rad_s=omega,
        cov=0.5 * (P + P.T),
    )


def imu_factor(
    pre: ImuPreintegration, xi: ImuValues, xj: ImuValues, noise: ImuNoise
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IMU factor between keyframes i and j (Forster eq. 45 with the eq. 44 bias update; bias random walk).

    Residual ``[r_R, r_v, r_p, r_bg, r_ba]`` (15,)::

        r_R = Log((dR Exp(J_R^g dbg))^T R_i^T R_j)
        r_v = R_i^T (v_j - v_i - g dt) - dv(b_i)
        r_p = R_i^T (p_j - p_i - v_i dt - 1/2 g dt^2) - dp(b_i)
        r_b = b_j - b_i

    Returns:
        ``(r (15,), J_i (15, 15), J_j (15, 15), cov (15, 15))``: Jacobians w.r.t. the error states
        ``[dtheta, dp, dv, dbg, dba]`` of i and j, and the residual covariance (preintegration ``[dtheta, dv,
        dp]`` block, then the random walk ``density^2 dt``).
    """
    g = gravity_W()
    dt = pre.dt_s
    dbg = xi.gyro_bias_rad_s - pre.gyro_bias_rad_s
    dR, dv, dp = pre.corrected(xi.gyro_bias_rad_s, xi.accel_bias_m_s2)
    Ri_T = xi.R_WB.T
    u_v = Ri_T @ (xj.v_WB - xi.v_WB - g * dt)
    u_p = Ri_T @ (xj.p_WB - xi.p_WB - xi.v_WB * dt - 0.5 * g * dt * dt)
    r_R = log_so3(dR.T @ Ri_T @ xj.R_WB)
    r = np.concatenate(
        [
            r_R,
            u_v - dv,
            u_p - dp,
            xj.gyro_bias_rad_s - xi.gyro_bias_rad_s,
            xj.accel_bias_m_s2 - xi.accel_bias_m_s2,
        ]
    )
    Jr_inv = right_jacobian_inv_so3(r_R)
    J_i = np.zeros((NX, NX))
    J_j = np.zeros((NX, NX))
    # rotation rows
    J_i[0:3, 0:3] = -Jr_inv @ xj.R_WB.T @ xi.R_WB
    J_j[0:3, 0:3] = Jr_inv
    J_i[0:3, 9:12] = -Jr_inv @ exp_so3(r_R).T @ right_jacobian_so3(pre.d_R_d_bg @ dbg) @ pre.d_R_d_bg
    # velocity rows
    J_i[3:6, 0:3] = skew(u_v)
    J_i[3:6, 6:9] = -Ri_T
    J_j[3:6, 6:9] = Ri_T
    J_i[3:6, 9:12] = -pre.d_v_d_bg
    J_i[3:6, 12:15] = -pre.d_v_d_ba
    # position rows
    J_i[6:9, 0:3] = skew(u_p)
    J_i[6:9, 3:6] = -Ri_T
    J_j[6:9, 3:6] = Ri_T
    J_i[6:9, 6:9] = -Ri_T * dt
    J_i[6:9, 9:12] = -pre.d_p_d_bg
    J_i[6:9, 12:15] = -pre.d_p_d_ba
    # bias random walk rows
    J_i[9:15, 9:15] = -np.eye(6)
    J_j[9:15, 9:15] = np.eye(6)
    cov = np.zeros((NX, NX))
    cov[0:9, 0:9] = pre.cov
    cov[9:12, 9:12] = np.eye(3) * noise.gyro_random_walk_rad_s2_sqrthz**2 * dt
    cov[12:15, 12:15] = np.eye(3) * noise.accel_random_walk_m_s3_sqrthz**2 * dt
    return r, J_i, J_j, cov


def project(
    R_WB: np.ndarray, p_WB: np.ndarray, p_W: np.ndarray, R_BC: np.ndarray, p_BC: np.ndarray
) -> np.ndarray:
    """Normalized projections ``z (M, 2)`` of :func:`reprojection` without the Jacobians (same arguments)."""
    p_C = (np.einsum("mji,mj->mi", R_WB, p_W - p_WB) - p_BC) @ R_BC
    Z = p_C[:, 2]
    return p_C[:, :2] / np.where(np.abs(Z) < 1e-9, 1e-9, Z)[:, None]


def seen_behind(
    xs: list[ImuValues],
    pts: np.ndarray,
    cams: list[tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray, np.ndarray]],
    min_depth_m: float,
) -> np.ndarray:
    """Landmarks that some observation sees closer than ``min_depth_m`` (or behind the camera), (L,) bool.

    Args:
        xs: Keyframe values (N).
        pts: Landmarks in W (m), shape (L, 3).
        cams: Per camera ``(observations (kf index (M,), landmark index (M,), xy (M, 2)), R_BC, p_BC)``.
        min_depth_m: Smallest depth along the optical axis (m).
    """
    bad = np.zeros(len(pts), dtype=bool)
    R_WB = np.stack([x.R_WB for x in xs])
    p_WB = np.stack([x.p_WB for x in xs])
    for (kf_i, lm_i, _), R_BC, p_BC in cams:
        q = np.einsum("mji,mj->mi", R_WB[kf_i], pts[lm_i] - p_WB[kf_i])
        depth = ((q - p_BC) @ R_BC)[:, 2]
        bad[lm_i[depth < min_depth_m]] = True
    return bad


def reprojection(
    R_WB: np.ndarray, p_WB: np.ndarray, p_W: np.ndarray, R_BC: np.ndarray, p_BC: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normalized projections of M points with Jacobians (right perturbation on ``R_WB``).

    ``p_C = R_BC^T (R_WB^T (p_W - p_WB) - p_BC)``, ``z = p_C[:2] / p_C[2]``.

    Args:
        R_WB: Keyframe orientations, shape (M, 3, 3).
        p_WB: Keyframe positions (m), shape (M, 3).
        p_W: Landmarks (m), shape (M, 3).
        R_BC: Camera-to-body rotation, shape (3, 3).
        p_BC: Camera origin in B (m), shape (3,).

    Returns:
        ``(z (M, 2), depth_m (M,), J_pose (M, 2, 6) w.r.t. [dtheta, dp], J_point (M, 2, 3))``.
    """
    q = np.einsum("mji,mj->mi", R_WB, p_W - p_WB)
    p_C = (q - p_BC) @ R_BC
    Z = p_C[:, 2]
    Zs = np.where(np.abs(Z) < 1e-9, 1e-9, Z)
    z = p_C[:, :2] / Zs[:, None]
    dz = np.zeros((len(q), 2, 3))
    dz[:, 0, 0] = 1.0 / Zs
    dz[:, 1, 1] = 1.0 / Zs
    dz[:, :, 2] = -z / Zs[:, None]
    A = dz @ R_BC.T  # d z / d q
    sq = np.zeros((len(q), 3, 3))
    sq[:, 0, 1], sq[:, 0, 2], sq[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    sq[:, 1, 0], sq[:, 2, 0], sq[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    J_point = A @ np.swapaxes(R_WB, 1, 2)
    J_pose = np.concatenate([A @ sq, -J_point], axis=2)
    return z, Z, J_pose, J_point
